"""Median smoothing of a stiffness regressor (Chiang et al. 2020; DESIGN 3) and its
split-conformal calibration (Mondrian per label).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Sequence

import numpy as np
import torch

from drake_cert.certification.sampler import SmoothedModel, make_generator
from drake_cert.certification.statistics import (
    check_count,
    conformal_beta,
    conformity_score,
    percentile_bound_indices,
    percentile_bounds,
)
from drake_cert.errors import CertificationError


class MedianSmoothedRegressor(SmoothedModel):
    """Median smoothing ``h_0.5(x)`` of a scalar regressor (Chiang et al. 2020; DESIGN 3).

    Args:
        base: torch module mapping [B, C, H, W] frames to [B] or [B, 1] (stiffness, N/rad).
        sigma: noise level, > 0 (pixel units).
        device, compile, precision: as for :class:`SmoothedClassifier`.
    """

    def __init__(self, base: torch.nn.Module, sigma: float, *,
                 device: str | torch.device = "cpu", compile: bool = False,
                 precision: str = "fp32"):
        super().__init__(base, sigma, device, compile, precision)

    def sample_sorted(self, x: torch.Tensor, num: int, batch_size: int,
                      generator: torch.Generator | None = None) -> np.ndarray:
        """The base model's outputs on ``num`` noisy copies of ``x``, ascending, float64 [num]."""
        with torch.inference_mode():
            values = torch.empty(num, dtype=torch.float32, device=self.device)
            start = 0
            for out in self._sampler.outputs(x, num, batch_size, generator):
                if not (out.dim() == 1 or (out.dim() == 2 and out.shape[1] == 1)):
                    raise CertificationError(f"regressor returned shape {list(out.shape)}; "
                                             "expected [batch] or [batch, 1]")
                values[start:start + out.shape[0]] = out.reshape(-1)
                start += out.shape[0]
            values = torch.sort(values).values.cpu().numpy().astype(np.float64)
        if not np.isfinite(values).all():
            raise CertificationError("regressor returned NaN or infinite outputs")
        return values

    def certify_interval(self, x: torch.Tensor, eps: float, n: int, alpha: float,
                         batch_size: int, *, seed: int | None = None
                         ) -> tuple[float, float, float]:
        """Median and raw certified bounds ``(median, lower, upper)`` at frame x (DESIGN 3).

        With probability at least ``1 - alpha`` over the noise, ``lower <= h_0.5(z) <= upper``
        for every frame z with ``||z - x||_2 <= eps`` (:func:`percentile_bounds`). ``median``
        is the empirical median ``y_(ceil(n/2))``. Raises :class:`CertificationError` when n is
        too small for eps/sigma. The run-time interval adds the conformal beta
        (:func:`runtime_interval`).
        """
        percentile_bound_indices(n, eps, self.sigma, alpha)  # fail before sampling
        check_count(batch_size, "batch_size")
        y = self.sample_sorted(x, n, batch_size, make_generator(seed, self.device))
        lower, upper = percentile_bounds(y, eps, self.sigma, alpha)
        return float(y[math.ceil(n / 2) - 1]), lower, upper


@dataclasses.dataclass(frozen=True)
class ConformalCalibration:
    """Per-label conformal betas (N/rad) of a median-smoothed regressor (DESIGN 3)."""

    betas: dict[int, float]  # true label -> beta_l
    alpha_c: float
    alpha_m: float
    n: int
    sigma: float
    frames: int

    @property
    def beta(self) -> float:
        """Run-time beta: the largest per-label beta (the label is unknown at run time)."""
        return max(self.betas.values())


def calibrate_conformal(regressor: MedianSmoothedRegressor, frames: torch.Tensor,
                        stiffness_n_per_rad: Sequence[float], labels: Sequence[int], *, n: int,
                        batch_size: int, alpha_m: float = 0.001, alpha_c: float = 0.01,
                        seed: int | None = 0,
                        progress: Callable[[Iterable], Iterable] | None = None,
                        frame_seeds: Sequence[int] | None = None) -> ConformalCalibration:
    """Split-conformal calibration of the run-time interval on calibration frames (DESIGN 3).

    For each frame: ``[L_i, U_i]``, the order-statistic interval of the smoothed median
    (eps = 0 bounds at level ``alpha_m``, n samples), the score
    ``max(y_i - L_i, U_i - y_i)`` with y_i the true stiffness, and per true label the
    conformal quantile at ``alpha_c`` (:func:`conformal_beta`). Noise: one stream from
    ``seed`` for all frames, or one per frame from ``frame_seeds``
    (``seeds.stream_seed(root, i, "calibration", split="calibration")``).
    """
    if len(frames) != len(stiffness_n_per_rad) or len(frames) != len(labels):
        raise CertificationError("frames, stiffness and labels must have the same length")
    if frame_seeds is not None and len(frame_seeds) != len(frames):
        raise CertificationError(f"{len(frame_seeds)} frame seeds for {len(frames)} frames")
    gen = make_generator(seed, regressor.device)
    iterator: Iterable = range(len(frames))
    if progress is not None:
        iterator = progress(iterator)
    lower, upper = np.empty(len(frames)), np.empty(len(frames))
    for i in iterator:
        if frame_seeds is not None:
            gen = make_generator(int(frame_seeds[i]), regressor.device)
        y = regressor.sample_sorted(frames[i], n, batch_size, gen)
        lower[i], upper[i] = percentile_bounds(y, 0.0, regressor.sigma, alpha_m)
    scores = conformity_score(np.asarray(stiffness_n_per_rad, dtype=np.float64), lower, upper)
    return ConformalCalibration(conformal_beta(scores, np.asarray(labels), alpha_c),
                                alpha_c=alpha_c, alpha_m=alpha_m, n=n, sigma=regressor.sigma,
                                frames=len(frames))
