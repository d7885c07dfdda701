"""Median smoothing of a stiffness regressor, or of each end of a band regressor (Chiang et al.
2020; DESIGN 3, 3.5), and its split-conformal calibration (Mondrian per label).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Sequence

import numpy as np
import torch
from scipy.stats import norm

from drake_cert.certification.sampler import (
    CalibrationSampling,
    SmoothedModel,
    check_frame,
    check_frame_size,
    make_generator,
)
from drake_cert.certification.statistics import (
    SequentialOptions,
    check_alpha,
    check_count,
    conformal_beta,
    conformity_score,
    look_plan,
    percentile_bound_indices,
    percentile_bounds,
)
from drake_cert.errors import CertificationError


@dataclasses.dataclass(frozen=True)
class MedianDecision:
    """Outcome of :meth:`MedianSmoothedRegressor.decide`: the first candidate interval
    ``(lo, hi)`` (N/rad) certified to hold the smoothed median of every frame within eps, or
    None on abstain; ``index`` its place among the candidates (-1 on abstain)."""

    certified: bool
    interval: tuple[float, float] | None
    index: int
    base_value: float  # the base model's output on the observed frame (chose the candidates)
    samples: int
    eps: float
    alpha: float
    bound: str
    reason: str  # "certified", "futile" or "n_max"
    sample_median: float | None = None  # lower median of the outputs drawn (N/rad); None at 0


def band_columns(out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A regressor's outputs as (lower, upper) [B] each, N/rad: a point regressor's [B] or
    [B, 1] is both ends; a band regressor's [B, 2] gives the smaller and the larger of its
    two outputs (a deterministic function of the base outputs, so smoothing it is sound)."""
    if out.dim() == 1 or (out.dim() == 2 and out.shape[1] == 1):
        y = out.reshape(-1)
        return y, y
    if out.dim() == 2 and out.shape[1] == 2:
        return out.min(dim=1).values, out.max(dim=1).values
    raise CertificationError(f"regressor returned shape {list(out.shape)}; expected [batch], "
                             "[batch, 1] or a band's [batch, 2]")


def point_value(out: torch.Tensor) -> torch.Tensor:
    """A regressor's point prediction [B] (N/rad): the output itself, or a band's midpoint."""
    lo, hi = band_columns(out)
    return lo if lo is hi else (lo + hi) / 2


