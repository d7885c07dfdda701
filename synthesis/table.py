"""The design table: one design per contiguous label range of each preset (DESIGN 5.4).

Ranges are deduplicated by their label tuple across presets (``sunny`` appears in three
presets, it gets one design). Labels with equal stiffness intervals are not merged, because
their friction differs (grip condition); they do share the interval's gain LMI and the
evaluations of the interval-only conditions.
"""

import dataclasses
from collections.abc import Callable, Iterable

from drake_cert.config import ConditionsTable, Settings, VehicleParams
from drake_cert.errors import InfeasibleDesign
from synthesis.design import ControllerDesign
from synthesis.gains import synthesize_state_feedback
from synthesis.speed import IntervalEvaluator, search_speed

GAIN_LMI = "gain_lmi"  # failed_condition when no k_m exists for the interval


def design_label_ranges(conditions: ConditionsTable) -> list[tuple[str, ...]]:
    """Every contiguous label range of every preset, first occurrence order, no duplicates."""
    seen: dict[tuple[str, ...], None] = {}
    for preset in conditions.presets:
        for labels in conditions.contiguous_ranges(preset.name):
            seen.setdefault(tuple(labels), None)
    return list(seen)


def friction_lower_bound(conditions: ConditionsTable, preset: str,
                         interval: tuple[float, float]) -> float:
    """Least friction a stiffness interval (N/rad) can mean in a preset (regression designs).

    DESIGN 5.3d maps C_lo through the condition table; soundly: every label whose stiffness
    interval meets ``[C_lo, C_hi]`` could be the true condition, so take the least friction
    among them; if none meets it, the least friction of the whole preset.
    """
    lo, hi = interval
    conds = conditions.preset_conditions(preset)
    meeting = [c.friction_mu for c in conds
               if c.stiffness_lo_n_per_rad <= hi and lo <= c.stiffness_hi_n_per_rad]
    return min(meeting) if meeting else min(c.friction_mu for c in conds)


@dataclasses.dataclass
class DesignCache:
    """Per-interval gain and condition evaluations shared between designs."""

    evaluators: dict = dataclasses.field(default_factory=dict)
    failures: dict = dataclasses.field(default_factory=dict)


def synthesize_design(vehicle: VehicleParams, interval: tuple[float, float],
                      friction_mu_lo: float, settings: Settings, labels=(),
                      cache: DesignCache | None = None) -> ControllerDesign:
    """Gains, filter gain and safe speed for one stiffness interval (N/rad) and friction.

    ``labels``: the label names of the range ([] for a regression interval). A range whose gain
    LMI is infeasible gets speed 0, ``failed_condition = 'gain_lmi'`` and ``k_m = 0``.
    """
    cache = cache if cache is not None else DesignCache()
    interval = (float(interval[0]), float(interval[1]))
    c_hat = 0.5 * (interval[0] + interval[1])
    if interval not in cache.evaluators and interval not in cache.failures:
        try:
            k_m, v_hi = synthesize_state_feedback(vehicle, interval, settings.synthesis)
            cache.evaluators[interval] = IntervalEvaluator(vehicle, settings, interval, k_m, v_hi)
        except InfeasibleDesign as e:
            cache.failures[interval] = str(e)
    if interval in cache.failures:
        return ControllerDesign(list(labels), interval[0], interval[1], c_hat,
                                float(friction_mu_lo), [0.0] * 4, 0.0,
                                settings.synthesis.filter_gain_max, 0.0, GAIN_LMI, {})
    evaluator = cache.evaluators[interval]
    result = search_speed(evaluator, friction_mu_lo)
    return ControllerDesign(
        labels=list(labels),
        stiffness_lo_n_per_rad=interval[0],
        stiffness_hi_n_per_rad=interval[1],
        nominal_stiffness_n_per_rad=c_hat,
        friction_mu_lo=float(friction_mu_lo),
        k_m=[float(x) for x in evaluator.k_m],
        gain_speed_max_mps=evaluator.gain_speed_max_mps,
        filter_gain=result.filter_gain,
        speed_mps=result.speed_mps,
        failed_condition=result.failed_condition,
        margins={k: float(v) for k, v in result.margins.items()},
    )


def synthesize_table(vehicle: VehicleParams, conditions: ConditionsTable, settings: Settings,
                     progress: Callable[[Iterable], Iterable] | None = None
                     ) -> list[ControllerDesign]:
    """One design per label range (see :func:`design_label_ranges`), in that order.

    ``progress`` wraps the iteration over label ranges (e.g. ``tqdm``).
    """
    cache = DesignCache()
    designs = []
    ranges = design_label_ranges(conditions)
    for labels in (progress(ranges) if progress is not None else ranges):
        designs.append(synthesize_design(vehicle, conditions.hull(labels),
                                         conditions.least_friction(labels), settings,
                                         labels, cache))
    return designs
