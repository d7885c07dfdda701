"""The smoothed classifier g (Cohen et al. 2019) certified for sets of labels (paper Prop. 1,
made sound; DESIGN 3).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Mapping, Sequence

import numpy as np
import torch
from scipy.stats import binomtest

from drake_cert.certification.sampler import SmoothedModel, make_generator
from drake_cert.certification.statistics import (
    check_alpha,
    check_count,
    clopper_pearson_bounds,
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
