"""The design table: one design per contiguous label range of each preset (DESIGN 5.4).

Ranges are deduplicated by their label tuple across presets (``sunny`` appears in three
presets, it gets one design). Labels with equal stiffness intervals are not merged, because
their friction differs (grip condition); they do share the interval's gain LMI and the
evaluations of the interval-only conditions.
"""

import dataclasses
import math
from collections.abc import Callable, Iterable

import numpy as np

from drake_cert.config import ConditionsTable, Settings, VehicleParams
from drake_cert.errors import ConfigError, InfeasibleDesign
from drake_cert.synthesis.conditions import (
    grip_speed_limit_mps,
    tire_stiffness_lo,
    vehicle_speed_limit_mps,
)
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.synthesis.gains import synthesize_state_feedback
from drake_cert.synthesis.joint_gains import (
    GAIN_SYNTHESES,
    JOINT,
    gain_box,
    solve_common_lyapunov_gains,
)
from drake_cert.synthesis.speed import IntervalEvaluator, search_speed

GAIN_LMI = "gain_lmi"  # failed_condition when no k_m exists for the interval
JOINT_REPORT = "joint_report"  # DesignCache.joint key: the JointSolve of the joint program


def design_label_ranges(conditions: ConditionsTable) -> list[tuple[str, ...]]:
    """Every contiguous label range of every preset, first occurrence order, no duplicates.

    A range is a run of consecutive labels in the preset's friction order, grippiest first,
    singles and the whole family included. These are the label ranges "the conditions define":
    the run time selects among their designs, and ``drake_cert.synthesis.verify.completeness_check``
    requires a design for each one.
    """
    seen: dict[tuple[str, ...], None] = {}
    for preset in conditions.presets:
        for labels in conditions.contiguous_ranges(preset.name):
            seen.setdefault(tuple(labels), None)
    return list(seen)


def friction_lower_bound(conditions: ConditionsTable, preset: str,
                         interval: tuple[float, float]) -> float:
    """Least friction a stiffness interval (N/rad) can mean in a preset (regression designs).

    DESIGN 5.3d: every label whose stiffness interval meets ``[C_lo, C_hi]`` could be the true
    condition, so take the least friction among them (mapping C_lo alone through the table
    could pick a grippier label); if none meets it, the least friction of the whole preset.
    """
    lo, hi = interval
    conds = conditions.preset_conditions(preset)
    meeting = [c.friction_mu for c in conds
               if c.stiffness_lo_n_per_rad <= hi and lo <= c.stiffness_hi_n_per_rad]
    return min(meeting) if meeting else min(c.friction_mu for c in conds)


@dataclasses.dataclass(frozen=True)
class LabelRange:
    """What one design is synthesized for: the label names (grippiest first; [] for a
    regression interval), their stiffness interval (N/rad) and least friction."""

    labels: tuple | list
    interval: tuple[float, float]  # (C_lo, C_hi) of this vehicle's tires, N/rad
    friction_mu_lo: float


@dataclasses.dataclass
class DesignCache:
    """Per-interval gain and condition evaluations shared between designs, and the joint
    gains (:func:`joint_design_gains`). One cache serves one vehicle, conditions table and
    settings."""

    evaluators: dict = dataclasses.field(default_factory=dict)
    failures: dict = dataclasses.field(default_factory=dict)
    joint: dict = dataclasses.field(default_factory=dict)
    # designs whose filter gain was capped so their family's L1 loops share a matrix:
    # (labels, filter gain before, after, safe speed before, after), in that order
    capped: list = dataclasses.field(default_factory=list)


def joint_solve_report(cache: DesignCache) -> dict | None:
    """How the joint program was solved and accepted (solver status, rescaled, the decay rate
    its matrix proves, cond X) for the design file's provenance; None when it was not run."""
    solve = cache.joint.get(JOINT_REPORT)
    return solve.as_dict() if solve is not None else None


