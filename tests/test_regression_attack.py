"""The regression attack targets the smoothed median, the quantity the certificate bounds.

Mean-targeting (SmoothAdv's expectation) can spend its budget on a rare tail of the noisy
outputs, which raises their mean but not their median. The median surrogate (Harrell-Davis
weights on the sorted noisy outputs) follows the median.
"""

import math

import numpy as np
import pytest
import torch

from drake_cert.certification.attacks import (
    AttackSettings,
    attack,
    central_mean,
    harrell_davis_median,
)

SIGMA = 0.25
HALF = 32  # pixels per half of a 1x8x8 frame


class RareTail(torch.nn.Module):
    """Stiffness = 1e5 * (mean of the first half of the pixels + 200 relu(v - t)): v is the
    mean of the second half and t sits two noise standard deviations above the clean v, so
    about 2 % of the noisy outputs are far out in a tail that never reaches the median."""

    def __init__(self):
        super().__init__()
        self.t = 0.5 + 2.0 * SIGMA / math.sqrt(HALF)

    def forward(self, x):
        f = x.flatten(1)
        return 1e5 * (f[:, :HALF].mean(1) + 200.0 * torch.relu(f[:, HALF:].mean(1) - self.t))


def smoothed_median(model, frames, samples=20_000, seed=9):
    g = torch.Generator().manual_seed(seed)
    with torch.inference_mode():
        return np.array([float(model(x.unsqueeze(0) + SIGMA * torch.randn(
            (samples, *x.shape), generator=g)).median()) for x in frames])


def test_median_target_moves_the_median_more_than_the_mean_target_on_a_rare_tail():
    model = RareTail()
    frames = torch.full((6, 1, 8, 8), 0.5)
    before = smoothed_median(model, frames)
    moved = {}
    for target in ("median", "mean"):
        adv = attack(model, frames, "sa", AttackSettings(eps=0.25, seed=0,
                                                         regression_target=target),
                     task="regress", sigma=SIGMA)
        moved[target] = smoothed_median(model, adv) - before
    best = 1e5 * 0.25 / math.sqrt(HALF)  # all of the budget on the first half's mean
    # Both bounds are tight for 6 frames: over 24 attack seeds about 1 in 4 missed one of them
    # (a frame at 0.946 best, or a gap of 0.029 best), as with torch's old 32-bit seeding.
    assert moved["median"].mean() > moved["mean"].mean() + 0.03 * best
    assert (moved["median"] > 0.95 * best).all()


def test_median_surrogates_are_the_median_of_a_sorted_sample():
    values = torch.tensor([[5.0], [1.0], [4.0], [2.0], [3.0], [100.0], [0.0], [3.5]])
    assert float(central_mean(values)) == pytest.approx(3.25)  # 4th and 5th of 8
    hd = float(harrell_davis_median(values))
    assert 2.5 < hd < 4.5  # near the sample median, barely moved by the outlier 100
    weights_sum = harrell_davis_median(torch.ones(8, 1))
    assert float(weights_sum) == pytest.approx(1.0)


@pytest.fixture(scope="module")
def shipped():
    from drake_cert.perception.datasets import load_split
    from drake_cert.perception.models import load_model

    model = load_model("carla-like", "regress", SIGMA)
    frames = load_split("carla-like", "test", frames_per_class=1).images[:2]
    return model, frames


@pytest.mark.slow  # ~15 s of CPU, ~50 s on the shared machine
def test_median_attack_moves_the_shipped_regressors_median_as_intended(shipped):
    """On the shipped regressor the noisy outputs are nearly symmetric (median - mean within
    about 150 N/rad), so median and mean targets ascend alike; measured: the median target
    moves the median 0.5-1.5 % less than the mean target (its gradient is noisier)."""
    model, frames = shipped
    before = smoothed_median(model, frames, samples=2000)
    up = attack(model, frames, "sa", AttackSettings(eps=0.5, steps=10, seed=3), task="regress",
                sigma=SIGMA)
    down = attack(model, frames, "ea", AttackSettings(eps=0.5, steps=10, seed=3),
                  task="regress", sigma=SIGMA)
    mean_up = attack(model, frames, "sa", AttackSettings(eps=0.5, steps=10, seed=3,
                                                         regression_target="mean"),
                     task="regress", sigma=SIGMA)
    rise = smoothed_median(model, up, samples=2000) - before
    fall = smoothed_median(model, down, samples=2000) - before
    rise_mean = smoothed_median(model, mean_up, samples=2000) - before
    assert (rise > 2000).all() and (fall < -2000).all()  # N/rad, at eps = 0.5
    assert rise.mean() > 0.95 * rise_mean.mean()
