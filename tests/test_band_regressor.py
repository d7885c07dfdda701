"""A band regressor (two outputs: lower and upper stiffness) smoothed end by end (DESIGN 3.2).

Each end is median-smoothed on its own; the run-time interval bounds the lower end's smoothed
median from below and the upper end's from above, so a point regressor is the band whose two
ends coincide. The bounds are checked against the exact percentiles of linear ends.
"""

import numpy as np
import pytest
import torch
from scipy.stats import norm

from drake_cert.certification.regressor import (
    MedianSmoothedRegressor,
    band_columns,
    calibrate_conformal,
)
from drake_cert.certification.sampler import CalibrationSampling
from drake_cert.errors import CertificationError
from drake_cert.perception.training import pinball_loss

SHAPE = (3, 4, 4)


class LinearBand(torch.nn.Module):
    """Ends ``w.x + b_lo`` and ``w.x + b_hi`` (in either column order)."""

    def __init__(self, w: torch.Tensor, b_lo: float, b_hi: float, swap: bool = False):
        super().__init__()
        self.register_buffer("w", w.flatten())
        self.b_lo, self.b_hi, self.swap = b_lo, b_hi, swap

    def forward(self, x):
        y = x.flatten(1) @ self.w
        ends = [y + self.b_lo, y + self.b_hi]
        return torch.stack(ends[::-1] if self.swap else ends, dim=1)


def _band(rng, swap=False):
    w = torch.tensor(rng.normal(size=int(np.prod(SHAPE))), dtype=torch.float32)
    x = torch.tensor(rng.uniform(0.2, 0.8, size=SHAPE), dtype=torch.float32)
    b_lo = float(rng.normal())
    return LinearBand(w, b_lo, b_lo + float(rng.uniform(0.5, 3.0)), swap), w, x


def test_band_bounds_hold_the_exact_percentiles_of_each_end():
    sigma, eps, alpha = 0.25, 0.3, 0.001
    rng = np.random.default_rng(11)
    for trial in range(40):
        model, w, x = _band(rng, swap=bool(trial % 2))
        smooth = MedianSmoothedRegressor(model, sigma)
        median, lower, upper = smooth.certify_interval(x, eps, 2_000, alpha, 1_000, seed=trial)
        mean = float(w @ x.flatten())
        shift = eps * float(w.norm())  # the worst case: each end's median moves by eps ||w||
        assert lower <= mean + model.b_lo - shift  # below the lower end's lowest median
        assert upper >= mean + model.b_hi + shift  # above the upper end's highest median
        assert lower <= median <= upper
        # and no looser than a point regressor at either end (same noise: same order statistics)
        scale = sigma * float(w.norm())
        assert lower >= mean + model.b_lo + scale * norm.ppf(1e-4)


def test_a_band_of_equal_ends_certifies_what_the_point_regressor_does():
    rng = np.random.default_rng(12)
    w = torch.tensor(rng.normal(size=int(np.prod(SHAPE))), dtype=torch.float32)
    x = torch.tensor(rng.uniform(0.2, 0.8, size=SHAPE), dtype=torch.float32)
    band = MedianSmoothedRegressor(LinearBand(w, 0.5, 0.5), 0.25)

    class Point(torch.nn.Module):
        def forward(self, z):
            return z.flatten(1) @ w + 0.5

    point = MedianSmoothedRegressor(Point(), 0.25)
    assert band.certify_interval(x, 0.25, 1_000, 0.001, 500, seed=3) == pytest.approx(
        point.certify_interval(x, 0.25, 1_000, 0.001, 500, seed=3))


def test_band_calibration_scores_bound_the_upper_end_from_below_and_the_lower_from_above():
    # Ends at stiffness -/+ 2 (noise-free frames of constant brightness): a true value inside
    # the band scores below 0, so beta is negative and the run-time interval narrows.
    class Ends(torch.nn.Module):
        def forward(self, z):
            c = 1e4 * z.flatten(1).mean(1)
            return torch.stack([c - 2.0, c + 2.0], dim=1)

    frames = torch.stack([torch.full(SHAPE, v) for v in np.linspace(0.2, 0.8, 120)]).float()
    truth = [1e4 * float(f.mean()) for f in frames]
    calib = calibrate_conformal(MedianSmoothedRegressor(Ends(), 1e-6), frames, truth,
                                [0] * 120, sampling=CalibrationSampling(n=200, batch_size=200,
                                                                        seed=0))
    assert calib.beta == pytest.approx(-2.0, abs=0.05)


def test_band_columns_refuse_other_shapes():
    lo, hi = band_columns(torch.tensor([[3.0, 1.0], [0.0, 2.0]]))
    assert lo.tolist() == [1.0, 0.0] and hi.tolist() == [3.0, 2.0]
    one = torch.tensor([[1.0], [2.0]])
    assert band_columns(one)[0] is band_columns(one)[1] or \
        torch.equal(band_columns(one)[0], band_columns(one)[1])
    with pytest.raises(CertificationError, match="expected"):
        band_columns(torch.zeros(2, 3))


def test_pinball_loss_is_minimised_by_the_quantiles():
    y = torch.linspace(0.0, 1.0, 1001)
    grid = torch.linspace(0.0, 1.0, 201)
    for tau in (0.05, 0.5, 0.95):
        losses = [float(pinball_loss(torch.full((1001, 1), float(q)), y, (tau,))) for q in grid]
        assert float(grid[int(np.argmin(losses))]) == pytest.approx(tau, abs=0.01)


def test_sequential_decision_tests_the_lower_end_against_lo_and_the_upper_end_against_hi():
    rng = np.random.default_rng(13)
    w = torch.tensor(rng.normal(size=int(np.prod(SHAPE))), dtype=torch.float32) * 0.01
    x = torch.tensor(rng.uniform(0.2, 0.8, size=SHAPE), dtype=torch.float32)
    mean = float(w @ x.flatten())
    smooth = MedianSmoothedRegressor(LinearBand(w, -1.0, 1.0), 0.25)
    # a candidate holding the band certifies; one holding only its midpoint cannot
    wide = smooth.decide(x, 0.25, 0.001, 2_000, 200,
                         lambda v: [(mean - 1.5, mean + 1.5)], seed=0)
    assert wide.certified and wide.interval == (mean - 1.5, mean + 1.5)
    assert wide.base_value == pytest.approx(mean, abs=1e-4)
    narrow = smooth.decide(x, 0.25, 0.001, 2_000, 200,
                           lambda v: [(mean - 0.5, mean + 0.5)], seed=0)
    assert not narrow.certified and narrow.reason == "futile"
