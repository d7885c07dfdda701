"""The statistics behind the certificates (DESIGN 3): joint Clopper-Pearson bounds, the
safe-set radius, order-statistic bounds on the smoothed median, split-conformal quantiles,
and the argument checks they share. Pure functions of numbers; no model, no torch.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
from scipy.stats import beta as beta_dist
from scipy.stats import binom, norm

from drake_cert.errors import CertificationError


def check_alpha(alpha: float, name: str = "alpha") -> None:
    if not (isinstance(alpha, (int, float)) and 0.0 < alpha < 1.0):
        raise CertificationError(f"{name} = {alpha!r} must be in (0, 1)")


def check_sigma(sigma: float) -> None:
    if not (isinstance(sigma, (int, float)) and math.isfinite(sigma) and sigma > 0):
        raise CertificationError(f"sigma = {sigma!r} must be a positive finite number")


def check_count(value: int, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise CertificationError(f"{name} = {value!r} must be a positive integer")



def clopper_pearson_bounds(counts: Sequence[int] | np.ndarray,
                           alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """Joint one-sided Clopper-Pearson bounds on every label's probability (DESIGN 3).

    ``counts[l]`` is how many of the ``n = sum(counts)`` noisy samples the base classifier gave
    label ``l``. Each of the 2K one-sided bounds is taken at level ``alpha / (2K)``, so with
    probability at least ``1 - alpha`` over the samples, ``p_low[l] <= P(f(x + noise) = l) <=
    p_up[l]`` holds for all K labels at once (union bound); any radius computed from these
    bounds, for any set of labels, then holds simultaneously.

    Returns ``(p_low, p_up)``, float arrays of shape [K].
    """
    counts = np.asarray(counts)
    if counts.ndim != 1 or counts.size < 2 or not np.issubdtype(counts.dtype, np.integer) \
            or (counts < 0).any():
        raise CertificationError(f"counts must be a 1-D array of >= 2 non-negative integers, "
                                 f"got {counts!r}")
    check_alpha(alpha)
    n = int(counts.sum())
    if n <= 0:
        raise CertificationError("counts sum to 0: no samples to bound")
    level = alpha / (2 * counts.size)
    k = counts.astype(np.float64)
    # Beta quantiles are undefined at k = 0 (lower) and k = n (upper): the bounds are 0 and 1 there.
    p_low = np.where(counts > 0, beta_dist.ppf(level, np.maximum(k, 1), n - k + 1), 0.0)
    p_up = np.where(counts < n, beta_dist.ppf(1 - level, k + 1, np.maximum(n - k, 1)), 1.0)
    return p_low, p_up


def safe_set_radius(p_low: np.ndarray, p_up: np.ndarray, members: Iterable[int],
                    sigma: float) -> float:
    """Certified L2 radius of a label set T (DESIGN 3; paper Prop. 1, made sound).

    ``R_T = sigma/2 * (PhiInv(max_{t in T} p_low_t) - PhiInv(p_up_out))`` with
    ``p_up_out = min(max_{b not in T} p_up_b, 1 - sum_{t in T} p_low_t)``.
    If the bounds hold, the exact smoothed classifier's label stays in T for every frame ``z``
    with ``||z - x||_2 < R_T`` (strict). The in-T term is a single label's bound: for each
    label the map ``z -> PhiInv(P(f(z + noise) = l))`` is 1/sigma-Lipschitz (Cohen et al.
    Lemma 2; the same holds for the mass outside T), so the best label of T keeps beating
    every label outside T within the radius.

    Returns the radius in pixel-space L2 units, 0.0 when nothing is certified (the bound for T
    does not beat the outside), and ``inf`` when T holds every label.
    """
    members = sorted(set(int(t) for t in members))
    k = len(p_low)
    if not members or members[0] < 0 or members[-1] >= k:
        raise CertificationError(f"label set {members} is empty or not within 0..{k - 1}")
    if not (math.isfinite(sigma) and sigma > 0):
        raise CertificationError(f"sigma = {sigma!r} must be a positive finite number")
    outside = [b for b in range(k) if b not in members]
    best_in = float(max(p_low[t] for t in members))
    max_out = float(max((p_up[b] for b in outside), default=0.0))
    p_up_out = max(0.0, min(max_out, 1.0 - float(sum(p_low[t] for t in members))))
    if best_in <= p_up_out:
        return 0.0
    return float(0.5 * sigma * (norm.ppf(best_in) - norm.ppf(p_up_out)))


def percentile_bound_indices(n: int, eps: float, sigma: float, alpha: float) -> tuple[int, int]:
    """1-indexed order statistics that bound the smoothed median within budget eps (DESIGN 3).

    Chiang et al. (2020): for ``||x - x'||_2 <= eps``,
    ``h_pLow(x') <= h_0.5(x) <= h_pHigh(x')`` with ``pLow/High = Phi(-/+ eps/sigma)``.
    From n samples at x' sorted as ``y_(1) <= ... <= y_(n)``:

    - upper index: the smallest q with ``BinomCDF(q - 1; n, pHigh) >= 1 - alpha/2``
      (then ``P(y_(q) >= h_pHigh(x')) >= 1 - alpha/2``);
    - lower index: the largest q with ``P(Bin(n, pLow) >= q) >= 1 - alpha/2``
      (then ``P(y_(q) <= h_pLow(x')) >= 1 - alpha/2``).

    Both hold jointly with probability at least ``1 - alpha``. Raises
    :class:`CertificationError` when no such order statistic exists (n too small for
    eps/sigma; n = 10,000 and alpha = 0.001 allow eps/sigma up to about 3.17).
    """
    check_count(n, "n")
    check_alpha(alpha)
    check_sigma(sigma)
    if not (math.isfinite(eps) and eps >= 0):
        raise CertificationError(f"eps = {eps!r} must be a finite number >= 0")
    p_high = float(norm.cdf(eps / sigma))
    p_low = float(norm.cdf(-eps / sigma))
    q = np.arange(1, n + 1)
    upper_ok = binom.cdf(q - 1, n, p_high) >= 1 - alpha / 2
    lower_ok = binom.sf(q - 1, n, p_low) >= 1 - alpha / 2  # P(Bin >= q) = sf(q - 1)
    if not upper_ok.any() or not lower_ok.any():
        raise CertificationError(
            f"n = {n} samples are too few to bound the median at eps/sigma = {eps / sigma:.4g} "
            f"(eps = {eps}, sigma = {sigma}) with alpha = {alpha}; use a larger n or smaller eps")
    q_upper = int(q[upper_ok][0])
    q_lower = int(q[lower_ok][-1])
    return q_lower, q_upper


def percentile_bounds(sorted_outputs: np.ndarray, eps: float, sigma: float,
                      alpha: float) -> tuple[float, float]:
    """Order-statistic bounds ``(lower, upper)`` on ``h_0.5`` of every frame within eps (DESIGN 3).

    ``sorted_outputs`` are the n base-model outputs at the observed frame, ascending. With
    probability at least ``1 - alpha`` over the noise, ``lower <= h_0.5(x) <= upper`` for every
    ``x`` with ``||x - x'||_2 <= eps`` (see :func:`percentile_bound_indices`).
    """
    q_lower, q_upper = percentile_bound_indices(len(sorted_outputs), eps, sigma, alpha)
    return float(sorted_outputs[q_lower - 1]), float(sorted_outputs[q_upper - 1])


def conformity_score(y_true: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Split-conformal score ``max(y - L, U - y)`` of a calibration frame (DESIGN 3).

    ``[L, U]`` is the order-statistic interval of the smoothed median (eps = 0 bounds) and ``y``
    the frame's true stiffness. ``score <= beta`` means ``U - beta <= y <= L + beta``.
    """
    y = np.asarray(y_true)
    return np.maximum(y - np.asarray(lower), np.asarray(upper) - y)


def min_calibration_frames(alpha_c: float) -> int:
    """Smallest number of calibration frames of one label whose conformal quantile is finite:
    the least n_l with ``ceil((n_l + 1)(1 - alpha_c)) <= n_l`` (99 at alpha_c = 0.01)."""
    check_alpha(alpha_c, "alpha_c")
    n = max(1, math.floor(1.0 / alpha_c) - 2)
    while n > 1 and math.ceil(n * (1 - alpha_c)) <= n - 1:  # n - 1 already works: step down
        n -= 1
    while math.ceil((n + 1) * (1 - alpha_c)) > n:
        n += 1
    return n


def conformal_beta(scores: np.ndarray, labels: np.ndarray, alpha_c: float) -> dict[int, float]:
    """Mondrian split-conformal quantiles of the scores, one per true label (DESIGN 3).

    For the ``n_l`` calibration frames of label ``l``: the ``ceil((n_l + 1)(1 - alpha_c))``-th
    smallest score, ``inf`` when that exceeds ``n_l`` (too few frames). For a new frame of
    label ``l`` exchangeable with them, ``P(score <= beta_l) >= 1 - alpha_c``.
    """
    check_alpha(alpha_c, "alpha_c")
    scores = np.asarray(scores, dtype=np.float64)
    labels = np.asarray(labels)
    if scores.shape != labels.shape or scores.ndim != 1:
        raise CertificationError(f"scores {scores.shape} and labels {labels.shape} must be "
                                 "1-D arrays of the same length")
    if not np.isfinite(scores).all():
        raise CertificationError("conformity scores contain NaN or infinite values")
    betas = {}
    for label in np.unique(labels):
        s = np.sort(scores[labels == label])
        rank = math.ceil((len(s) + 1) * (1 - alpha_c))
        betas[int(label)] = float(s[rank - 1]) if rank <= len(s) else math.inf
    return betas