def joint_design_gains(vehicle: VehicleParams, conditions: ConditionsTable, settings: Settings,
                       cache: DesignCache | None = None) -> dict | None:
    """Every label range's ``(k_m, gain_speed_max_mps)`` from one LMI with a common Lyapunov
    matrix (:mod:`drake_cert.synthesis.joint_gains`), on the vehicle's tires; None when that LMI is
    infeasible. Ranges with the same gain box share one gain. Cached in ``cache``."""
    if cache is not None and JOINT in cache.joint:
        return cache.joint[JOINT]
    scaled = conditions.with_stiffness_scale(vehicle.tire_stiffness_scale)
    ranges = design_label_ranges(conditions)
    boxes = {r: gain_box(scaled.hull(r), scaled.least_friction(r), settings) for r in ranges}
    distinct = list(dict.fromkeys(boxes.values()))
    solve = solve_common_lyapunov_gains(vehicle, distinct, settings) if distinct else None
    gains = solve.gains if solve is not None else []
    out = None
    if gains is not None:
        by_box = {b: (k, b.speed_hi_mps) for b, k in zip(distinct, gains, strict=True)}
        out = {r: by_box[b] for r, b in boxes.items()}
    if cache is not None:
        cache.joint[JOINT] = out
        cache.joint[JOINT_REPORT] = solve
    return out


SLIP_BOUND_FRACTIONS = (1.0, 0.8, 0.6, 0.4, 0.2)  # of normalised_slip_max, tried in order


def slip_bound_candidates(settings: Settings) -> list[float]:
    """Normalised slip bounds a design may admit, largest first (DESIGN 5.3d)."""
    return [f * settings.synthesis.normalised_slip_max for f in SLIP_BOUND_FRACTIONS]


def check_design_inputs(interval, friction_mu_lo) -> None:
    """ConfigError unless ``interval`` is (C_lo, C_hi) with 0 < C_lo <= C_hi finite (N/rad)
    and 0 < ``friction_mu_lo`` <= 2 (the range the conditions file accepts)."""
    try:
        lo, hi = (float(v) for v in interval)
    except (TypeError, ValueError):
        raise ConfigError(f"stiffness interval {interval!r} must be two numbers "
                          "(C_lo, C_hi) in N/rad") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
        raise ConfigError(f"stiffness interval ({lo!r}, {hi!r}) must satisfy 0 < C_lo <= C_hi "
                          "(finite, N/rad)")
    try:
        mu = float(friction_mu_lo)
    except (TypeError, ValueError):
        raise ConfigError(f"friction_mu_lo = {friction_mu_lo!r} must be a number") from None
    if not (math.isfinite(mu) and 0 < mu <= 2):
        raise ConfigError(f"friction_mu_lo = {friction_mu_lo!r} must be in (0, 2]")


def synthesize_design(vehicle: VehicleParams, interval: tuple[float, float],
                      friction_mu_lo: float, settings: Settings, labels=(),
                      cache: DesignCache | None = None, gain=None) -> ControllerDesign:
    """Gains, filter gain and safe speed for one stiffness interval (N/rad) and friction.

    ``interval`` is the cornering stiffness of THIS vehicle's tires on the road (the design
    model's C). For a label range of the conditions table on a vehicle whose tires differ from
    the table's (``tire_stiffness_scale`` != 1), :func:`synthesize_label_range` applies the
    vehicle's tires and gives the design the command line writes.

    ``labels``: the label names of the range ([] for a regression interval). The tire slip
    bound z_b widens the certified interval to ``[C_lo (1 - z_b + z_b^2/3), C_hi]`` (the
    Fiala secant stiffness) and caps the grip speed; the bounds of
    :func:`slip_bound_candidates` are tried largest first, and the fastest design is kept
    (the search stops once a design reaches the grip speed of its bound, which only falls
    with smaller bounds). With no safe speed at any bound, the design at the smallest bound
    says which condition failed. Raises :class:`ConfigError` for an interval that is not
    two finite numbers 0 < C_lo <= C_hi, or a friction outside (0, 2].

    ``gain``: ``(k_m, gain_speed_max_mps)`` fixed beforehand (the joint synthesis of
    :func:`joint_design_gains`), certified on a box that holds every slip bound's; None
    (default) solves this interval's own gain LMI (5.1).
    """
    check_design_inputs(interval, friction_mu_lo)
    cache = cache if cache is not None else DesignCache()
    syn = settings.synthesis
    best = None
    for slip_bound in slip_bound_candidates(settings):
        design = design_for_slip_bound(vehicle, LabelRange(labels, interval, friction_mu_lo),
                                       settings, cache, slip_bound, gain)
        if (best is None or not best.has_safe_speed
                or (design.has_safe_speed and design.speed_mps > best.speed_mps)):
            best = design
        # grip and the vehicle limits cap the speed; smaller slip bounds only lower the first
        top_speed = min(vehicle_speed_limit_mps(vehicle, settings)[0], grip_speed_limit_mps(
            friction_mu_lo, syn.design_radius_m, slip_bound, syn.lateral_accel_fraction))
        if design.has_safe_speed and design.speed_mps >= top_speed - syn.speed_grid_step_mps / 16:
            break
    return best


