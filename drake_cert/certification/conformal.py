"""Adversarially robust conformal label sets and stiffness intervals (DESIGN 3.6, "Coverage
without the standing assumption").

Unlike :func:`~drake_cert.certification.intervals.runtime_classification_interval`, which holds
the TRUE stiffness only if the smoothed classifier is right on the clean frame, the interval
built here holds it with probability at least ``1 - alpha_total`` under any L2 perturbation of
at most eps, with no assumption that the classifier is right: randomized-smoothed conformal
prediction (Gendler et al. 2022) with a finite-sample Monte-Carlo correction (after Yan et al.
2024), Mondrian (per true label), on the smoothed vote share ``p_l(x)``.

Calibration (:func:`calibrate_robust_conformal`; per label l, held-out frames of true label l,
each with its own noise stream): scores ``r_i = CPlow(k_i; n, beta_cal)``, the one-sided
Clopper-Pearson lower bound on the true label's share; ``q_l`` the ``floor(alpha_c (n_l + 1))``-th
smallest (0 when that index is 0: label l is then always in the set). Threshold at budget eps:
``t_l(eps) = Phi(Phi^-1(q_l) - eps/sigma)``. Run time at the observed frame x' (n fresh samples):
``C(x') = {l : CPup(k'_l; n, beta_test) >= t_l(eps)}``; the interval is the hull of the
stiffness intervals from its first to its last label in friction order (the envelope when C is
empty). :func:`sequential_label_set` decides the same set at looks fixed in advance.

Guarantee: ``P(C_true in interval) >= 1 - alpha_total``, ``alpha_total = alpha_c + beta_cal +
beta_test``, per true label and marginally, over calibration frames, test frame and all noise.
Assumes calibration and test frames exchangeable within a label (fails under distribution
shift), an attacker who does not know the test noise, ``||delta|| <= eps``, and the condition
table's interval of each label holding its stiffness. Not claimed: coverage for one given
frame. Defaults alpha_c = 0.008, beta_cal = beta_test = 0.001 (alpha_total = 0.01); alpha_c
needs at least ``1/alpha_c - 1`` calibration frames per label (124 at 0.008).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence

import numpy as np
import torch
from scipy.stats import norm

from drake_cert.certification.classifier import ClassCertificate, SmoothedClassifier
from drake_cert.certification.intervals import StiffnessBounds
from drake_cert.certification.pac_conformal import (
    BinThreshold,
    PacTargets,
    check_bins_informative,
    pac_binned_thresholds,
)
from drake_cert.certification.sampler import CalibrationSampling, make_generator
from drake_cert.certification.seeds import stream_seed
from drake_cert.certification.statistics import check_alpha, check_count, clopper_pearson_one_sided
from drake_cert.errors import CertificationError

ALPHA_C = 0.008
BETA_CAL = 0.001
BETA_TEST = 0.001


def lower_conformal_quantile(scores: np.ndarray, alpha_c: float) -> float:
    """``r_(j)``, the j-th smallest score with ``j = floor(alpha_c (m + 1))``; 0.0 when j = 0.

    For a new score exchangeable with the m given ones, ``P(new >= r_(j)) >= 1 - alpha_c``.
    (Scores are probabilities in [0, 1]; 0 is the trivial threshold.)
    """
    check_alpha(alpha_c, "alpha_c")
    s = np.sort(np.asarray(scores, dtype=np.float64))
    j = math.floor(alpha_c * (len(s) + 1))
    return float(s[j - 1]) if j >= 1 else 0.0


def min_frames_per_label(alpha_c: float) -> int:
    """The fewest calibration frames m of a label for which :func:`lower_conformal_quantile`
    gives a threshold (``floor(alpha_c (m + 1)) >= 1``); with fewer the label is always in the
    set (19 at alpha_c = 0.05, 124 at 0.008)."""
    check_alpha(alpha_c, "alpha_c")
    m = max(0, math.ceil(1.0 / alpha_c) - 2)
    while math.floor(alpha_c * (m + 1)) < 1:
        m += 1
    return m


@dataclasses.dataclass(frozen=True)
class RobustConformalCalibration:
    """Per-label thresholds ``q_l`` of the robust conformal label set (see module doc)."""

    thresholds: dict[int, float]  # true label -> q_l (a lower bound on p_l, in [0, 1])
    frames_per_label: dict[int, int]
    num_classes: int
    sigma: float
    n: int  # samples per calibration frame
    alpha_c: float = ALPHA_C  # the conformal step's miss rate (PAC: the largest bin bound)
    beta_cal: float = BETA_CAL
    beta_test: float = BETA_TEST
    # 0: marginal coverage (over calibration and test frame). > 0: calibration-conditional,
    # per stiffness bin (drake_cert.certification.pac_conformal): alpha_total bounds the miss
    # rate in every bin for all calibrations outside an event of probability delta_cal
    delta_cal: float = 0.0
    bins: dict[int, tuple[BinThreshold, ...]] | None = None  # per label, its bins (PAC only)

    def to_json(self) -> dict:
        """A JSON-ready dict (label keys as strings); :meth:`from_json` inverts it exactly."""
        out = dataclasses.asdict(self)
        for key in ("thresholds", "frames_per_label"):
            out[key] = {str(k): v for k, v in out[key].items()}
        if self.bins is not None:
            out["bins"] = {str(k): [dataclasses.asdict(r) for r in rows]
                           for k, rows in self.bins.items()}
        return out

    @classmethod
    def from_json(cls, data: dict) -> RobustConformalCalibration:
        data = dict(data)
        data["thresholds"] = {int(k): float(v) for k, v in data["thresholds"].items()}
        data["frames_per_label"] = {int(k): int(v) for k, v in data["frames_per_label"].items()}
        if data.get("bins") is not None:
            data["bins"] = {int(k): tuple(BinThreshold(**r) for r in rows)
                            for k, rows in data["bins"].items()}
        return cls(**data)

    @property
    def alpha_total(self) -> float:
        """Miscoverage guaranteed by the construction: ``alpha_c + beta_cal + beta_test``
        (marginal, or with ``delta_cal`` > 0 in every stiffness bin given the calibration)."""
        return self.alpha_c + self.beta_cal + self.beta_test

    def threshold(self, label: int, eps: float) -> float:
        """``t_l(eps) = Phi(Phi^-1(q_l) - eps / sigma)``; labels never calibrated: 0 (always in)."""
        if not (math.isfinite(eps) and eps >= 0):
            raise CertificationError(f"eps = {eps!r} must be a finite number >= 0")
        q = self.thresholds.get(int(label), 0.0)
        if q <= 0.0:
            return 0.0
        return float(norm.cdf(norm.ppf(q) - eps / self.sigma))

    def label_set(self, counts: Sequence[int] | np.ndarray, eps: float) -> tuple[int, ...]:
        """``C(x') = {l : CPup(k'_l; n', beta_test) >= t_l(eps)}`` from the run-time vote counts."""
        counts = np.asarray(counts)
        if counts.ndim != 1 or counts.size != self.num_classes or (counts < 0).any() \
                or counts.sum() <= 0:
            raise CertificationError(f"counts {counts!r} must be {self.num_classes} non-negative "
                                     "integers with a positive sum")
        upper = clopper_pearson_one_sided(counts, int(counts.sum()), self.beta_test)[1]
        return tuple(int(lab) for lab in range(self.num_classes)
                     if upper[lab] >= self.threshold(lab, eps))


def calibration_scores(true_counts: np.ndarray, n: int, beta_cal: float = BETA_CAL) -> np.ndarray:
    """``r_i = CPlow(k_i; n, beta_cal)``: lower bounds on ``p_{y_i}(x_i)`` from k_i votes."""
    check_alpha(beta_cal, "beta_cal")
    check_count(n, "n")
    return clopper_pearson_one_sided(np.asarray(true_counts), n, beta_cal)[0]


def thresholds_from_scores(scores: np.ndarray, labels: np.ndarray, num_classes: int,
                           alpha_c: float = ALPHA_C) -> tuple[dict[int, float], dict[int, int]]:
    """Mondrian lower conformal quantiles ``q_l`` of the scores per true label (0.0: no frames)."""
    scores, labels = np.asarray(scores, dtype=np.float64), np.asarray(labels)
    if scores.shape != labels.shape or scores.ndim != 1:
        raise CertificationError(f"scores {scores.shape} and labels {labels.shape} must be 1-D "
                                 "arrays of the same length")
    thresholds, sizes = {}, {}
    for lab in range(num_classes):
        s = scores[labels == lab]
        sizes[lab] = int(len(s))
        thresholds[lab] = lower_conformal_quantile(s, alpha_c) if len(s) else 0.0
    return thresholds, sizes


@dataclasses.dataclass(frozen=True)
class ConformalLevels:
    """The robust conformal calibration's levels (module doc): ``alpha_c`` the conformal
    miss level, ``beta_cal`` and ``beta_test`` the smoothing bounds' failure probabilities at
    calibration and at test time."""

    alpha_c: float = ALPHA_C
    beta_cal: float = BETA_CAL
    beta_test: float = BETA_TEST


@dataclasses.dataclass(frozen=True)
class TrueLabelVotes:
    """The calibration frames' true-label votes (:func:`true_label_counts`): ``true_counts[i]``
    of ``n`` noisy samples of frame i voted for its true label ``labels[i]`` (stiffness
    ``stiffness_n_per_rad[i]``, N/rad)."""

    true_counts: np.ndarray
    labels: Sequence[int]
    stiffness_n_per_rad: Sequence[float]
    n: int


def true_label_counts(classifier: SmoothedClassifier, frames: torch.Tensor,
                      labels: Sequence[int], *, sampling: CalibrationSampling) -> np.ndarray:
    """Votes for its true label among ``sampling.n`` noisy samples of each calibration frame;
    frame i draws from its own stream (``seeds.stream_seed(sampling.seed, i, "calibration",
    split="calibration")``; seed None: fresh global noise)."""
    n, batch_size, root_seed = sampling.n, sampling.batch_size, sampling.seed
    progress = sampling.progress
    if sampling.frame_seeds is not None:
        raise CertificationError("the classifier's calibration derives its frame streams "
                                 "from the root seed; it takes no frame_seeds")
    check_count(n, "n")
    labels = np.asarray([int(v) for v in labels])
    if len(frames) != len(labels):
        raise CertificationError(f"{len(frames)} frames but {len(labels)} labels")
    if len(labels) and (labels.min() < 0 or labels.max() >= classifier.num_classes):
        raise CertificationError(f"calibration labels must lie in 0..{classifier.num_classes - 1}")
    iterator: Iterable = range(len(frames))
    if progress is not None:
        iterator = progress(iterator)
    true_counts = np.empty(len(frames), dtype=np.int64)
    for i in iterator:
        seed = None if root_seed is None else stream_seed(root_seed, i, "calibration",
                                                          split="calibration")
        counts = classifier.sample_counts(frames[i], n, batch_size,
                                          make_generator(seed, classifier.device))
        true_counts[i] = counts[labels[i]]
    return true_counts


def calibrate_robust_conformal(classifier: SmoothedClassifier, frames: torch.Tensor,
                               labels: Sequence[int], *, sampling: CalibrationSampling,
                               levels: ConformalLevels | None = None
                               ) -> RobustConformalCalibration:
    """Calibrate the robust conformal label set on held-out frames (see module doc): marginal
    coverage, one threshold per label (:func:`true_label_counts` draws the votes as
    ``sampling`` says). ``levels``: alpha_c, beta_cal, beta_test (default
    :class:`ConformalLevels`)."""
    levels = levels or ConformalLevels()
    alpha_c, beta_cal, beta_test = levels.alpha_c, levels.beta_cal, levels.beta_test
    n = sampling.n
    for name, a in (("alpha_c", alpha_c), ("beta_cal", beta_cal), ("beta_test", beta_test)):
        check_alpha(a, name)
    true_counts = true_label_counts(classifier, frames, labels, sampling=sampling)
    scores = calibration_scores(true_counts, n, beta_cal)
    thresholds, sizes = thresholds_from_scores(scores, np.asarray(labels, dtype=np.int64),
                                               classifier.num_classes, alpha_c)
    return RobustConformalCalibration(thresholds, sizes, classifier.num_classes,
                                      classifier.sigma, int(n), alpha_c, beta_cal, beta_test)


def pac_calibration_from_counts(votes: TrueLabelVotes, intervals: Sequence[tuple[float, float]],
                                *, sigma: float, targets: PacTargets,
                                levels: ConformalLevels | None = None,
                                label_names: Sequence[str] | None = None
                                ) -> RobustConformalCalibration:
    """The calibration-conditional, per-stiffness-bin calibration
    (:mod:`drake_cert.certification.pac_conformal`) from the calibration frames' true-label
    votes (:class:`TrueLabelVotes`, n samples each) with ``targets`` (bins, miss target,
    delta_cal). ``levels``: beta_cal and beta_test (its alpha_c is not used: ``alpha_c`` of
    the result is the largest bin bound, at most ``targets.miss_target``);
    :class:`CertificationError` when a bin has too few frames for any threshold
    (``label_names`` name it)."""
    levels = levels or ConformalLevels()
    beta_cal, beta_test = levels.beta_cal, levels.beta_test
    n, delta_cal = votes.n, targets.delta_cal
    for name, a in (("beta_cal", beta_cal), ("beta_test", beta_test)):
        check_alpha(a, name)
    labels = np.asarray(votes.labels, dtype=np.int64)
    scores = calibration_scores(np.asarray(votes.true_counts), n, beta_cal)
    thresholds, per_bin = pac_binned_thresholds(scores, labels,
                                                np.asarray(votes.stiffness_n_per_rad),
                                                intervals, targets=targets)
    names = list(label_names) if label_names is not None else \
        [str(i) for i in range(len(intervals))]
    check_bins_informative(per_bin, names)
    worst = max(r.miss_bound for rows in per_bin.values() for r in rows)
    sizes = {lab: int((labels == lab).sum()) for lab in range(len(intervals))}
    return RobustConformalCalibration(thresholds, sizes, len(intervals), float(sigma), int(n),
                                      float(worst), beta_cal, beta_test, float(delta_cal),
                                      {lab: tuple(rows) for lab, rows in per_bin.items()})


@dataclasses.dataclass(frozen=True)
class ConformalDecision:
    """Outcome of :func:`sequential_label_set`: the robust conformal label set at one observed
    frame, decided sequentially.

    ``label_set``: ``C(x')`` (label indices), from the bounds of the look it stopped at;
    ``counts``: the votes drawn; ``samples``: their number; ``looks``: the looks planned (each
    label's upper bound is taken at ``beta_test / len(looks)`` at every look); ``reason``:
    "narrowest" (one label), "settled" (both ends of the label range are in the set at the
    settling level: more samples would not narrow it), "futile" (at the present vote shares
    both ends would still be in the set at n_max: more samples are not expected to narrow
    it), "fixed" (the range is every label and neither end can leave it whatever the votes
    still to come: 0 samples where no count could exclude them), "n_max" (the last look).
    """

    label_set: tuple[int, ...]
    counts: np.ndarray
    samples: int
    looks: tuple[int, ...]
    beta_test: float
    reason: str


def conformal_looks(n_max: int, first_look: int = 64) -> tuple[int, ...]:
    """Sample sizes at which :func:`sequential_label_set` looks: ``first_look`` doubling up to
    ``n_max`` (the last look is ``n_max``)."""
    check_count(n_max, "n_max")
    check_count(first_look, "first_look")
    looks, n = [], min(int(first_look), int(n_max))
    while n < n_max:
        looks.append(n)
        n *= 2
    looks.append(int(n_max))
    return tuple(looks)


def look_batches(n_max: int, batch_size: int, samples: int,
                 first_look: int = 64) -> tuple[int, ...]:
    """The batches (their sizes, in order) in which :func:`sequential_label_set` draws its
    first ``samples`` samples (whole looks: those of the looks up to ``samples``), e.g. to
    draw their noise ahead (:meth:`~drake_cert.certification.sampler.SmoothedModel.draw_ahead`)."""
    check_count(batch_size, "batch_size")
    batches, drawn = [], 0
    for look in conformal_looks(n_max, first_look):
        if look > samples:
            break
        step, drawn = look - drawn, look
        batches += [batch_size] * (step // batch_size) + ([step % batch_size] if step % batch_size
                                                           else [])
    return tuple(batches)


@dataclasses.dataclass(frozen=True)
class LabelSetStopping:
    """When :func:`sequential_label_set` looks and stops (a stopping rule: no guarantee rests
    on it)."""

    first_look: int = 64  # samples at the first look, doubling up to n_max
    settle_level: float = 0.01  # level of the lower bounds that settle the range's ends
    # Futility: stop once both end labels, at their vote shares lowered by this many standard
    # errors, would still be in the set at n_max (None: never stop for futility).
    futility_z: float | None = 1.0


def expected_to_stay(counts: np.ndarray, drawn: int, n_max: int, level: float,
                     thresholds: np.ndarray, z: float) -> np.ndarray:
    """Which labels would still be in the set at ``n_max`` samples if their vote shares stayed
    at the present ones lowered by ``z`` standard errors (a forecast for the stopping rule,
    not a bound: :func:`labels_that_stay` is the exact "whatever the votes" version)."""
    share = np.asarray(counts, dtype=float) / drawn
    pessimistic = np.clip(share - z * np.sqrt(share * (1.0 - share) / drawn), 0.0, 1.0)
    return clopper_pearson_one_sided(np.floor(pessimistic * n_max).astype(np.int64), n_max,
                                     level)[1] >= thresholds


def sequential_label_set(classifier: SmoothedClassifier, x: torch.Tensor,
                         calibration: RobustConformalCalibration, eps: float, n_max: int,
                         batch_size: int, *, seed: int | None = None,
                         stopping: LabelSetStopping | None = None) -> ConformalDecision:
    """The robust conformal label set ``C(x')`` at the observed frame ``x`` (budget ``eps``),
    drawing samples only until the set's label range is decided (DESIGN 3.6, 3.7).

    At looks fixed in advance (:func:`conformal_looks`) each label's Clopper-Pearson upper
    bound is taken at ``beta_test / J`` for J looks, so the TRUE label's bound holds at every
    look at once with probability at least ``1 - beta_test`` (union bound over the looks; the
    other labels' bounds need not hold: a label wrongly kept only widens the set). Step (d) of
    the module's argument therefore holds at whichever look it stops, and the coverage stays
    ``1 - alpha_total``. It stops at the first look where the set's range is one label, or
    where both end labels of the range have a lower bound (at ``settle_level``; a stopping
    rule only, no guarantee rests on it) above their threshold, or where both end labels are
    expected to stay in the set by ``n_max`` at their present shares (:func:`expected_to_stay`,
    also a stopping rule only), or where the range is every label and neither end can leave it
    by ``n_max`` (:func:`labels_that_stay`; before the first sample where no count could
    exclude them: the envelope, free), or at ``n_max``.
    ``stopping``: ``first_look``, ``settle_level`` and ``futility_z``
    (:class:`LabelSetStopping`).
    """
    stopping = stopping or LabelSetStopping()
    first_look, settle_level = stopping.first_look, stopping.settle_level
    check_count(batch_size, "batch_size")
    check_alpha(settle_level, "settle_level")
    z = stopping.futility_z
    if z is not None and not (isinstance(z, (int, float)) and math.isfinite(z) and z >= 0):
        raise CertificationError(f"futility_z = {z!r} must be a finite number >= 0 or None")
    if not (math.isfinite(eps) and eps >= 0):
        raise CertificationError(f"eps = {eps!r} must be a finite number >= 0")
    if classifier.num_classes != calibration.num_classes:
        raise CertificationError(f"a classifier over {classifier.num_classes} labels with a "
                                 f"calibration over {calibration.num_classes}")
    looks = conformal_looks(n_max, first_look)
    level = calibration.beta_test / len(looks)
    k = calibration.num_classes
    thresholds = np.array([calibration.threshold(lab, eps) for lab in range(k)])
    counts = np.zeros(k, dtype=np.int64)
    gen = classifier.stream(seed)  # with any noise drawn ahead for it
    members, reason = np.zeros(k, dtype=bool), "n_max"
    if labels_that_stay(counts, n_max, level, thresholds)[[0, k - 1]].all():
        members, reason, looks_left = np.ones(k, dtype=bool), "fixed", ()
    else:
        looks_left = looks
    for look in looks_left:
        drawn = int(counts.sum())
        counts += classifier.sample_counts(x, look - drawn, batch_size, gen)
        up = clopper_pearson_one_sided(counts, look, level)[1]
        members = up >= thresholds
        inside = np.flatnonzero(members)
        if len(inside) == 0:
            continue
        lo, hi = int(inside[0]), int(inside[-1])
        if lo == hi:
            reason = "narrowest"
            break
        if lo == 0 and hi == k - 1 and \
                labels_that_stay(counts, n_max, level, thresholds)[[lo, hi]].all():
            reason = "fixed"
            break
        low = clopper_pearson_one_sided(counts[[lo, hi]], look, settle_level)[0]
        if low[0] >= thresholds[lo] and low[1] >= thresholds[hi]:
            reason = "settled"
            break
        if z is not None and look < n_max and expected_to_stay(
                counts, look, n_max, level, thresholds, z)[[lo, hi]].all():
            reason = "futile"
            break
    return ConformalDecision(tuple(int(i) for i in np.flatnonzero(members)), counts,
                             int(counts.sum()), looks, float(calibration.beta_test), reason)


def labels_that_stay(counts: np.ndarray, n_max: int, level: float,
                     thresholds: np.ndarray) -> np.ndarray:
    """Which labels are in the set at every look up to ``n_max`` whatever the votes still to
    come: a label's upper bound only falls while samples come without its votes, and with its
    present count at ``n_max`` samples it is still at its threshold."""
    return clopper_pearson_one_sided(np.asarray(counts), n_max, level)[1] >= thresholds


@dataclasses.dataclass(frozen=True)
class ConformalInterval(StiffnessBounds):
    """Robust conformal stiffness interval at an observed frame (N/rad).

    ``label_set`` is C(x') (label names), ``labels`` the contiguous friction range whose hull
    is the interval (the whole family when C(x') is empty), ``alpha_total`` the guaranteed
    miscoverage.
    """

    label_set: tuple[str, ...]
    labels: tuple[str, ...]
    stiffness_lo_n_per_rad: float
    stiffness_hi_n_per_rad: float
    alpha_total: float


def conformal_interval(counts: Sequence[int] | np.ndarray | ClassCertificate | ConformalDecision,
                       calibration: RobustConformalCalibration, table, preset: str, eps: float,
                       label_names: Sequence[str] | None = None) -> ConformalInterval:
    """The robust conformal stiffness interval at an observed frame (see module doc).

    ``counts`` are the n estimation votes at the observed frame (or a
    :class:`ClassCertificate`, whose counts are used: the same samples serve both intervals),
    or a :class:`ConformalDecision` (its label set, decided sequentially).
    The label set is widened to the contiguous friction range from its first to its last
    label (presets list labels in friction order) and the interval is that range's hull.
    """
    decided = counts.label_set if isinstance(counts, ConformalDecision) else None
    if isinstance(counts, ClassCertificate):
        counts = counts.counts
    names = list(label_names) if label_names is not None else list(table.preset(preset).labels)
    family = list(table.preset(preset).labels)
    if len(names) != calibration.num_classes:
        raise CertificationError(f"{len(names)} label names for a calibration over "
                                 f"{calibration.num_classes} labels")
    members = decided if decided is not None else calibration.label_set(counts, eps)
    chosen = [names[i] for i in members]
    missing = [c for c in chosen if c not in family]
    if missing:
        raise CertificationError(f"labels {missing} are not in preset {preset!r} ({family})")
    if chosen:
        positions = sorted(family.index(c) for c in chosen)
        span = family[positions[0]:positions[-1] + 1]
    else:
        span = family
    lo, hi = table.hull(span)
    return ConformalInterval(tuple(chosen), tuple(span), float(lo), float(hi),
                             calibration.alpha_total)
