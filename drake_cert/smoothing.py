"""Randomized smoothing with sound certificates (DESIGN section 3).

Classification: Cohen et al. (2019) randomized smoothing,
`g(x) = argmax_l P(f(x + N(0, sigma^2 I)) = l)`, certified for a *set* of labels (paper
Prop. 1, made sound): joint Clopper-Pearson bounds for every label, the set radius `R_T`, and
the run-time stiffness interval at an observed frame.
Regression: Chiang et al. (2020) median smoothing, order-statistic bounds on the percentiles
`h_p`, widened by a split-conformal beta (Mondrian per label) into the run-time interval.

Standing assumption (DESIGN 3; measured, not certified): the exact smoothed classifier is right
on the clean frame and the condition table's interval holds the true stiffness (classification);
calibration and test frames are exchangeable (regression). Every probability statement is over
the Monte-Carlo noise of the certificate, which the attacker does not know: experiments fix seeds
to be reproducible, a deployment draws fresh noise (``seed=None``).

Frames are one image ``x`` of shape [C, H, W], floating point, in [0, 1]; perturbation budgets
``eps`` are L2 norms in that pixel space.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np
import torch
from scipy.stats import beta as beta_dist
from scipy.stats import binom, binomtest, norm

from drake_cert.errors import CertificationError

ABSTAIN = -1
"""Label returned when the smoothed classifier abstains."""


# --------------------------------------------------------------------------- statistics

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
    _check_alpha(alpha)
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
    _check_count(n, "n")
    _check_alpha(alpha)
    _check_sigma(sigma)
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


def conformal_beta(scores: np.ndarray, labels: np.ndarray, alpha_c: float) -> dict[int, float]:
    """Mondrian split-conformal quantiles of the scores, one per true label (DESIGN 3).

    For the ``n_l`` calibration frames of label ``l``: the ``ceil((n_l + 1)(1 - alpha_c))``-th
    smallest score, ``inf`` when that exceeds ``n_l`` (too few frames). For a new frame of
    label ``l`` exchangeable with them, ``P(score <= beta_l) >= 1 - alpha_c``.
    """
    _check_alpha(alpha_c, "alpha_c")
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


def runtime_interval(lower: float, upper: float, beta: float,
                     envelope: tuple[float, float]) -> tuple[float, float]:
    """Run-time stiffness interval of the regressor: ``[lower - beta, upper + beta]`` clipped
    to the envelope (DESIGN 3), in N/rad.

    With ``[lower, upper]`` from :func:`percentile_bounds` at budget eps and ``beta`` from
    :func:`conformal_beta` (largest over labels), the true stiffness of the clean frame lies
    inside with probability at least ``1 - alpha - alpha_c - alpha_m`` (marginal over
    calibration and test frames): ``y <= L(x) + beta <= h_0.5(x) + beta <= upper + beta`` and
    symmetrically below. An infinite beta, or an interval that misses the envelope, gives the
    envelope (the most conservative interval).
    """
    env_lo, env_hi = envelope
    if not (math.isfinite(beta) and math.isfinite(lower) and math.isfinite(upper)):
        return float(env_lo), float(env_hi)
    lo, hi = max(lower - beta, env_lo), min(upper + beta, env_hi)
    if lo > hi:
        return float(env_lo), float(env_hi)
    return float(lo), float(hi)


# --------------------------------------------------------------------------- validation

def _check_alpha(alpha: float, name: str = "alpha") -> None:
    if not (isinstance(alpha, (int, float)) and 0.0 < alpha < 1.0):
        raise CertificationError(f"{name} = {alpha!r} must be in (0, 1)")


def _check_sigma(sigma: float) -> None:
    if not (isinstance(sigma, (int, float)) and math.isfinite(sigma) and sigma > 0):
        raise CertificationError(f"sigma = {sigma!r} must be a positive finite number")


def _check_count(value: int, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise CertificationError(f"{name} = {value!r} must be a positive integer")


def check_frame(x: torch.Tensor) -> None:
    """Raise :class:`CertificationError` unless x is one finite float [C, H, W] frame in [0, 1]."""
    if not isinstance(x, torch.Tensor):
        raise CertificationError(f"frame must be a torch.Tensor, got {type(x).__name__}")
    if x.dim() != 3 or min(x.shape) == 0:
        raise CertificationError(f"frame must have shape [C, H, W], got {list(x.shape)}")
    if not x.is_floating_point():
        raise CertificationError(f"frame dtype must be floating point in [0, 1], got {x.dtype} "
                                 "(convert uint8 images with x.float() / 255)")
    if not torch.isfinite(x).all():
        raise CertificationError("frame contains NaN or infinite values")
    lo, hi = float(x.min()), float(x.max())
    if lo < -1e-6 or hi > 1 + 1e-6:
        raise CertificationError(f"frame values must lie in [0, 1], got [{lo:.4g}, {hi:.4g}]")


def resolve_device(device: str | torch.device) -> torch.device:
    """``torch.device`` for ``device``; CUDA only when asked for and available."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise CertificationError(f"unknown device {device!r} ({e})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CertificationError(f"device {device!r} requested but CUDA is not available")
    return dev


