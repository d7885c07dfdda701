"""The frame-adaptive (spread-normalised) conformal interval of the smoothed regressor holds the
true stiffness as often as it promises, under a worst-case shift within eps, and is narrower
than the constant-beta interval where the noisy outputs are tight (issue 10, item 2)."""

import numpy as np
import torch

from drake_cert.certification.intervals import runtime_interval
from drake_cert.certification.regressor import (
    MedianSmoothedRegressor,
    calibrate_conformal,
    calibrate_normalized,
    spread_lower_bound,
    spread_upper_bound,
)
from drake_cert.certification.sampler import make_generator
from drake_cert.certification.statistics import percentile_bounds

SIGMA, EPS, N = 0.25, 0.25, 400
ENVELOPE = (-1e9, 1e9)


class Heteroscedastic(torch.nn.Module):
    """Frames [B, 1, 1, 66]: 4e3 * pixel 0, plus 6e4 * (mean of pixels 1..64) * pixel 65.
    Pixel 65 is 0 in every frame, so under noise the outputs spread in proportion to the
    mean level of pixels 1..64 (0.05, 0.5 or 1; the mean averages most of its noise away)."""

    def forward(self, x):
        x = x.flatten(1)
        return 4e3 * x[:, 0] + 6e4 * x[:, 1:65].mean(1) * x[:, 65]


def frames(count, seed):
    g = torch.Generator().manual_seed(seed)
    t = 0.3 + 0.7 * torch.rand(count, generator=g)
    level = torch.randint(0, 3, (count,), generator=g)
    spread = torch.tensor([0.05, 0.5, 1.0])[level]
    x = torch.cat([t[:, None], spread[:, None].expand(count, 64), torch.zeros(count, 1)], 1)
    # the true stiffness errs from the model in proportion to the output spread
    y = 4e3 * t + 6e4 * SIGMA * spread * torch.randn(count, generator=g)
    return x.view(count, 1, 1, 66), y.double().numpy(), level.numpy()


def test_spread_bounds_bracket_the_known_spread_of_gaussian_outputs():
    rng = np.random.default_rng(0)
    true = 2 * 0.6744897501960817  # h_0.75 - h_0.25 of N(0, 1)
    lows, ups = [], []
    for _ in range(200):
        y = np.sort(rng.standard_normal(N))
        lows.append(spread_lower_bound(y, (0.25, 0.75), 0.01))
        ups.append(spread_upper_bound(y, 0.0, SIGMA, (0.25, 0.75), 0.01))
    assert np.mean(np.array(lows) <= true) >= 0.98 and np.mean(np.array(ups) >= true) >= 0.98
    assert np.all(np.array(lows) <= np.array(ups))


def test_normalized_interval_covers_under_a_shift_and_adapts_to_the_spread():
    smooth = MedianSmoothedRegressor(Heteroscedastic(), SIGMA)
    cal_x, cal_y, cal_l = frames(450, seed=1)
    seeds = list(range(1000, 1450))
    norm = calibrate_normalized(smooth, cal_x, cal_y, cal_l, n=N, batch_size=N,
                                alpha_c=0.05, frame_seeds=seeds, floor_n_per_rad=100.0)
    plain = calibrate_conformal(smooth, cal_x, cal_y, cal_l, n=N, batch_size=N, alpha_c=0.05,
                                frame_seeds=seeds)
    test_x, test_y, test_l = frames(450, seed=2)
    shift = torch.zeros(1, 1, 66)
    shift[..., 0] = -EPS  # lowers the median by 4e3 * eps
    covered, width_norm, width_plain = [], [], []
    for i in range(len(test_x)):
        y = smooth.sample_sorted(test_x[i] + shift, N, N, make_generator(5000 + i, "cpu"))
        lo, hi = norm.interval(y, EPS, 0.001, ENVELOPE)
        covered.append(lo <= test_y[i] <= hi)
        width_norm.append(hi - lo)
        lower, upper = percentile_bounds(y, EPS, SIGMA, 0.001)
        plo, phi = runtime_interval(lower, upper, plain.beta, ENVELOPE)
        width_plain.append(phi - plo)
    guarantee = 1 - 0.001 - 0.05 - 0.001 - 2 * 0.001
    assert np.mean(covered) >= guarantee - 0.03  # 450 frames: binomial slack
    tight = test_l == 0
    assert np.mean(np.array(width_norm)[tight]) < 0.7 * np.mean(np.array(width_plain)[tight])