def design_for_slip_bound(vehicle: VehicleParams, label_range: LabelRange, settings: Settings,
                          cache: DesignCache, slip_bound: float,
                          gain=None) -> ControllerDesign:
    """:func:`synthesize_design` at one normalised slip bound z_b, for ``label_range``
    (:class:`LabelRange`: labels, stiffness interval, least friction).

    Every condition is evaluated on the certified interval ``[C_lo ratio(z_b), C_hi]``
    (:func:`drake_cert.synthesis.conditions.tire_stiffness_lo`), whose midpoint is ``C_hat``. An
    interval whose gain LMI is infeasible gives speed 0, ``failed_condition = 'gain_lmi'``, ``k_m =
    0``. ``gain``: a fixed ``(k_m, gain_speed_max_mps)`` instead of the interval's own LMI.
    """
    labels, interval = label_range.labels, label_range.interval
    friction_mu_lo = label_range.friction_mu_lo
    label_interval = (float(interval[0]), float(interval[1]))
    searched = LabelRange(labels, label_interval, friction_mu_lo)
    certified = (tire_stiffness_lo(label_interval[0], slip_bound), label_interval[1])
    c_hat = 0.5 * (certified[0] + certified[1])
    law = settings.controller.adaptation_law
    if gain is not None:
        evaluator = _fixed_gain_evaluator(vehicle, settings, cache, certified, gain)
        return _searched_design(evaluator, searched, c_hat, slip_bound, law)
    if certified not in cache.evaluators and certified not in cache.failures:
        try:
            k_m, v_hi = synthesize_state_feedback(vehicle, certified, settings.synthesis)
            cache.evaluators[certified] = IntervalEvaluator(vehicle, settings, certified, k_m,
                                                            v_hi)
        except InfeasibleDesign as e:
            cache.failures[certified] = str(e)
    if certified in cache.failures:
        return ControllerDesign(list(labels), label_interval[0], label_interval[1], c_hat,
                                float(friction_mu_lo), [0.0] * 4, 0.0,
                                settings.synthesis.filter_gain_max, 0.0, GAIN_LMI, {},
                                float(slip_bound), law)
    return _searched_design(cache.evaluators[certified], searched, c_hat, slip_bound, law)


def _fixed_gain_evaluator(vehicle: VehicleParams, settings: Settings, cache: DesignCache,
                          certified, gain) -> IntervalEvaluator:
    """The cached :class:`IntervalEvaluator` of ``certified`` with the fixed ``gain``
    ``(k_m, gain_speed_max_mps)``."""
    k_fixed, v_fixed = np.asarray(gain[0], dtype=float), float(gain[1])
    key = (certified, tuple(k_fixed), v_fixed)
    if key not in cache.evaluators:
        cache.evaluators[key] = IntervalEvaluator(vehicle, settings, certified, k_fixed, v_fixed)
    return cache.evaluators[key]


