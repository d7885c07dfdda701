"""The statistics behind the certificates (DESIGN 3): joint Clopper-Pearson bounds, the
safe-set radius, order-statistic bounds on the smoothed median, split-conformal quantiles,
and the argument checks they share. Pure functions of numbers; no model, no torch.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence

import numpy as np
from scipy.optimize import brentq
from scipy.special import betaincinv, betaln
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
    return clopper_pearson_one_sided(counts, n, alpha / (2 * counts.size))


def clopper_pearson_one_sided(successes, trials: int, level: float):
    """One-sided Clopper-Pearson bounds ``(low, up)`` on a binomial probability, each at
    ``level``: ``P(p < low) <= level`` and ``P(p > up) <= level`` for a fixed number of trials.
    ``successes`` may be an array (the bounds are then arrays). Exact (beta quantiles); 0 and
    1 where the quantile is undefined (no successes, no failures)."""
    k = np.asarray(successes, dtype=np.float64)
    n = float(trials)
    # betaincinv(a, b, q) is beta.ppf(q, a, b) without scipy.stats' overhead (~30x faster).
    low = np.where(k > 0, betaincinv(np.maximum(k, 1), n - k + 1, level), 0.0)
    up = np.where(k < n, betaincinv(k + 1, np.maximum(n - k, 1), 1 - level), 1.0)
    return low, up


def beta_mixture_bounds(successes: int, trials: int, alpha: float) -> tuple[float, float]:
    """Robbins' beta-mixture confidence sequence for a Bernoulli mean: ``(low, up)`` at time t.

    For i.i.d. Bernoulli(p) draws with ``S`` successes in ``t`` trials, the mixture of the
    likelihood ratios ``(q/p)^S ((1-q)/(1-p))^(t-S)`` over a uniform prior on q,
    ``M_t(p) = B(S + 1, t - S + 1) / (p^S (1 - p)^(t - S))``, is a nonnegative martingale
    with mean 1 under p, so by Ville's inequality ``P(exists t: M_t(p) >= 1/alpha) <= alpha``.
    The set ``{p: M_t(p) < 1/alpha}`` is therefore a confidence sequence: with probability at
    least ``1 - alpha`` it holds the true p at EVERY t at once, so a decision taken at any
    data-dependent stopping time (after any batch, for any reason) keeps level alpha. That is
    what a fixed-n bound re-checked after every batch does not do. ``log M_t`` is convex in p
    with its minimum at ``S/t``, so the set is the interval ``[low, up]`` returned here
    (``low = 0`` when S = 0, ``up = 1`` when S = t). Both ends hold jointly at level alpha.
    """
    check_count(trials, "trials")
    check_alpha(alpha)
    if isinstance(successes, bool) or not 0 <= successes <= trials:
        raise CertificationError(f"successes = {successes!r} must be in 0..{trials}")
    return (_mixture_lower(int(successes), int(trials), alpha),
            1.0 - _mixture_lower(int(trials - successes), int(trials), alpha))


def _mixture_lower(s: int, t: int, alpha: float) -> float:
    """Lower end of the beta-mixture confidence interval (see :func:`beta_mixture_bounds`)."""
    if s == 0:
        return 0.0
    f = t - s
    log_b = betaln(s + 1, f + 1)
    log_level = math.log(1.0 / alpha)

    def excess(p: float) -> float:  # log M_t(p) - log(1/alpha): > 0 outside the set
        return log_b - s * math.log(p) - (f * math.log1p(-p) if f else 0.0) - log_level

    # excess falls monotonically on (0, S/t] from +inf to at most -log(1/alpha) (the mixture
    # never exceeds the maximum likelihood); bisect, then step down by the tolerance (sound).
    root = brentq(excess, 1e-300, s / t, xtol=1e-13, rtol=1e-12)
    return max(0.0, root - 2e-12)


SEQUENTIAL_BOUNDS = ("looks", "mixture")
"""Bounds of a sequential decision: Clopper-Pearson at fixed geometric looks (default), or
Robbins' beta-mixture confidence sequence (any look)."""


@dataclasses.dataclass(frozen=True)
class SequentialOptions:
    """How a sequential decision is laid out before any sample is drawn (docs/design.md 3).

    The looks (:func:`look_plan`): ``bound``, ``first_look``, ``futility_level``. The label
    selection (:meth:`SmoothedClassifier.decide` only): ``selection_n``, ``selection_seed``.
    None of them can make a certificate unsound; they trade samples against abstentions.
    """

    bound: str = "looks"  # "looks" (Clopper-Pearson at fixed looks) or "mixture"
    first_look: int = 32  # samples at the first look (mixture: the first batch)
    futility_level: float = 0.01  # level of the upper bounds that give up
    selection_n: int = 0  # noisy samples that choose the top label (0: the base model's)
    selection_seed: int | None = None  # stream of those samples (independent of the estimate)