# --------------------------------------------------------------------------- sampling

class _NoisySampler:
    """Evaluates a base model on Gaussian-noised copies of one frame: the hot path.

    One preallocated [batch_size, C, H, W] buffer per shape; noise is written into it in place
    (``normal_``), the frame is added in place, and the model runs under
    ``torch.inference_mode``. With a compiled model every batch has the same shape (the last
    one is padded and its extra outputs dropped), so it is compiled once; an eager model runs
    a short last batch unpadded.
    """

    def __init__(self, base: torch.nn.Module, sigma: float, device: str | torch.device,
                 compile: bool):
        _check_sigma(sigma)
        if not isinstance(base, torch.nn.Module):
            raise CertificationError(f"base model must be a torch.nn.Module, got "
                                     f"{type(base).__name__}")
        self.sigma = float(sigma)
        self.device = resolve_device(device)
        self.base = base.to(self.device).eval()
        self.compiled = False
        self.compile_seconds = 0.0
        self._model: Callable[[torch.Tensor], torch.Tensor] = self.base
        self._needs_first_call = False
        if compile:
            try:
                # Freezing folds batch norm into the convolutions and pre-packs weights for
                # inference (2x over plain compilation on CPU, measured); the weights are then
                # constants, so build a new smoothed model after changing the base model.
                self._model = torch.compile(self.base, dynamic=False,
                                            options={"freezing": True})
                self.compiled = True
                self._needs_first_call = True
            except Exception as e:  # noqa: BLE001 - any failure means: run eager
                warnings.warn(f"torch.compile unavailable ({e}); running the model eagerly",
                              RuntimeWarning, stacklevel=3)
        self._buffer: torch.Tensor | None = None

    def _forward(self, batch: torch.Tensor) -> torch.Tensor:
        if not self._needs_first_call:
            return self._model(batch)
        # The first call compiles; a failure (no C++ compiler, unsupported op) falls back.
        start = time.perf_counter()
        try:
            out = self._model(batch)
        except Exception as e:  # noqa: BLE001
            warnings.warn(f"torch.compile failed ({type(e).__name__}: {str(e)[:200]}); "
                          "running the model eagerly", RuntimeWarning, stacklevel=4)
            self._model, self.compiled = self.base, False
            out = self._model(batch)
        self.compile_seconds += time.perf_counter() - start
        self._needs_first_call = False
        return out

    def _get_buffer(self, shape: torch.Size, batch_size: int, dtype: torch.dtype) -> torch.Tensor:
        want = (batch_size, *shape)
        if self._buffer is None or tuple(self._buffer.shape) != want or self._buffer.dtype != dtype:
            if self.compiled and self._buffer is not None:
                self._needs_first_call = True  # a new shape recompiles: time it separately
            self._buffer = torch.empty(want, dtype=dtype, device=self.device)
        return self._buffer

    def outputs(self, x: torch.Tensor, num: int, batch_size: int,
                generator: torch.Generator | None,
                selection: bool = False) -> Iterator[torch.Tensor]:
        """Yield the model's outputs on ``num`` noisy copies of ``x``, batch by batch.

        ``selection``: the samples only choose a label (CERTIFY's n0), which no guarantee
        depends on; a short batch then runs the eager model unpadded (cheaper than a padded
        compiled batch when it is at most half full). Estimation samples always use one model
        (the compiled one when compiled, padding the last batch).
        Must be consumed inside ``torch.inference_mode()`` (the callers do).
        """
        _check_count(num, "number of samples")
        _check_count(batch_size, "batch_size")
        check_frame(x)
        x = x.to(device=self.device, dtype=torch.float32)
        buf = self._get_buffer(x.shape, batch_size, torch.float32)
        remaining = num
        while remaining > 0:
            m = min(batch_size, remaining)
            # Short batches: an eager model runs them unpadded; a compiled one is padded (one
            # shape, compiled once) except for selection samples (see above).
            short = m < batch_size and (not self.compiled or (selection and 2 * m <= batch_size))
            batch = buf[:m] if short else buf
            batch.normal_(0.0, self.sigma, generator=generator)
            batch.add_(x)
            try:
                out = self.base(batch) if short else self._forward(batch)
            except RuntimeError as e:
                raise CertificationError(f"base model rejected a batch of frames of shape "
                                         f"{list(x.shape)}: {str(e).splitlines()[0]}") from None
            yield out[:m]
            remaining -= m

    def warmup(self, frame_shape: Sequence[int], batch_size: int) -> float:
        """Run one batch of the given frame shape (compiling if asked); return its seconds."""
        start = time.perf_counter()
        with torch.inference_mode():
            x = torch.full(tuple(frame_shape), 0.5)
            for _ in self.outputs(x, 1, batch_size, None):
                pass
        return time.perf_counter() - start


