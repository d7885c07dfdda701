"""Calibration-conditional robust conformal thresholds, bounded in every stiffness bin
(docs/design.md 3.6, "A miss rate at every stiffness, for the calibration we ship").

The marginal calibration of :mod:`drake_cert.certification.conformal` bounds the miss rate on
average over a label and over the calibration draw. Misses cluster at a label's stiffness
edges (the generator draws the frame's severity from its stiffness), and every drive shares
one calibration, so the drive-level guarantee needs more:

* **Bins.** Each label's stiffness interval is cut into ``bins`` equal-width bins. Calibration
  frames are binned by their TRUE stiffness; the threshold of bin b is its own order statistic.
* **PAC bound of one order statistic** (:func:`order_statistic_miss_bound`). For m scores
  i.i.d. from any distribution and G(t) = P(new score < t), the k-th smallest r_(k) satisfies
  ``P(G(r_(k)) > u) <= P(Bin(m, u) < k) = P(Beta(k, m - k + 1) > u)``, atoms included. So with
  probability at least ``1 - delta`` over the calibration, a new frame of that bin scores below
  r_(k) with probability at most ``BetaInv(1 - delta; k, m - k + 1)``.
* **Per label, the worst bin.** Each bin takes the largest k whose bound at
  ``delta_cal / (labels x bins)`` is within ``miss_target`` (:func:`pac_order_index`); the label's
  threshold is the least of its bins' thresholds, so every bin's miss rate is within its own
  bound, and by a union bound all bins of all labels hold at once with probability at least
  ``1 - delta_cal`` over the calibration draw.

What the threshold feeds is unchanged: :class:`~drake_cert.certification.conformal.
RobustConformalCalibration` with ``alpha_c`` the largest bin bound (at most ``miss_target``) and
``delta_cal`` set; the run-time label set then misses the true label of a frame of any bin, under
any L2 perturbation within eps, with probability at most ``alpha_c + beta_cal + beta_test``,
for every calibration outside an event of probability ``delta_cal``. Assumption beyond the
marginal one: within a bin the miss rate is that of the bin (bins narrow enough; measured at
the bins' edges, docs/results.md).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
from scipy.stats import beta as beta_dist

from drake_cert.certification.statistics import check_alpha, check_count
from drake_cert.errors import CertificationError


def order_statistic_miss_bound(k: int, m: int, delta: float) -> float:
    """``BetaInv(1 - delta; k, m - k + 1)``: with probability at least ``1 - delta`` over m
    i.i.d. calibration scores, a new score of the same distribution falls strictly below their
    k-th smallest with probability at most this (0.0 for k = 0: the threshold is 0)."""
    check_alpha(delta, "delta")
    if not (isinstance(k, (int, np.integer)) and isinstance(m, (int, np.integer))
            and 0 <= k <= m):
        raise CertificationError(f"order statistic k = {k!r} must be an integer in 0..m = {m!r}")
    if k == 0:
        return 0.0
    return float(beta_dist.ppf(1.0 - delta, k, m - k + 1))


def pac_order_index(m: int, miss_target: float, delta: float) -> int:
    """The largest k in 0..m with :func:`order_statistic_miss_bound` ``(k, m, delta) <=
    miss_target`` (the bound grows with k); 0 when even k = 1 exceeds it."""
    check_alpha(miss_target, "miss_target")
    lo, hi = 0, int(m)
    while lo < hi:  # invariant: bound(lo) <= target
        mid = (lo + hi + 1) // 2
        if order_statistic_miss_bound(mid, int(m), delta) <= miss_target:
            lo = mid
        else:
            hi = mid - 1
    return lo


def bin_edges(lo: float, hi: float, bins: int) -> np.ndarray:
    """``bins + 1`` equal-width edges of the stiffness interval ``[lo, hi]`` (N/rad)."""
    check_count(bins, "bins")
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise CertificationError(f"stiffness interval [{lo!r}, {hi!r}] must be finite, lo < hi")
    return np.linspace(float(lo), float(hi), int(bins) + 1)


def bin_index(stiffness_n_per_rad: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The bin of each stiffness (0-based; the upper edge belongs to the last bin, values
    outside the interval to the nearest end bin)."""
    inner = np.asarray(edges, dtype=np.float64)[1:-1]
    return np.searchsorted(inner, np.asarray(stiffness_n_per_rad, dtype=np.float64),
                           side="right").astype(np.int64)