def _searched_design(evaluator: IntervalEvaluator, label_range: LabelRange, c_hat,
                     slip_bound, law, filter_gain_cap: float | None = None) -> ControllerDesign:
    """The design of ``label_range`` with the evaluator's gains and the speed search's filter
    gain (at most ``filter_gain_cap``) and safe speed at ``slip_bound``."""
    labels, label_interval = label_range.labels, label_range.interval
    friction_mu_lo = label_range.friction_mu_lo
    result = search_speed(evaluator, friction_mu_lo, slip_bound, filter_gain_cap)
    return ControllerDesign(
        labels=list(labels),
        stiffness_lo_n_per_rad=label_interval[0],
        stiffness_hi_n_per_rad=label_interval[1],
        nominal_stiffness_n_per_rad=c_hat,
        friction_mu_lo=float(friction_mu_lo),
        k_m=[float(x) for x in evaluator.k_m],
        gain_speed_max_mps=evaluator.gain_speed_max_mps,
        filter_gain=result.filter_gain,
        speed_mps=result.speed_mps,
        failed_condition=result.failed_condition,
        margins={k: float(v) for k, v in result.margins.items()},
        tire_slip_bound=float(slip_bound),
        certified_law=law,
        speed_limited_by=result.limited_by if result.speed_mps > 0.0 else "",
    )


def synthesize_label_range(vehicle: VehicleParams, conditions: ConditionsTable, labels,
                           settings: Settings, cache: DesignCache | None = None,
                           gains: str = JOINT) -> ControllerDesign:
    """The design ``drake-cert synthesize`` writes for the label range ``labels`` (names,
    grippiest first, e.g. ``["rain", "snow"]``) and this vehicle: the range's stiffness hull in
    the conditions table times the vehicle's ``tire_stiffness_scale`` (the tires the vehicle
    has), and the range's least friction. :class:`ConfigError` names the ranges the table
    defines when ``labels`` is not one of them.

    :func:`synthesize_design` takes the interval of the vehicle's own tires; this function
    applies the vehicle file's tires to the road conditions, as the design table does.

    ``gains``: ``"joint"`` (default: the gain from the LMI shared by every range of
    ``conditions``, :func:`joint_design_gains`, so the design equals the table's) or
    ``"separate"`` (the range's own gain LMI). Joint falls back to separate, for every range
    alike, when the joint LMI is infeasible.
    """
    labels = tuple(labels)
    ranges = design_label_ranges(conditions)
    if labels not in ranges:
        raise ConfigError(f"label range {'+'.join(labels) or '(empty)'} is not one the "
                          f"conditions table defines (contiguous runs of a preset's labels, "
                          f"grippiest first): {', '.join('+'.join(r) for r in ranges)}")
    if gains not in GAIN_SYNTHESES:
        raise ConfigError(f"gains = {gains!r} must be one of {', '.join(GAIN_SYNTHESES)}")
    cache = cache if cache is not None else DesignCache()
    joint = joint_design_gains(vehicle, conditions, settings, cache) if gains == JOINT else None
    scaled = conditions.with_stiffness_scale(vehicle.tire_stiffness_scale)
    return synthesize_design(vehicle, scaled.hull(labels), scaled.least_friction(labels),
                             settings, labels, cache, joint[labels] if joint else None)


def synthesize_table(vehicle: VehicleParams, conditions: ConditionsTable, settings: Settings,
                     progress: Callable[[Iterable], Iterable] | None = None,
                     gains: str = JOINT, cache: DesignCache | None = None
                     ) -> list[ControllerDesign]:
    """One design per label range (see :func:`design_label_ranges`), in that order.

    ``progress`` wraps the iteration over label ranges (e.g. ``tqdm``). The label intervals
    are the table's times ``vehicle.tire_stiffness_scale`` (friction unchanged). ``gains``:
    ``"joint"`` (default; one common Lyapunov matrix for every design, docs/design.md 5.6,
    falling back to ``"separate"`` when that LMI is infeasible) or ``"separate"``.
    ``cache``: a fresh :class:`DesignCache` to read afterwards (``joint_solve_report``).
    """
    cache = cache if cache is not None else DesignCache()
    ranges = design_label_ranges(conditions)
    designs = [synthesize_label_range(vehicle, conditions, labels, settings, cache, gains)
               for labels in (progress(ranges) if progress is not None else ranges)]
    return with_switchable_l1_loops(vehicle, conditions, settings, designs, cache)


