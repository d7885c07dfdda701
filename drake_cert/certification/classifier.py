"""The smoothed classifier g (Cohen et al. 2019) certified for sets of labels (paper Prop. 1,
made sound; DESIGN 3).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Mapping, Sequence

import numpy as np
import torch
from scipy.special import ndtri
from scipy.stats import binomtest, norm

from drake_cert.certification.sampler import (
    SmoothedModel,
    check_frame,
    check_frame_size,
    make_generator,
)
from drake_cert.certification.statistics import (
    SequentialOptions,
    check_alpha,
    check_count,
    clopper_pearson_bounds,
    look_plan,
    safe_set_radius,
)
from drake_cert.errors import CertificationError

ABSTAIN = -1
"""Label returned when the smoothed classifier abstains."""


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
Ranges = Sequence[Iterable[int]] | Callable[[int], Sequence[Iterable[int]]]


@dataclasses.dataclass(frozen=True)
class SequentialDecision:
    """Outcome of :meth:`SmoothedClassifier.decide`: is a label range certified at radius eps?

    ``labels`` is the certified range T (the most preferred candidate certified at some
    look), empty on abstain. ``samples`` counts every noisy sample drawn, selection included
    (``selection_samples`` of them chose a top label). ``radius`` is the radius the bounds
    certify for T (> eps when certified, 0 otherwise); ``top_label`` the label of T it was
    certified through (on abstain: the chosen or the most frequent label); ``p_low_top`` and
    ``p_low_range`` the lower confidence bounds behind it, on that label's probability and on
    T's mass. ``bound`` names the bounds and their looks, ``alpha`` the overall level.
    """

    certified: bool
    labels: tuple[int, ...]
    top_label: int
    samples: int
    selection_samples: int
    radius: float
    p_low_top: float
    p_low_range: float
    eps: float
    alpha: float
    bound: str
    counts: np.ndarray
    reason: str  # "certified", "futile" (no candidate can be certified) or "n_max"

    @property
    def abstained(self) -> bool:
        return not self.certified


def sequential_radius(p_low_top: float, p_low_range: float, sigma: float,
                      size: int = 1) -> float:
    """Certified radius of a range T of ``size`` labels from lower bounds on the probability
    of a label a in T and on T's mass: the larger of two radii, each sufficient for
    ``g(z) in T``, 0 when neither is positive.

    * label radius ``sigma/2 * (PhiInv(p_low_top) + PhiInv(p_low_range))``: :func:`safe_set_radius`
      with the outside term bounded by ``1 - P(T)`` (``PhiInv(1 - P(T)) = -PhiInv(P(T))``);
      for T = {a} it is Cohen's ``sigma PhiInv(p_low)``;
    * mass radius ``sigma * (PhiInv(p_low_range) - PhiInv(k / (k + 1)))`` for ``k = size``:
      ``PhiInv(P(f(z + noise) in T))`` is 1/sigma-Lipschitz in z (as for one label), so within
      it T keeps a mass above k/(k+1); then its best label has more than 1/(k+1) and every label
      outside at most 1 - mass < 1/(k+1), so g(z) is in T. It needs no dominant label: it
      certifies a range whose mass is split between two labels (a frame near a condition
      boundary) where the label radius cannot. For k = 1 the two coincide.
    """
    r = 0.5 * sigma * (float(ndtri(p_low_top)) + float(ndtri(p_low_range)))  # ndtri: PhiInv
    if size > 1:
        r = max(r, sigma * (float(ndtri(p_low_range)) - float(ndtri(size / (size + 1.0)))))
    return r if r > 0 else 0.0



class SmoothedClassifier(SmoothedModel):
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
        precision: "fp32" (default) or "bf16": evaluate the base model in bfloat16
            (:class:`~drake_cert.certification.sampler.Bfloat16Model`; certificates are then
            those of that model, so attack and calibrate it too).
    """

    def __init__(self, base: torch.nn.Module, num_classes: int, sigma: float, *,
                 device: str | torch.device = "cpu", compile: bool = False,
                 precision: str = "fp32"):
        check_count(num_classes, "num_classes")
        if num_classes < 2:
            raise CertificationError(f"num_classes = {num_classes} must be >= 2")
        self.num_classes = int(num_classes)
        super().__init__(base, sigma, device, compile, precision)

    def sample_counts(self, x: torch.Tensor, num: int, batch_size: int,
                      generator: torch.Generator | None = None, *,
                      selection: bool = False) -> np.ndarray:
        """How many of ``num`` noisy copies of ``x`` the base model gives each label, [K].

        ``selection=True`` marks samples that only choose a label (see ``NoisySampler``).
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
        check_alpha(alpha)
        check_count(n, "n")
        counts = self.sample_counts(x, n, batch_size, make_generator(seed, self.device))
        top2 = np.argsort(counts, kind="stable")[::-1][:2]
        n_a, n_b = int(counts[top2[0]]), int(counts[top2[1]])
        if binomtest(n_a, n_a + n_b, 0.5).pvalue > alpha:
            return ABSTAIN
        return int(top2[0])

    def certify(self, x: torch.Tensor, n0: int, n: int, alpha: float, batch_size: int,
                safe_set: SafeSet | None = None, *, seed: int | None = None,
                selection_seed: int | None = None) -> ClassCertificate:
        """Cohen et al.'s CERTIFY with joint per-label bounds and a set radius (DESIGN 3).

        ``n0`` samples pick the top label a; ``n`` fresh samples give joint Clopper-Pearson
        bounds on every label (:func:`clopper_pearson_bounds`). The certified set T is
        ``safe_set(a)`` (a callable, mapping or sequence indexed by label; it must contain a),
        or {a} when ``safe_set`` is None. With probability at least ``1 - alpha`` over the
        noise, the exact smoothed label ``g(z)`` lies in T for every z with
        ``||z - x||_2 < radius`` (and the radius of every other set read from the same
        certificate holds too). Abstains (label ABSTAIN, radius 0) when ``R_T <= 0``.

        Ties in the n0 counts go to the least-friction label (:func:`select_label`). Noise:
        one generator seeded by ``seed`` for both stages, or, when ``selection_seed`` is
        given, the n0 samples from ``selection_seed`` and the n samples from ``seed``
        (independent streams, see :mod:`drake_cert.certification.seeds`).
        """
        check_alpha(alpha)
        check_count(n0, "n0")
        check_count(n, "n")
        self._check_enough_samples(n, alpha)
        gen = make_generator(seed, self.device)
        select_gen = gen if selection_seed is None else make_generator(selection_seed,
                                                                       self.device)
        top = select_label(self.sample_counts(x, n0, batch_size, select_gen, selection=True))
        counts = self.sample_counts(x, n, batch_size, gen)
        p_low, p_up = clopper_pearson_bounds(counts, alpha)
        members = (top,) if safe_set is None else self._members(safe_set, top)
        radius = safe_set_radius(p_low, p_up, members, self.sigma)
        label = top if radius > 0 else ABSTAIN
        return ClassCertificate(label=label, radius=radius if radius > 0 else 0.0,
                                labels=members, top_label=top, counts=counts, p_low=p_low,
                                p_up=p_up, sigma=self.sigma, alpha=float(alpha))

    def decide(self, x: torch.Tensor, eps: float, alpha: float, n_max: int, batch_size: int,
               ranges: Ranges | None = None, *, seed: int | None = None,
               options: SequentialOptions | None = None) -> SequentialDecision:
        """Is a label range certified at radius ``eps`` around the observed frame ``x``?
        Decided sequentially: it stops as soon as the answer is known either way.

        ``ranges`` are the candidate label ranges, most preferred first, fixed before any
        estimation sample is drawn:

        - a sequence of ranges (e.g. every contiguous range of a preset,
          :func:`drake_cert.certification.intervals.candidate_ranges`): no label is chosen
          first; each range T is certified through its best label;
        - a callable of a top label a giving the ranges that hold a, with a the base model's
          prediction on ``x`` (``options.selection_n = 0``: one noise-free forward pass) or
          the most frequent label among ``options.selection_n`` noisy samples from
          ``options.selection_seed`` (an independent stream; ties to the least-friction
          label); or None: {a} alone.

        Contract: with probability at least ``1 - alpha`` over the noise, the exact smoothed
        label ``g(z)`` lies in the returned range T for every z with ``||z - x||_2 < radius``
        (radius > eps), whichever look it stops at; it stops when the most preferred
        candidate not yet ruled out is certified, when every candidate is ruled out
        (futility: an abstention, never unsound), or at ``n_max``. How: bounds at looks fixed
        in advance (:func:`look_plan`), the set radius of :func:`sequential_radius`, alpha
        split over labels, masses and looks; the argument is docs/design.md 3.7.

        Args:
            x: the observed frame [C, H, W] in [0, 1].
            eps: the radius to certify (L2, pixel units), >= 0.
            alpha: failure probability of the decision.
            n_max: most estimation samples to draw.
            batch_size: most noisy copies per forward pass.
            seed: stream of the estimation noise.
            options: :class:`SequentialOptions` (default: its defaults): ``bound`` "looks"
                or "mixture"; ``first_look`` the first look's least size;
                ``futility_level`` the level of the upper bounds that give up (0.01: it
                trades samples against certified frames, never soundness); the label
                selection ``selection_n``, ``selection_seed``.
        """
        options = options or SequentialOptions()
        selection_n = options.selection_n
        _check_decide_arguments(eps, alpha, n_max, batch_size, ranges, selection_n)
        top = self._decide_top(x, ranges, batch_size, options)
        tested = _Tested.of(top, self._candidates(ranges, top))
        plan = look_plan(int(n_max), alpha, len(tested.singles) + len(tested.masses),
                         threshold=float(norm.cdf(eps / self.sigma)), options=options,
                         batch_size=int(batch_size))
        outcome = self._sequential_looks(x, eps, batch_size, seed, plan, tested)
        return _sequential_decision(outcome, tested, plan, eps, alpha, selection_n)

    def _decide_top(self, x: torch.Tensor, ranges: Ranges | None, batch_size: int,
                    options: SequentialOptions) -> int | None:
        """The top label :meth:`decide`'s ranges are a function of: the most frequent label of
        ``options.selection_n`` noisy samples, else the base model's label; None for a fixed
        list."""
        if options.selection_n:
            select_gen = make_generator(options.selection_seed, self.device)
            return select_label(self.sample_counts(x, options.selection_n, batch_size,
                                                   select_gen, selection=True))
        if ranges is None or callable(ranges):
            return self.base_label(x)
        return None

    def _sequential_looks(self, x: torch.Tensor, eps: float, batch_size: int,
                          seed: int | None, plan, tested: _Tested) -> _LookOutcome:
        """Estimation samples drawn look by look until :meth:`decide`'s answer is known:
        ``(counts, best, reason)``, best = (T's index, R, a, L_a, L_T) or None."""
        candidates, singles, masses = tested.candidates, tested.singles, tested.masses
        k = self.num_classes
        counts = np.zeros(k, dtype=np.int64)
        gen = make_generator(seed, self.device)
        best: tuple[int, float, int, float, float] | None = None  # (T, R, a, L_a, L_T)
        reason = "n_max"
        with torch.inference_mode():
            for look in plan.looks:
                for out in self._sampler.outputs(x, look - int(counts.sum()), int(batch_size),
                                                 gen):
                    counts += torch.bincount(out.argmax(dim=1), minlength=k).cpu().numpy()
                bounds = {(a,): plan.bounds(int(counts[a]), look) for a in singles}
                bounds |= {c: plan.bounds(int(counts[list(c)].sum()), look) for c in masses}
                best, live = self._scan_look(bounds, plan, candidates, singles, eps, best)
                if live is None:
                    reason = "futile"
                    break
                if best is not None and best[0] <= live:
                    break
        return _LookOutcome(counts, best, reason)

    def _scan_look(self, bounds: dict, plan, candidates: list[tuple[int, ...]],
                   singles: list[int], eps: float, best: tuple | None
                   ) -> tuple[tuple | None, int | None]:
        """One look over the candidates, most preferred first: ``(best, live)``, the best
        certified candidate so far (kept across looks: every look's bounds hold at once) and
        the index of the most preferred candidate not yet ruled out (None: every one is)."""
        live = None
        for i, c in enumerate(candidates):
            low_t, up_t = bounds[c]
            for a in (t for t in c if t in singles):
                low_a, up_a = bounds[(a,)]
                radius = sequential_radius(low_a, low_t, self.sigma, len(c))
                if radius > eps and (best is None or (i, -radius) < (best[0], -best[1])):
                    best = (i, radius, a, low_a, low_t)
                reachable = sequential_radius(plan.reachable_low(up_a),
                                              plan.reachable_low(up_t), self.sigma, len(c))
                if reachable > eps and live is None:
                    live = i
        return best, live

    def base_label(self, x: torch.Tensor) -> int:
        """The base model's label on the frame itself (no noise), as evaluated."""
        check_frame(x)
        check_frame_size(x, self._sampler.base)
        with torch.inference_mode():
            out = self._sampler.base(x.to(self.device, torch.float32)[None])
        if out.dim() != 2 or out.shape[1] != self.num_classes:
            raise CertificationError(f"base model returned scores of shape {list(out.shape)}; "
                                     f"expected [1, {self.num_classes}]")
        return int(out.argmax(dim=1)[0])

    def _candidates(self, ranges: Ranges | None, top: int | None) -> list[tuple[int, ...]]:
        if ranges is None:
            return [(top,)]
        try:
            listed = [tuple(sorted(set(int(t) for t in c)))
                      for c in (ranges(top) if callable(ranges) else ranges)]
        except (TypeError, ValueError):
            raise CertificationError("ranges must be label ranges (sequences of label "
                                     "indices), or a function of the top label giving them; "
                                     f"got {ranges!r}") from None
        for c in listed:
            if not c or not all(0 <= t < self.num_classes for t in c) \
                    or (top is not None and top not in c):
                held = f" containing label {top}" if top is not None else ""
                raise CertificationError(f"candidate range {list(c)} must be a non-empty range"
                                         f"{held} within 0..{self.num_classes - 1}")
        if not listed:
            raise CertificationError("no candidate range was listed")
        return listed

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


def _check_decide_arguments(eps: float, alpha: float, n_max: int, batch_size: int,
                            ranges, selection_n: int) -> None:
    """The checks of :meth:`SmoothedClassifier.decide`'s arguments, in order."""
    check_alpha(alpha)
    check_count(n_max, "n_max")
    check_count(batch_size, "batch_size")
    if not (math.isfinite(eps) and eps >= 0):
        raise CertificationError(f"eps = {eps!r} must be a finite number >= 0")
    if isinstance(selection_n, bool) or not isinstance(selection_n, (int, np.integer)) \
            or selection_n < 0:
        raise CertificationError(f"selection_n = {selection_n!r} must be an integer >= 0")
    if selection_n and not (ranges is None or callable(ranges)):
        raise CertificationError("selection_n chooses a top label: give ranges as a "
                                 "function of that label (or None), not a fixed list")


@dataclasses.dataclass(frozen=True)
class _Tested:
    """What :meth:`SmoothedClassifier.decide` bounds: the candidate ranges, most preferred
    first, the single labels and the multi-label masses tested, and the top label (None for
    a fixed list)."""

    top: int | None
    candidates: list[tuple[int, ...]]
    singles: list[int]
    masses: list[tuple[int, ...]]

    @classmethod
    def of(cls, top: int | None, candidates: list[tuple[int, ...]]) -> _Tested:
        singles = sorted({top} if top is not None else {t for c in candidates for t in c})
        masses = sorted({c for c in candidates if len(c) > 1})
        return cls(top, candidates, singles, masses)


@dataclasses.dataclass(frozen=True)
class _LookOutcome:
    """Where the looks stopped: the estimation counts, the best certified candidate
    (T's index, R, a, L_a, L_T) or None, and the reason (certified, futile, n_max)."""

    counts: np.ndarray
    best: tuple | None
    reason: str


def _sequential_decision(outcome: _LookOutcome, tested: _Tested, plan, eps: float,
                         alpha: float, selection_n: int) -> SequentialDecision:
    """:meth:`SmoothedClassifier.decide`'s answer from the looks' outcome."""
    best, reason, counts = outcome.best, outcome.reason, outcome.counts
    candidates, top = tested.candidates, tested.top
    samples = int(counts.sum()) + int(selection_n)
    common = dict(samples=samples, selection_samples=int(selection_n), eps=float(eps),
                  alpha=float(alpha), bound=plan.name, counts=counts)
    if best is None:
        return SequentialDecision(certified=False, labels=(), radius=0.0, p_low_top=0.0,
                                  p_low_range=0.0, reason=reason,
                                  top_label=int(top if top is not None
                                                else select_label(counts)), **common)
    i, radius, a, low_a, low_t = best
    return SequentialDecision(certified=True, labels=candidates[i], radius=radius,
                              top_label=a, p_low_top=low_a, p_low_range=low_t,
                              reason="certified", **common)


def select_label(counts: np.ndarray) -> int:
    """The label with the most selection votes; ties go to the LAST maximal label.

    Labels are ordered grippiest first, so the last of the tied labels has the least friction:
    a tie is resolved to the conservative side (a lower stiffness, a lower safe speed).
    """
    counts = np.asarray(counts)
    return int(len(counts) - 1 - np.argmax(counts[::-1]))


def _can_certify(n: int, alpha: float, num_classes: int) -> bool:
    return (alpha / (2 * num_classes)) ** (1.0 / n) > 0.5


def min_certifying_samples(alpha: float, num_classes: int) -> int:
    """The smallest n for which n unanimous votes certify a label at ``alpha`` (the n that
    :func:`check_enough_samples` names): the least n > log2(2K / alpha)."""
    n = max(1, math.floor(math.log2(2 * num_classes / alpha)))
    while n > 1 and _can_certify(n - 1, alpha, num_classes):
        n -= 1
    while not _can_certify(n, alpha, num_classes):
        n += 1
    return n


def check_enough_samples(n: int, alpha: float, num_classes: int) -> None:
    """Raise unless n votes, all for one label, would certify it: p_low must exceed 1/2.

    With all n samples on one label its bound is ``(alpha / 2K)^(1/n)``; below 1/2 every
    single-label certificate abstains, so such an n is an input error.
    """
    check_count(n, "n")
    check_alpha(alpha)
    if not _can_certify(n, alpha, num_classes):
        need = min_certifying_samples(alpha, num_classes)
        raise CertificationError(f"n = {n} samples can never certify at alpha = {alpha} with "
                                 f"{num_classes} labels; use n >= {need}")