@dataclasses.dataclass(frozen=True)
class BinThreshold:
    """One stiffness bin of one label: its calibration frames, the order statistic used, the
    threshold it gives and the miss-rate bound that holds for it (at the bin's share of
    delta_cal)."""

    stiffness_lo_n_per_rad: float
    stiffness_hi_n_per_rad: float
    frames: int  # m: calibration frames in the bin
    order: int  # k: the threshold is the k-th smallest score (0: threshold 0)
    threshold: float  # r_(k), a lower bound on the true label's vote share (0 when k = 0)
    miss_bound: float  # BetaInv(1 - delta_bin; k, m - k + 1)


@dataclasses.dataclass(frozen=True)
class PacTargets:
    """What the calibration-conditional calibration aims for (DESIGN 3.6)."""

    bins: int  # stiffness bins per label
    miss_target: float  # largest miss bound a bin's threshold may have
    delta_cal: float  # probability that some bin's bound fails, split over labels x bins


def pac_binned_thresholds(scores: np.ndarray, labels: np.ndarray,
                          stiffness_n_per_rad: np.ndarray,
                          intervals: Sequence[tuple[float, float]], *, targets: PacTargets
                          ) -> tuple[dict[int, float], dict[int, list[BinThreshold]]]:
    """Per label the threshold ``q_l = min_b r_(k_b)`` over its stiffness bins, and each bin's
    :class:`BinThreshold` (module doc). ``intervals[l]``: label l's stiffness interval;
    ``targets``: bins per label, miss target and delta_cal (:class:`PacTargets`).

    Every bin's bound is taken at ``delta_cal / (labels x bins)``. A bin with too few frames
    for any order statistic within ``miss_target`` gets k = 0, i.e. threshold 0 (the label is
    never dropped from a set): sound, and useless, so :func:`check_bins_informative` names it.
    """
    bins, miss_target, delta_cal = targets.bins, targets.miss_target, targets.delta_cal
    check_alpha(delta_cal, "delta_cal")
    scores = np.asarray(scores, dtype=np.float64)
    labels = np.asarray(labels, dtype=np.int64)
    stiffness = np.asarray(stiffness_n_per_rad, dtype=np.float64)
    if not (scores.shape == labels.shape == stiffness.shape and scores.ndim == 1):
        raise CertificationError(f"scores {scores.shape}, labels {labels.shape} and stiffness "
                                 f"{stiffness.shape} must be 1-D arrays of one length")
    delta_bin = delta_cal / (len(intervals) * int(bins))
    thresholds: dict[int, float] = {}
    per_bin: dict[int, list[BinThreshold]] = {}
    for lab, (lo, hi) in enumerate(intervals):
        edges = bin_edges(lo, hi, bins)
        mine = labels == lab
        which = bin_index(stiffness[mine], edges)
        rows = []
        for b in range(int(bins)):
            s = np.sort(scores[mine][which == b])
            k = pac_order_index(len(s), miss_target, delta_bin) if len(s) else 0
            rows.append(BinThreshold(float(edges[b]), float(edges[b + 1]), int(len(s)), int(k),
                                     float(s[k - 1]) if k >= 1 else 0.0,
                                     order_statistic_miss_bound(int(k), int(len(s)), delta_bin)))
        per_bin[lab] = rows
        thresholds[lab] = min(r.threshold for r in rows)
    return thresholds, per_bin


def check_bins_informative(per_bin: dict[int, list[BinThreshold]],
                           label_names: Sequence[str]) -> None:
    """:class:`CertificationError` naming the first bin whose threshold is 0 (too few
    calibration frames for ``miss_target`` at its share of ``delta_cal``): its label would
    never leave a set."""
    for lab, rows in per_bin.items():
        for r in rows:
            if r.order == 0:
                raise CertificationError(
                    f"label {label_names[lab]!r}, stiffness bin [{r.stiffness_lo_n_per_rad:.0f}, "
                    f"{r.stiffness_hi_n_per_rad:.0f}] N/rad: {r.frames} calibration frames give "
                    "no order statistic within the miss target at its share of delta_cal; "
                    "give more calibration frames, fewer bins, or a larger target")


def min_frames_per_bin(miss_target: float, delta: float) -> int:
    """The fewest frames m of a bin for which some order statistic has its bound within
    ``miss_target`` at ``delta`` (k = 1: ``1 - delta^(1/m) <= miss_target``)."""
    check_alpha(miss_target, "miss_target")
    check_alpha(delta, "delta")
    m = max(1, math.ceil(math.log(delta) / math.log1p(-miss_target)) - 1)
    while order_statistic_miss_bound(1, m, delta) > miss_target:
        m += 1
    return m