def make_generator(seed: int | None, device: torch.device) -> torch.Generator | None:
    """A seeded ``torch.Generator`` on ``device``, or None (global RNG, fresh noise)."""
    if seed is None:
        return None
    return torch.Generator(device=device).manual_seed(int(seed))


# --------------------------------------------------------------------------- classification

@dataclasses.dataclass(frozen=True)
class ClassCertificate:
    """Outcome of :meth:`SmoothedClassifier.certify` at one frame.

    ``label`` is the certified (top) label or :data:`ABSTAIN`; ``radius`` the certified L2
    radius of ``labels`` (the set T: {label}, or its safe set), 0 on abstain. The joint bounds
    ``p_low``/``p_up`` are kept so that the radius of any other set can be read off for free
    (:meth:`radius_for`): they hold for all sets at once.
    """

    label: int
    radius: float
    labels: tuple[int, ...]
    top_label: int
    counts: np.ndarray
    p_low: np.ndarray
    p_up: np.ndarray
    sigma: float
    alpha: float

    @property
    def abstained(self) -> bool:
        return self.label == ABSTAIN

    def radius_for(self, members: Iterable[int]) -> float:
        """Certified radius ``R_T`` of any label set T from the same joint bounds."""
        return safe_set_radius(self.p_low, self.p_up, members, self.sigma)


SafeSet = Callable[[int], Iterable[int]] | Mapping[int, Iterable[int]] | Sequence[Iterable[int]]


class _SmoothedModel:
    """What both smoothed models share: the noisy sampler, its device, compilation and warm-up."""

    def __init__(self, base: torch.nn.Module, sigma: float, device: str | torch.device,
                 compile: bool):
        self._sampler = _NoisySampler(base, sigma, device, compile)
        self.sigma = self._sampler.sigma
        self.device = self._sampler.device

    @property
    def compile_seconds(self) -> float:
        """Seconds spent in first (compiling) calls so far; 0.0 when not compiled."""
        return self._sampler.compile_seconds if self._sampler.compiled else 0.0

    def warmup(self, frame_shape: Sequence[int], batch_size: int) -> float:
        """Evaluate one batch (compiles the model when asked); returns the seconds taken."""
        return self._sampler.warmup(frame_shape, batch_size)