class MedianSmoothedRegressor(SmoothedModel):
    """Median smoothing ``h_0.5(x)`` of a scalar regressor (Chiang et al. 2020; DESIGN 3), or of
    each end of a band regressor (``H_lo``, ``H_hi``; DESIGN 3.5).

    Args:
        base: torch module mapping [B, C, H, W] frames to [B] or [B, 1] (stiffness, N/rad),
            or to [B, 2] (a band's lower and upper stiffness, N/rad; :func:`band_columns`).
        sigma: noise level, > 0 (pixel units).
        device, compile, precision: as for :class:`SmoothedClassifier`.
    """

    def __init__(self, base: torch.nn.Module, sigma: float, *,
                 device: str | torch.device = "cpu", compile: bool = False,
                 precision: str = "fp32"):
        super().__init__(base, sigma, device, compile, precision)

    def sample_sorted(self, x: torch.Tensor, num: int, batch_size: int,
                      generator: torch.Generator | None = None) -> np.ndarray:
        """The base model's outputs on ``num`` noisy copies of ``x``, ascending, float64:
        [num] for a point regressor, [2, num] (lower ends, upper ends; each ascending) for a
        band regressor."""
        with torch.inference_mode():
            lows = torch.empty(num, dtype=torch.float32, device=self.device)
            highs = torch.empty(num, dtype=torch.float32, device=self.device)
            start, band = 0, False
            for out in self._sampler.outputs(x, num, batch_size, generator):
                lo, hi = band_columns(out)
                band = band or lo is not hi
                lows[start:start + lo.shape[0]] = lo
                highs[start:start + hi.shape[0]] = hi
                start += lo.shape[0]
            values = torch.stack([torch.sort(lows).values, torch.sort(highs).values]) if band \
                else torch.sort(lows).values
            values = values.cpu().numpy().astype(np.float64)
        if not np.isfinite(values).all():
            raise CertificationError("regressor returned NaN or infinite outputs")
        return values

    def certified_bounds(self, x: torch.Tensor, eps: float, n: int, alpha: float,
                         batch_size: int, generator: torch.Generator | None = None
                         ) -> tuple[float, float, float]:
        """``(median, lower, upper)`` of :meth:`certify_interval` from a given noise stream."""
        y = self.sample_sorted(x, n, batch_size, generator)
        lows, highs = (y[0], y[1]) if y.ndim == 2 else (y, y)
        lower = percentile_bounds(lows, eps, self.sigma, alpha)[0]
        upper = percentile_bounds(highs, eps, self.sigma, alpha)[1]
        k = math.ceil(n / 2) - 1  # the lower empirical median (of each end, for a band)
        return float((lows[k] + highs[k]) / 2), lower, upper

    def certify_interval(self, x: torch.Tensor, eps: float, n: int, alpha: float,
                         batch_size: int, *, seed: int | None = None
                         ) -> tuple[float, float, float]:
        """Median and raw certified bounds ``(median, lower, upper)`` at frame x (DESIGN 3).

        With probability at least ``1 - alpha`` over the noise, ``lower <= h_0.5(z) <= upper``
        for every frame z with ``||z - x||_2 <= eps`` (:func:`percentile_bounds`); for a band
        regressor ``lower <= H_lo(z)`` and ``H_hi(z) <= upper`` (each end smoothed on its own,
        one side each, so the same alpha). ``median`` is the empirical median
        ``y_(ceil(n/2))`` (for a band, the midpoint of the two ends' empirical medians).
        Raises :class:`CertificationError` when n is too small for eps/sigma. The run-time
        interval adds the conformal beta (:func:`runtime_interval`).
        """
        percentile_bound_indices(n, eps, self.sigma, alpha)  # fail before sampling
        check_count(batch_size, "batch_size")
        return self.certified_bounds(x, eps, n, alpha, batch_size,
                                     make_generator(seed, self.device))


    def decide(self, x: torch.Tensor, eps: float, alpha: float, n_max: int, batch_size: int,
               intervals: Callable[[float], Sequence[tuple[float, float]]], *,
               seed: int | None = None,
               options: SequentialOptions | None = None) -> MedianDecision:
        """Is the smoothed median of every frame within ``eps`` of ``x`` inside one of the
        candidate intervals? Decided sequentially (a confidence sequence for quantiles).

        Chiang et al.: for ``||z - x|| <= eps``, ``h_pLow(x) <= h_0.5(z) <= h_pHigh(x)`` with
        ``pHigh = Phi(eps/sigma) = 1 - pLow``. With y the base output under noise at x:
        ``P(y <= hi) > pHigh`` implies ``h_pHigh(x) <= hi``, and ``P(y >= lo) > pHigh`` implies
        ``h_pLow(x) >= lo`` (for a band regressor y is the upper end in the first and the lower
        end in the second). Each is a Bernoulli mean, bounded at looks fixed in advance
        (:func:`look_plan`; alpha split over the m distinct ends tested and the looks), so the
        decision may stop at any look: with probability at least ``1 - alpha``, a certified
        ``(lo, hi)`` holds ``h_0.5(z)`` for every such z.

        ``intervals(v)`` lists the candidates, most preferred first, given v, the base
        model's output on ``x`` itself (noise-free, so chosen before any sample is drawn).
        Stops at the most preferred candidate not yet ruled out once it is certified, when
        all are ruled out (futility, free), or at ``n_max``. ``options``
        (:class:`SequentialOptions`): the looks' ``bound``, ``first_look`` and
        ``futility_level``; it takes no label selection.
        """
        options = options or SequentialOptions()
        if options.selection_n or options.selection_seed is not None:
            raise CertificationError("a regressor's decision takes no label selection "
                                     "(selection_n, selection_seed)")
        check_alpha(alpha)
        check_count(n_max, "n_max")
        check_count(batch_size, "batch_size")
        if not (math.isfinite(eps) and eps >= 0):
            raise CertificationError(f"eps = {eps!r} must be a finite number >= 0")
        check_frame(x)
        check_frame_size(x, self._sampler.base)
        with torch.inference_mode():
            base_value = float(point_value(
                self._sampler.base(x.to(self.device, torch.float32)[None]))[0])
        if not math.isfinite(base_value):
            raise CertificationError("regressor returned a non-finite output on the frame")
        candidates = [(float(lo), float(hi)) for lo, hi in intervals(base_value)]
        if not candidates or any(not lo <= hi for lo, hi in candidates):
            raise CertificationError(f"candidate intervals {candidates} must be a non-empty "
                                     "list of (lo, hi) with lo <= hi")
        his = sorted({hi for _, hi in candidates})
        los = sorted({lo for lo, _ in candidates})
        p_high = float(norm.cdf(eps / self.sigma))
        plan = look_plan(int(n_max), alpha, len(his) + len(los), threshold=p_high,
                         options=options, batch_size=int(batch_size))
        below = dict.fromkeys(his, 0)  # samples with y <= hi
        above = dict.fromkeys(los, 0)  # samples with y >= lo
        t, gen, chosen, reason = 0, make_generator(seed, self.device), -1, "n_max"
        drawn = []  # the outputs, for the point estimate only (no bound rests on it)
        with torch.inference_mode():
            for look in plan.looks:
                for out in self._sampler.outputs(x, look - t, int(batch_size), gen):
                    y_lo, y_hi = band_columns(out)
                    if not (torch.isfinite(y_lo).all() and torch.isfinite(y_hi).all()):
                        raise CertificationError("regressor returned NaN or infinite outputs")
                    for hi in his:
                        below[hi] += int((y_hi <= hi).sum())
                    for lo in los:
                        above[lo] += int((y_lo >= lo).sum())
                    t += int(y_lo.shape[0])
                    drawn.append(((y_lo + y_hi) / 2).to("cpu", torch.float64).numpy())
                hi_b = {hi: plan.bounds(below[hi], t) for hi in his}
                lo_b = {lo: plan.bounds(above[lo], t) for lo in los}
                live = next((i for i, (lo, hi) in enumerate(candidates)
                             if plan.reachable_low(hi_b[hi][1]) > p_high
                             and plan.reachable_low(lo_b[lo][1]) > p_high), None)
                if live is None:
                    reason = "futile"
                    break
                lo, hi = candidates[live]
                if hi_b[hi][0] > p_high and lo_b[lo][0] > p_high:
                    chosen, reason = live, "certified"
                    break
        if chosen < 0:  # at n_max: the most preferred candidate certified by then, if any
            chosen = next((i for i, (lo, hi) in enumerate(candidates)
                           if hi_b[hi][0] > p_high and lo_b[lo][0] > p_high), -1) \
                if reason == "n_max" else -1
        ys = np.sort(np.concatenate(drawn)) if drawn else None
        return MedianDecision(
            certified=chosen >= 0, interval=candidates[chosen] if chosen >= 0 else None,
            index=chosen, base_value=base_value, samples=t, eps=float(eps),
            alpha=float(alpha), bound=plan.name,
            reason="certified" if chosen >= 0 else reason,
            sample_median=float(ys[math.ceil(t / 2) - 1]) if t else None)


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
                        stiffness_n_per_rad: Sequence[float], labels: Sequence[int], *,
                        sampling: CalibrationSampling, alpha_m: float = 0.001,
                        alpha_c: float = 0.01) -> ConformalCalibration:
    """Split-conformal calibration of the run-time interval on calibration frames (DESIGN 3).

    For each frame: ``[L_i, U_i]``, the order-statistic interval of the smoothed median
    (eps = 0 bounds at level ``alpha_m``, n samples), the score
    ``max(y_i - L_i, U_i - y_i)`` with y_i the true stiffness, and per true label the
    conformal quantile at ``alpha_c`` (:func:`conformal_beta`). For a band regressor L_i is
    the lower bound of ``H_hi`` and U_i the upper bound of ``H_lo`` (DESIGN 3.5). ``sampling``
    (:class:`CalibrationSampling`): n samples per frame in batches; noise: one stream from
    ``sampling.seed`` for all frames, or one per frame from ``sampling.frame_seeds``
    (``seeds.stream_seed(root, i, "calibration", split="calibration")``).
    """
    n, batch_size, seed = sampling.n, sampling.batch_size, sampling.seed
    progress, frame_seeds = sampling.progress, sampling.frame_seeds
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
        lows, highs = (y[0], y[1]) if y.ndim == 2 else (y, y)
        # the score's L bounds H_hi from below and its U bounds H_lo from above (eps = 0)
        lower[i] = percentile_bounds(highs, 0.0, regressor.sigma, alpha_m)[0]
        upper[i] = percentile_bounds(lows, 0.0, regressor.sigma, alpha_m)[1]
    scores = conformity_score(np.asarray(stiffness_n_per_rad, dtype=np.float64), lower, upper)
    return ConformalCalibration(conformal_beta(scores, np.asarray(labels), alpha_c),
                                alpha_c=alpha_c, alpha_m=alpha_m, n=n, sigma=regressor.sigma,
                                frames=len(frames))
