"""Run-time stiffness intervals at an observed frame (DESIGN 3): the classification interval
from a set certificate, and the regression interval from median bounds and a conformal beta.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

from drake_cert.certification.classifier import ClassCertificate, SequentialDecision
from drake_cert.errors import CertificationError


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


INSIDE_N_PER_RAD = 1.0  # how far inside a design's ends a sequential median decision stays


def median_candidates(designs, beta: float,
                      envelope: tuple[float, float]) -> list[tuple[float, float]]:
    """Candidate intervals for a sequential decision on the smoothed median
    (:meth:`MedianSmoothedRegressor.decide`), most preferred first: per design narrower than
    the envelope (narrowest, then slowest, first, as the fixed-n interval picks), the interval
    its run-time interval ``[lower - beta, upper + beta]`` (clipped to the envelope,
    :func:`runtime_interval`) stays inside when the median bounds do: its ends moved inward by
    beta and :data:`INSIDE_N_PER_RAD` more (so that the run-time interval never holds a
    boundary the design shares with a label of less friction), or open where the design
    reaches the envelope's end. Designs narrower than 2 beta have none. N/rad."""
    env_lo, env_hi = (float(e) for e in envelope)
    if not math.isfinite(beta):
        return []
    out = []
    for d in sorted(designs, key=lambda d: (d.stiffness_hi_n_per_rad - d.stiffness_lo_n_per_rad,
                                            d.speed_mps)):
        lo, hi = d.stiffness_lo_n_per_rad, d.stiffness_hi_n_per_rad
        if lo <= env_lo and hi >= env_hi:
            continue  # the envelope: what an abstention gives anyway
        inside = beta + INSIDE_N_PER_RAD
        c = (lo + inside if lo > env_lo else -math.inf, hi - inside if hi < env_hi else math.inf)
        if c[0] <= c[1] and c not in out:
            out.append(c)
    return out


class StiffnessBounds:
    """``interval`` and ``width_n_per_rad`` of a run-time interval with fields
    ``stiffness_lo_n_per_rad`` and ``stiffness_hi_n_per_rad`` (N/rad)."""

    @property
    def interval(self) -> tuple[float, float]:
        return (self.stiffness_lo_n_per_rad, self.stiffness_hi_n_per_rad)

    @property
    def width_n_per_rad(self) -> float:
        return self.stiffness_hi_n_per_rad - self.stiffness_lo_n_per_rad


@dataclasses.dataclass(frozen=True)
class RuntimeCertificate(StiffnessBounds):
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
    return _preference_key(cert.stiffness_lo_n_per_rad, cert.stiffness_hi_n_per_rad,
                           len(cert.labels))


def _preference_key(lo: float, hi: float, labels: int) -> tuple[float, float, int]:
    """Narrowest hull first; ties: the lower C_lo, then the fewer labels (equal hulls)."""
    return (hi - lo, lo, labels)


def candidate_ranges(table, preset: str,
                     label_names: Sequence[str] | None = None) -> list[tuple[int, ...]]:
    """The candidates of a sequential decision (:meth:`SmoothedClassifier.decide`): every
    contiguous label range of the preset but the whole family (the fallback), as label-index
    tuples, in the order :func:`runtime_classification_interval` prefers them (narrowest
    hull, then the lower C_lo, then the fewer labels). Depends on the table only, never on
    the noise. ``[c for c in ranges if a in c]`` are those holding a label a."""
    names = list(label_names) if label_names is not None else list(table.preset(preset).labels)
    index = {name: i for i, name in enumerate(names)}
    family = tuple(table.preset(preset).labels)
    ranked = []
    for rng in table.contiguous_ranges(preset):
        if len(rng) == len(family):
            continue
        if any(name not in index for name in rng):
            raise CertificationError(f"preset {preset!r} label {rng} not among the classifier's "
                                     f"labels {names}")
        lo, hi = table.hull(rng)
        ranked.append((_preference_key(lo, hi, len(rng)),
                       tuple(sorted(index[name] for name in rng))))
    return [members for _, members in sorted(ranked)]


def runtime_decision_interval(decision: SequentialDecision, table, preset: str,
                              label_names: Sequence[str] | None = None) -> RuntimeCertificate:
    """The run-time interval of a sequential decision at budget eps: the hull of the certified
    range's stiffness intervals, or the preset's envelope (``certified`` False) on abstain.

    Same guarantee as :func:`runtime_classification_interval`: with probability at least
    ``1 - alpha`` over the noise, ``g(x)`` of the clean frame lies in the range, and under the
    standing assumption the true stiffness lies in the hull.
    """
    names = list(label_names) if label_names is not None else list(table.preset(preset).labels)
    envelope = table.envelope(preset)
    if not decision.certified:
        return RuntimeCertificate(tuple(table.preset(preset).labels), envelope[0], envelope[1],
                                  0.0, False)
    chosen = {names[i] for i in decision.labels}
    labels = tuple(name for name in table.preset(preset).labels if name in chosen)
    lo, hi = table.hull(labels)
    return RuntimeCertificate(labels, lo, hi, decision.radius, True)