class SmoothedClassifier(_SmoothedModel):
    """The smoothed classifier ``g(x) = argmax_l P(f(x + N(0, sigma^2 I)) = l)`` (Cohen et al.).

    Args:
        base: torch module mapping [B, C, H, W] frames to [B, num_classes] scores (logits).
            It is moved to ``device`` and put in eval mode.
        num_classes: K, the number of labels.
        sigma: noise level (standard deviation per pixel, [0, 1] pixel units), > 0.
        device: "cpu" (default) or a CUDA device when asked for.
        compile: compile the base model with ``torch.compile`` (inductor, weights frozen).
            Default False: compiling takes ~15 s cold (~4 s with a warm inductor cache) on 2
            CPU cores and needs a C++ compiler, and pays off only after ~5 x 10^4 samples
            (benchmarks/bench_smoothing.py); tests and
            single frames are faster eager. ``drake-cert certify --compile auto`` turns it on
            for long runs. Falls back to eager with a warning if compilation fails.
            Certificates are those of the model as evaluated.
    """

    def __init__(self, base: torch.nn.Module, num_classes: int, sigma: float, *,
                 device: str | torch.device = "cpu", compile: bool = False):
        _check_count(num_classes, "num_classes")
        if num_classes < 2:
            raise CertificationError(f"num_classes = {num_classes} must be >= 2")
        self.num_classes = int(num_classes)
        super().__init__(base, sigma, device, compile)

    def sample_counts(self, x: torch.Tensor, num: int, batch_size: int,
                      generator: torch.Generator | None = None, *,
                      selection: bool = False) -> np.ndarray:
        """How many of ``num`` noisy copies of ``x`` the base model gives each label, [K].

        ``selection=True`` marks samples that only choose a label (see ``_NoisySampler``).
        """
        k = self.num_classes
        with torch.inference_mode():
            counts = torch.zeros(k, dtype=torch.int64, device=self.device)
            for out in self._sampler.outputs(x, num, batch_size, generator, selection):
                if out.dim() != 2 or out.shape[1] != k:
                    raise CertificationError(f"base model returned scores of shape "
                                             f"{list(out.shape)}; expected [batch, {k}]")
                counts += torch.bincount(out.argmax(dim=1), minlength=k)
            return counts.cpu().numpy()

    def predict(self, x: torch.Tensor, n: int, alpha: float, batch_size: int, *,
                seed: int | None = None) -> int:
        """Cohen et al.'s PREDICT: the smoothed label of ``x``, or :data:`ABSTAIN`.

        Draws n noisy samples and tests the top two counts with a two-sided binomial test.
        With probability at least ``1 - alpha`` over the noise, the returned label (when not
        ABSTAIN) is ``g(x)``.
        """
        _check_alpha(alpha)
        _check_count(n, "n")
        counts = self.sample_counts(x, n, batch_size, make_generator(seed, self.device))
        top2 = np.argsort(counts, kind="stable")[::-1][:2]
        n_a, n_b = int(counts[top2[0]]), int(counts[top2[1]])
        if binomtest(n_a, n_a + n_b, 0.5).pvalue > alpha:
            return ABSTAIN
        return int(top2[0])

    def certify(self, x: torch.Tensor, n0: int, n: int, alpha: float, batch_size: int,
                safe_set: SafeSet | None = None, *, seed: int | None = None) -> ClassCertificate:
        """Cohen et al.'s CERTIFY with joint per-label bounds and a set radius (DESIGN 3).

        ``n0`` samples pick the top label a; ``n`` fresh samples give joint Clopper-Pearson
        bounds on every label (:func:`clopper_pearson_bounds`). The certified set T is
        ``safe_set(a)`` (a callable, mapping or sequence indexed by label; it must contain a),
        or {a} when ``safe_set`` is None. With probability at least ``1 - alpha`` over the
        noise, the exact smoothed label ``g(z)`` lies in T for every z with
        ``||z - x||_2 < radius`` (and the radius of every other set read from the same
        certificate holds too). Abstains (label ABSTAIN, radius 0) when ``R_T <= 0``.
        """
        _check_alpha(alpha)
        _check_count(n0, "n0")
        _check_count(n, "n")
        self._check_enough_samples(n, alpha)
        gen = make_generator(seed, self.device)
        top = int(np.argmax(self.sample_counts(x, n0, batch_size, gen, selection=True)))
        counts = self.sample_counts(x, n, batch_size, gen)
        p_low, p_up = clopper_pearson_bounds(counts, alpha)
        members = (top,) if safe_set is None else self._members(safe_set, top)
        radius = safe_set_radius(p_low, p_up, members, self.sigma)
        label = top if radius > 0 else ABSTAIN
        return ClassCertificate(label=label, radius=radius if radius > 0 else 0.0,
                                labels=members, top_label=top, counts=counts, p_low=p_low,
                                p_up=p_up, sigma=self.sigma, alpha=float(alpha))

    def _members(self, safe_set: SafeSet, top: int) -> tuple[int, ...]:
        try:
            chosen = safe_set(top) if callable(safe_set) else safe_set[top]
            members = tuple(sorted(set(int(t) for t in chosen)))
        except (TypeError, KeyError, IndexError, ValueError):
            raise CertificationError(
                "safe_set must map each label index to the label indices of its safe set "
                f"(a callable, a mapping or a sequence of sequences); got {safe_set!r}") from None
        if top not in members or not all(0 <= t < self.num_classes for t in members):
            raise CertificationError(f"safe set {list(members)} of label {top} must contain it "
                                     f"and lie within 0..{self.num_classes - 1}")
        return members

    def _check_enough_samples(self, n: int, alpha: float) -> None:
        check_enough_samples(n, alpha, self.num_classes)