FILTER_GAIN_CAP_FRACTIONS = (1.0, 0.95, 0.9, 0.85, 0.8, 0.7, 0.6, 0.5)  # of filter_gain_max


def with_switchable_l1_loops(vehicle: VehicleParams, conditions: ConditionsTable,
                             settings: Settings, designs: list[ControllerDesign],
                             cache: DesignCache) -> list[ControllerDesign]:
    """``designs`` with the filter gains lowered where that gives a preset's L1 loops a common
    matrix (docs/design.md 5.6 (b)).

    Where the L1 condition binds, the speed search raises a filter gain past
    ``filter_gain_max`` up to its sample-period limit (5.3a). A fast filter in one design and a
    slow one in another can leave a preset's L1 loops with no common matrix, and their switching
    uncertified. For such a preset (piecewise-constant law) the raised designs are searched again
    with the filter gain capped at the fractions :data:`FILTER_GAIN_CAP_FRACTIONS` of
    ``filter_gain_max``, largest first, until the loops share a matrix: a slower safe speed
    where the L1 condition binds, for a switching certificate at any rate. Each change is
    recorded in ``cache.capped``; when no cap helps the designs are kept, and the preset's
    certificate gives its L1 loops one matrix per design with the average dwell they need
    (:func:`drake_cert.synthesis.loop_switching.loop_dwell_matrices`), or none.
    """
    from drake_cert.synthesis.conditions import PIECEWISE_CONSTANT
    from drake_cert.synthesis.loop_switching import loop_lyapunov_matrix
    from drake_cert.synthesis.switching import design_key, switching_families

    if settings.controller.adaptation_law != PIECEWISE_CONSTANT:
        return designs
    syn = settings.synthesis

    def share_a_matrix(members) -> bool:
        return loop_lyapunov_matrix(vehicle, members, syn.speed_min_mps, PIECEWISE_CONSTANT,
                                    syn.lmi_margin) is not None

    by_key = {design_key(d): d for d in designs}
    for _, members in switching_families(designs, conditions):
        covered = [by_key[design_key(d)] for d in members if d.has_safe_speed]
        raised = [d for d in covered if d.filter_gain > syn.filter_gain_max * (1.0 + 1e-9)]
        if len(covered) < 2 or not raised or share_a_matrix(covered):
            continue
        for fraction in FILTER_GAIN_CAP_FRACTIONS:
            capped = {design_key(d): _capped_design(vehicle, settings, d, cache,
                                                    fraction * syn.filter_gain_max)
                      for d in raised}
            trial = [capped.get(design_key(d), d) for d in covered]
            if all(d.has_safe_speed for d in capped.values()) and share_a_matrix(trial):
                for key, d in capped.items():
                    cache.capped.append((by_key[key].labels, by_key[key].filter_gain,
                                         d.filter_gain, by_key[key].speed_mps, d.speed_mps))
                    by_key[key] = d
                break
    return [by_key[design_key(d)] for d in designs]


def _capped_design(vehicle: VehicleParams, settings: Settings, design: ControllerDesign,
                   cache: DesignCache, cap: float) -> ControllerDesign:
    """``design`` searched again with its gain, slip bound and interval, the filter gain at
    most ``cap`` (1/s)."""
    evaluator = _fixed_gain_evaluator(vehicle, settings, cache, design.certified_interval,
                                      (design.k_m_array, design.gain_speed_max_mps))
    label_range = LabelRange(tuple(design.labels), (design.stiffness_lo_n_per_rad,
                                                    design.stiffness_hi_n_per_rad),
                             design.friction_mu_lo)
    return _searched_design(evaluator, label_range, design.nominal_stiffness_n_per_rad,
                            design.tire_slip_bound, design.certified_law, cap)