@dataclasses.dataclass(frozen=True)
class LookPlan:
    """When a sequential decision looks at its samples and which bounds it then uses.

    ``looks`` are the cumulative sample counts at which bounds are computed, fixed before any
    sample is drawn. Looks below ``certify_from`` may only rule a question out (futility costs
    no soundness, so they spend no alpha); from ``certify_from`` on they may certify. With
    ``tests`` bounded quantities: "looks" takes Clopper-Pearson bounds at ``level = alpha /
    (tests * J)``, J the number of certifying looks (a union bound over quantities and looks:
    all hold at every certifying look at once with probability >= 1 - alpha, so stopping at
    any look is sound); "mixture" takes :func:`beta_mixture_bounds` at ``alpha / tests``
    (valid at every sample count).
    """

    looks: tuple[int, ...]
    level: float
    bound: str
    certify_from: int = 1
    futility_level: float = 0.01

    def bounds(self, successes: int, trials: int) -> tuple[float, float]:
        """``(low, up)`` on a Bernoulli mean after ``trials`` draws (``trials`` a look):
        ``low`` at ``level`` (0 at a look that may not certify); ``up`` at
        ``futility_level``, used only to give up (a lower level gives up less often; no
        choice of it can make a certificate unsound)."""
        up = (beta_mixture_bounds(successes, trials, self.futility_level)[1]
              if self.bound == "mixture" else
              float(clopper_pearson_one_sided(successes, trials, self.futility_level)[1]))
        return (self._low(successes, trials) if trials >= self.certify_from else 0.0), up

    def _low(self, successes: int, trials: int) -> float:
        if self.bound == "mixture":
            return beta_mixture_bounds(successes, trials, self.level)[0]
        return float(clopper_pearson_one_sided(successes, trials, self.level)[0])

    def reachable_low(self, up: float) -> float:
        """The lower bound the last look would give if the mean were ``up`` (successes
        ``up * n_max``, rounded down): a question whose reachable bounds cannot certify is
        given up (futility: it never makes a certificate unsound, only an abstention)."""
        n = self.looks[-1]
        return self._low(math.floor(up * n), n)

    @property
    def name(self) -> str:
        if self.bound == "mixture":
            return f"beta-mixture confidence sequence (Robbins) at {self.level:.3g} per bound"
        return (f"Clopper-Pearson at looks {list(self.looks)} (certifying from "
                f"{self.certify_from}), {self.level:.3g} per bound and look")


def unanimous_samples(level: float, threshold: float) -> int:
    """Fewest samples whose unanimous votes give a one-sided Clopper-Pearson lower bound at
    ``level`` above ``threshold``: the least n with ``level^(1/n) > threshold``."""
    if threshold <= 0:
        return 1
    return math.floor(math.log(level) / math.log(threshold)) + 1


def look_plan(n_max: int, alpha: float, tests: int, *, threshold: float = 0.5,
              options: SequentialOptions | None = None, batch_size: int = 500) -> LookPlan:
    """The looks of a sequential decision with at most ``n_max`` samples (:class:`LookPlan`).

    ``options`` (:class:`SequentialOptions`, default: its defaults) gives ``bound``,
    ``first_look`` and ``futility_level``.

    "looks": the certifying looks start at ``n_min``, the fewest samples that could certify a
    Bernoulli mean above ``threshold`` (:func:`unanimous_samples`, at the level the looks
    leave), and double up to ``n_max``; futility-only looks at ``first_look``, doubling,
    precede them. Raises :class:`CertificationError` when even ``n_max`` unanimous samples
    could not certify. "mixture": looks after batches of ``first_look``, doubling up to
    ``batch_size`` (every look may certify).
    """
    options = options or SequentialOptions()
    bound, first_look = options.bound, options.first_look
    futility_level = options.futility_level
    check_count(n_max, "n_max")
    check_count(tests, "tests")
    check_count(first_look, "first_look")
    check_count(batch_size, "batch_size")
    check_alpha(alpha)
    check_alpha(futility_level, "futility_level")
    if bound not in SEQUENTIAL_BOUNDS:
        raise CertificationError(f"bound {bound!r} is not one of {', '.join(SEQUENTIAL_BOUNDS)}")
    if bound == "mixture":
        looks, drawn, step = [], 0, min(first_look, batch_size)
        while drawn < n_max:
            drawn = min(n_max, drawn + step)
            looks.append(drawn)
            step = min(2 * step, batch_size)
        return LookPlan(tuple(looks), alpha / tests, bound, futility_level=futility_level)
    count = 1  # certifying looks: a fixed point of (count -> n_min -> count)
    for _ in range(64):
        n_min = unanimous_samples(alpha / (tests * count), threshold)
        if n_min > n_max:
            raise CertificationError(
                f"n_max = {n_max} samples can never certify a probability above "
                f"{threshold:.6g} (eps/sigma = {float(norm.ppf(threshold)):.3g}): even "
                f"unanimous votes need {n_min} at alpha = {alpha:g} over {tests} bound(s); "
                "raise n_max or lower eps")
        new = math.floor(math.log2(n_max / n_min) + 0.5) + 1  # last gap in [1.4, 2.8)
        if new <= count:
            break
        count = new
    certifying = sorted({min(n_min * 2 ** j, n_max) for j in range(count - 1)} | {n_max})
    futile = [first_look * 2 ** j for j in range(64) if first_look * 2 ** j < n_min // 2]
    looks = tuple(sorted(set(futile + certifying)))
    return LookPlan(looks, alpha / (tests * len(certifying)), bound, certify_from=n_min,
                    futility_level=futility_level)


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