def check_enough_samples(n: int, alpha: float, num_classes: int) -> None:
    """Raise unless n votes, all for one label, would certify it: p_low must exceed 1/2.

    With all n samples on one label its bound is ``(alpha / 2K)^(1/n)``; below 1/2 every
    single-label certificate abstains, so such an n is an input error.
    """
    _check_count(n, "n")
    _check_alpha(alpha)
    if (alpha / (2 * num_classes)) ** (1.0 / n) <= 0.5:
        need = math.ceil(math.log2(2 * num_classes / alpha))
        raise CertificationError(f"n = {n} samples can never certify at alpha = {alpha} with "
                                 f"{num_classes} labels; use n >= {need}")


@dataclasses.dataclass(frozen=True)
class RuntimeCertificate:
    """Run-time stiffness interval at an observed frame (N/rad).

    ``labels`` is the certified contiguous range T (the whole family on fallback),
    ``radius`` its certified radius at the observed frame, ``certified`` False when the
    envelope was returned because the classifier abstained or no range qualified.
    """

    labels: tuple[str, ...]
    stiffness_lo_n_per_rad: float
    stiffness_hi_n_per_rad: float
    radius: float
    certified: bool

    @property
    def interval(self) -> tuple[float, float]:
        return (self.stiffness_lo_n_per_rad, self.stiffness_hi_n_per_rad)

    @property
    def width_n_per_rad(self) -> float:
        return self.stiffness_hi_n_per_rad - self.stiffness_lo_n_per_rad


def runtime_classification_interval(certificate: ClassCertificate, table, preset: str,
                                    eps: float,
                                    label_names: Sequence[str] | None = None) -> RuntimeCertificate:
    """The narrowest certified stiffness interval at an observed frame x' (DESIGN 3).

    Among the preset's contiguous friction ranges T that contain the top label at x' (the
    label the n0 selection samples chose), take the narrowest hull of stiffness intervals with
    ``R_T(x') > eps`` (strict; ties: the lower C_lo, then the fewer labels). The L2 ball is
    symmetric, so for a clean frame x with ``||x' - x|| <= eps``, ``g(x)`` is in T with
    probability at least ``1 - alpha`` over the noise (the joint bounds make every R_T hold at
    once, so the search is free); under the standing assumption (g right at x, the table's
    interval holds the true stiffness) the true stiffness is in the returned hull. No range
    qualifies (the run-time abstain; it includes every frame whose set {top} abstains and no
    wider range rescues): the preset's envelope, with ``certified`` False.

    ``table`` is a :class:`drake_cert.config.ConditionsTable`; ``label_names[i]`` names the
    classifier's label i (default: the preset's labels in order).
    """
    if not (math.isfinite(eps) and eps >= 0):
        raise CertificationError(f"eps = {eps!r} must be a finite number >= 0")
    names = list(label_names) if label_names is not None else list(table.preset(preset).labels)
    if len(names) != len(certificate.p_low):
        raise CertificationError(f"{len(names)} label names for a certificate over "
                                 f"{len(certificate.p_low)} labels")
    family = tuple(table.preset(preset).labels)
    envelope = table.envelope(preset)
    fallback = RuntimeCertificate(family, envelope[0], envelope[1], 0.0, False)
    index = {name: i for i, name in enumerate(names)}
    top = names[certificate.top_label]
    best: RuntimeCertificate | None = None
    for rng in table.contiguous_ranges(preset):
        if top not in rng or len(rng) == len(family):  # the whole family is the fallback
            continue
        if any(name not in index for name in rng):
            raise CertificationError(f"preset {preset!r} label {rng} not among the classifier's "
                                     f"labels {names}")
        radius = certificate.radius_for(index[name] for name in rng)
        if not radius > eps:
            continue
        lo, hi = table.hull(rng)
        cand = RuntimeCertificate(tuple(rng), lo, hi, radius, True)
        if best is None or _preference(cand) < _preference(best):
            best = cand
    return best if best is not None else fallback


def _preference(cert: RuntimeCertificate) -> tuple[float, float, int]:
    """Narrowest hull first; ties: the lower C_lo, then the fewer labels (equal hulls)."""
    return (cert.width_n_per_rad, cert.stiffness_lo_n_per_rad, len(cert.labels))


# --------------------------------------------------------------------------- regression

class MedianSmoothedRegressor(_SmoothedModel):
    """Median smoothing ``h_0.5(x)`` of a scalar regressor (Chiang et al. 2020; DESIGN 3).

    Args:
        base: torch module mapping [B, C, H, W] frames to [B] or [B, 1] (stiffness, N/rad).
        sigma: noise level, > 0 (pixel units).
        device, compile: as for :class:`SmoothedClassifier`.
    """

    def __init__(self, base: torch.nn.Module, sigma: float, *,
                 device: str | torch.device = "cpu", compile: bool = False):
        super().__init__(base, sigma, device, compile)

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
        _check_count(batch_size, "batch_size")
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
                        progress: Callable[[Iterable], Iterable] | None = None
                        ) -> ConformalCalibration:
    """Split-conformal calibration of the run-time interval on calibration frames (DESIGN 3).

    For each frame: ``[L_i, U_i]``, the order-statistic interval of the smoothed median
    (eps = 0 bounds at level ``alpha_m``, n samples), the score
    ``max(y_i - L_i, U_i - y_i)`` with y_i the true stiffness, and per true label the
    conformal quantile at ``alpha_c`` (:func:`conformal_beta`).
    """
    if len(frames) != len(stiffness_n_per_rad) or len(frames) != len(labels):
        raise CertificationError("frames, stiffness and labels must have the same length")
    gen = make_generator(seed, regressor.device)
    iterator: Iterable = range(len(frames))
    if progress is not None:
        iterator = progress(iterator)
    lower, upper = np.empty(len(frames)), np.empty(len(frames))
    for i in iterator:
        y = regressor.sample_sorted(frames[i], n, batch_size, gen)
        lower[i], upper[i] = percentile_bounds(y, 0.0, regressor.sigma, alpha_m)
    scores = conformity_score(np.asarray(stiffness_n_per_rad, dtype=np.float64), lower, upper)
    return ConformalCalibration(conformal_beta(scores, np.asarray(labels), alpha_c),
                                alpha_c=alpha_c, alpha_m=alpha_m, n=n, sigma=regressor.sigma,
                                frames=len(frames))
