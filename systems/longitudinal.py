"""Longitudinal motion: the car's speed follows the certified speed command (DESIGN 6.3-6.4).

Input ``decision`` (abstract; e.g. ``drake_cert.systems.certified_interval.Decision``): any
object with ``position_m`` (look point it applies from, m of arc length), ``speed_command_mps``
(0 = stop), ``design_index``, ``time_s`` and optionally ``look_m`` (default ``position_m``).
Continuous state ``[x, v]`` (m, m/s; a C++ ``SymbolicVectorSystem``); abstract state the
:class:`SpeedProfile`. Outputs (size 1): ``arc_length_m`` x (m), ``speed_mps`` max(v, 0),
``design_index`` (latest entry at or before x), ``speed_reference_mps`` v_ref(x) (m/s).
Parameters: the scenario's ``motion`` block (``max_decel_mps2``, ``max_accel_mps2``,
``initial_speed_mps``, ``stop_speed_mps``), ``camera.rate_hz``, the block's own
:class:`TrackingSettings` and the builder's :class:`ProfileDesigns`.

Profile update (camera rate, at :data:`OFFSET_FRACTION` 3/4 of the period): passed entries are
dropped but the one in force, an entry equal to its predecessor is not added, a command below
``stop_speed_mps`` is 0. Each decision on its own (a join table only): the road from the
previous look point q to this one gets the join of the two designs, and a decision at p
supersedes the entries at positions >= p. Decisions combined (``spans`` and ``window_m`` > 0):
the stretches within the window behind a new look get the span of
:func:`drake_cert.systems.decision_combination.counted_span`, sound while neither side of a
stretch holds more than ``tolerance`` wrong looks; past the newest look: the envelope
(tolerance 0: the newest decision's design).

Speed reference (a = ``envelope_decel_fraction`` a_dec, m = ``braking_margin_m``, f the
frontier, v_f = ``frontier_speed_mps``):
  ``v_ref(x) = min(c(x), min_{p_i > x} b(c_i, p_i - m - x), b(v_f, f - m - x))``,
  ``b(c, d) = sqrt(c^2 + 2 a max(d, 0))``; tracking law, ``dx/dt = max(v, 0)`` and
  ``dv/dt = clip(k (v_ref - v - v_creep [v_ref = 0]) + (dv_ref/dx) v, -a_dec, a_acc)``.
A look-ahead L carries ``v^2 <= v_f^2 + 2 a (L - m - (1.75 + j) T v)`` (T the camera period,
j = ``tolerance``; :func:`supported_speed_mps`, :func:`frontier_latency_s`), checked before
driving by ``drake_cert.systems.driving.check_look_ahead``. Why these hold: DESIGN 6.2-6.4.
"""

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence

import pydrake.symbolic as sym
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import Demultiplexer, SymbolicVectorSystem

from drake_cert.errors import ConfigError
from drake_cert.systems.decision_combination import LOOKS_PER_SIDE, is_within, stretch_spans
from drake_cert.systems.scenario import CameraSettings, MotionSettings

STOP_SPEED_MPS = 5.0  # DESIGN 2: below this the car is stopped (lateral dynamics frozen)
BRAKING_MARGIN_M = 2.0  # a command ahead is reached this far before its point (m)
ENVELOPE_DECEL_FRACTION = 0.9  # share of the braking authority the braking envelope plans with
MAX_LOOKS = 400  # recent decisions a combining profile keeps (the car at rest adds one a tick)
OFFSET_FRACTION = 0.75  # the profile update comes this share of a camera period after the frame


@dataclasses.dataclass(frozen=True)
class TrackingSettings:
    """The tracking law's and the braking envelope's own constants (not the scenario's)."""

    speed_gain_per_s: float = 2.0  # k: gain of the tracking law (1/s)
    braking_margin_m: float = BRAKING_MARGIN_M  # m: a command is reached this far before its point
    envelope_decel_fraction: float = ENVELOPE_DECEL_FRACTION  # a = this share of max_decel_mps2
    creep_speed_mps: float = 0.1  # v_creep: the target is this far below a stop command (m/s)


@dataclasses.dataclass(frozen=True)
class ProfileDesigns:
    """What the profile takes decisions in with, derived by the Diagram builder from the design
    table and the scenario (module docstring). Without one, each decision's command applies
    from its own point on and nothing is braked for at the frontier."""

    join: Mapping[tuple[int, int], int] | None = None  # design holding both of two designs
    design_speeds_mps: Sequence[float] | None = None  # safe speed of each design (m/s; 0: none)
    frontier_speed_mps: float | None = None  # braked for at the decided road's end; None: not
    spans: Sequence[tuple[int, int]] | None = None  # label span of each design: combine
    window_m: float = 0.0  # decisions are combined over this stretch (m; > 0 with spans)
    tolerance: int = 1  # wrong looks a side of a stretch may hold (the counting rule's j)
    looks_per_side: int = LOOKS_PER_SIDE  # most looks on each side of a stretch
    envelope_index: int | None = None  # the envelope design (needed to combine)


@dataclasses.dataclass(frozen=True)
class SpeedProfile:
    """Abstract state of :class:`LongitudinalMotion` (immutable; a new one per update).

    ``entries``: ``(position_m, speed_command_mps, design_index)`` sorted by position, the
    first at -inf. ``last_decision_time_s``: time of the last decision taken in (-inf if none).
    ``last_look_m``: the farthest look point of a decision taken in (the frontier: the road
    beyond it has no decision). ``looks``: ``(look point, design)`` of the decisions that can
    still pair with the next one (:meth:`with_combined_decision`).
    """

    entries: tuple[tuple[float, float, int], ...]
    last_decision_time_s: float = -math.inf
    last_look_m: float = -math.inf
    looks: tuple[tuple[float, int], ...] = ()  # (look point, design) of the recent decisions

    def in_force(self, arc_length_m: float) -> tuple[float, int]:
        """(command, design) of the latest entry with position <= x."""
        command, design = self.entries[0][1], self.entries[0][2]
        for position, c, d in self.entries:
            if position > arc_length_m:
                break
            command, design = c, d
        return command, design

    def with_decision(self, position_m: float, command_mps: float, design_index: int,
                      time_s: float, arc_length_m: float,
                      join: Callable[[int, int], tuple[float, int]] | None = None, *,
                      look_m: float | None = None) -> "SpeedProfile":
        """The profile after one decision, each decision on its own (see the module docstring).

        ``join(d_prev, d_new)``: the (command, design) that holds both designs' stiffness; when
        given, the road between the previous look point and this one (which no frame showed:
        a condition boundary may lie anywhere in it) gets the join of the designs on either
        side, from the previous look point on. ``look_m``: the look point of the frame behind
        the decision (default ``position_m``; a dwell-released request applies from the look
        point of the tick that first asked for it).
        """
        look = float(position_m if look_m is None else max(look_m, position_m))
        kept = [e for e in self.entries if e[0] < position_m]  # the -inf entry always stays
        q = self.last_look_m
        if join is not None and math.isfinite(q) and q < position_m:
            before = SpeedProfile(tuple(kept)).in_force(q)[1]
            gap = join(before, int(design_index))
            kept = [e for e in kept if e[0] < q]
            if (kept[-1][1], kept[-1][2]) != gap:
                kept.append((float(q), float(gap[0]), int(gap[1])))
        passed = [i for i, e in enumerate(kept) if e[0] <= arc_length_m]
        kept = kept[passed[-1]:]  # drop passed entries except the one in force
        if (kept[-1][1], kept[-1][2]) != (command_mps, design_index):
            kept.append((float(position_m), float(command_mps), int(design_index)))
        return SpeedProfile(tuple(kept), float(time_s), max(q, look))

    def with_combined_decision(self, look_m: float, design_index: int, time_s: float,
                               arc_length_m: float, *, rule: "CombinationRule"
                               ) -> "SpeedProfile":
        """The profile after one decision, combined with the decisions around it by the rule
        of :mod:`drake_cert.systems.decision_combination` (module docstring, "Decisions combined")
        with the designs and window of ``rule`` (:class:`CombinationRule`).
        """
        window_m, tolerance, looks_per_side = rule.window_m, rule.tolerance, rule.looks_per_side
        spans, design_of_span, command_of = rule.spans, rule.design_of_span, rule.command_of
        r, full = float(look_m), spans[int(rule.envelope_index)]
        looks = (*self.looks, (r, int(design_index)))
        looks = _recent_looks(looks, r - 2.0 * window_m)
        positions = sorted({lk[0] for lk in looks})
        # only stretches starting less than a window before r can pair with the new look
        first = next((k for k, q in enumerate(positions) if q > r - window_m), len(positions))
        spanned = sorted(((lk[0], spans[lk[1]]) for lk in looks), key=lambda lk: lk[0])
        new = stretch_spans(spanned, window_m=window_m, tolerance=tolerance, full=full,
                            looks_per_side=looks_per_side, first=first)
        start = new[0][0] if new else r
        kept = [e for e in self.entries if e[0] < start]
        for position, span in new:
            value = design_of_span[span]
            before = self.in_force(position)[1]
            if (is_within(span, spans[before]) and span != full
                    and command_of(value) < command_of(before)):
                value = before  # both hold; a narrower range need not be faster
            if not kept or (kept[-1][1], kept[-1][2]) != (command_of(value), value):
                # (kept is empty when the window reaches behind the entry in force at the car)
                kept.append((float(position), float(command_of(value)), int(value)))
        passed = [i for i, e in enumerate(kept) if e[0] <= arc_length_m]
        kept = kept[passed[-1]:] if passed else kept  # drop passed entries but the one in force
        return SpeedProfile(tuple(kept), float(time_s), max(self.last_look_m, r), looks=looks)


@dataclasses.dataclass(frozen=True)
class CombinationRule:
    """How :meth:`SpeedProfile.with_combined_decision` combines decisions (docs/design.md 6.3).

    ``spans[d]``: the label span of design d in friction order; ``design_of_span``: its
    inverse; ``tolerance``: the wrong decisions among the frames around a point that the rule
    tolerates; ``command_of(design)``: its speed command (m/s, 0 = stop).
    """

    spans: Sequence[tuple[int, int]]
    design_of_span: dict[tuple[int, int], int]
    command_of: Callable[[int], float]
    envelope_index: int  # the envelope design (its span is every label)
    window_m: float  # the road around a look point whose frames are combined (m)
    tolerance: int  # wrong looks tolerated on each side of a stretch
    looks_per_side: int = LOOKS_PER_SIDE  # looks counted on each side of a stretch


def _recent_looks(looks: tuple[tuple[float, int], ...],
                  after_m: float) -> tuple[tuple[float, int], ...]:
    """The looks a combining profile keeps: those after ``after_m`` (two windows back: every
    stretch a new look can change finds its left looks there), at most the newest
    :data:`MAX_LOOKS` (a car at rest sees one look point tick after tick). Only the oldest are
    dropped, so each side of a stretch stays a run of consecutive ticks (docs/design.md 6.3)."""
    kept = tuple(lk for lk in looks if lk[0] > after_m)
    return kept[-MAX_LOOKS:]


def _braking_curve(command_mps: float, distance_m: float,
                   decel_mps2: float) -> tuple[float, float]:
    """Speed (m/s) and its slope along x of the braking curve that reaches ``command_mps``
    ``distance_m`` ahead at ``decel_mps2`` (the command itself once the distance is <= 0)."""
    if distance_m <= 0.0:
        return command_mps, 0.0
    speed = math.sqrt(command_mps * command_mps + 2.0 * decel_mps2 * distance_m)
    return speed, -decel_mps2 / speed


def speed_reference(entries, arc_length_m: float, *, decel_mps2: float, margin_m: float,
                    frontier: tuple[float, float] | None = None) -> tuple[float, float]:
    """``(v_ref, dv_ref/dx)`` at x for a profile's entries (module docstring equation).

    ``dv_ref/dx`` is the slope of the active branch (0 on a command, ``-a / v_env`` on a
    braking envelope), used as the tracking law's feedforward. ``frontier``: ``(position,
    command)`` of the end of the road with a decision, braked for like an entry ahead.
    """
    x = arc_length_m
    v_ref, slope = entries[0][1], 0.0
    for position, command, _ in entries:
        if position <= x:
            v_ref, slope = command, 0.0  # entries are sorted: the last one <= x is in force
            continue
        curve = _braking_curve(command, position - margin_m - x, decel_mps2)
        if curve[0] < v_ref:
            v_ref, slope = curve
    if frontier is not None and math.isfinite(frontier[0]):
        curve = _braking_curve(frontier[1], frontier[0] - margin_m - x, decel_mps2)
        if curve[0] < v_ref:
            v_ref, slope = curve
    return v_ref, slope


def frontier_latency_s(rate_hz: float, offset_fraction: float = OFFSET_FRACTION,
                       lag_ticks: int = 0) -> float:
    """Longest time (s) the end of the decided road stays put: one camera period plus the
    offset at which the profile takes a decision in (the car drives this far on the last
    frontier), plus ``lag_ticks`` periods when the road is decided only up to the look point
    that many ticks back (combined decisions tolerating that many wrong frames, DESIGN 6.3)."""
    return (1.0 + offset_fraction + lag_ticks) / rate_hz


@dataclasses.dataclass(frozen=True)
class BrakingLimits:
    """How the car brakes for the end of the decided road (:func:`supported_speed_mps`)."""

    decel_mps2: float  # the envelope's deceleration a (m/s^2)
    margin_m: float  # stop this far before the frontier (m)
    floor_speed_mps: float  # the slowest command v_f (m/s)


def supported_speed_mps(look_ahead_m: float, rate_hz: float, *, braking: BrakingLimits,
                        offset_fraction: float = OFFSET_FRACTION, lag_ticks: int = 0) -> float:
    """Largest constant speed (m/s) a camera look-ahead supports: the car can still brake at
    ``braking.decel_mps2`` to ``braking.floor_speed_mps`` (the slowest command)
    ``braking.margin_m`` before the frontier when the frontier has not moved for
    :func:`frontier_latency_s`, i.e. the root of ``v^2 = v_f^2 + 2 a (L - m - tau v)``."""
    decel_mps2, margin_m = braking.decel_mps2, braking.margin_m
    floor_speed_mps = braking.floor_speed_mps
    a, tau = float(decel_mps2), frontier_latency_s(rate_hz, offset_fraction, lag_ticks)
    c = floor_speed_mps**2 + 2.0 * a * (look_ahead_m - margin_m)
    if c <= 0.0:
        return 0.0
    return max(-a * tau + math.sqrt((a * tau) ** 2 + c), 0.0)


def look_ahead_needed_m(speed_mps: float, rate_hz: float, *, braking: BrakingLimits,
                        offset_fraction: float = OFFSET_FRACTION, lag_ticks: int = 0) -> float:
    """The look-ahead (m) that supports ``speed_mps`` (inverse of :func:`supported_speed_mps`)."""
    decel_mps2, margin_m = braking.decel_mps2, braking.margin_m
    floor_speed_mps = braking.floor_speed_mps
    return (max(speed_mps**2 - floor_speed_mps**2, 0.0) / (2.0 * decel_mps2) + margin_m
            + frontier_latency_s(rate_hz, offset_fraction, lag_ticks) * speed_mps)


class SpeedPlanner(LeafSystem):
    """The Python part of :class:`LongitudinalMotion`: the profile and the tracking law.

    Inputs ``decision`` (abstract) and ``kinematics`` [x, v]; abstract state the
    :class:`SpeedProfile`; outputs ``acceleration_mps2`` (dv/dt of the tracking law),
    ``design_index`` and ``speed_reference_mps``.
    """

    def __init__(self, motion: "LongitudinalMotion", initial: SpeedProfile, period_s: float):
        super().__init__()
        self._motion = motion
        self._decision = self.DeclareAbstractInputPort("decision", AbstractValue.Make(object()))
        self._kinematics = self.DeclareVectorInputPort("kinematics", 2)
        self._profile = self.DeclareAbstractState(AbstractValue.Make(initial))
        self.DeclarePeriodicUnrestrictedUpdateEvent(period_s, motion.offset_s,
                                                    self._take_decision)
        both = {self.input_port_ticket(self._kinematics.get_index()),
                self.abstract_state_ticket(self._profile)}
        self.DeclareVectorOutputPort("acceleration_mps2", 1, self._calc_acceleration,
                                     prerequisites_of_calc=both)
        self.DeclareVectorOutputPort("design_index", 1, self._calc_design,
                                     prerequisites_of_calc=both)
        self.DeclareVectorOutputPort("speed_reference_mps", 1, self._calc_reference,
                                     prerequisites_of_calc=both)

    def profile(self, context) -> SpeedProfile:
        return context.get_abstract_state(self._profile).get_value()

    def _state(self, context) -> tuple[float, float]:
        x, v = self._kinematics.Eval(context)
        return float(x), float(v)

    def _take_decision(self, context, state) -> None:
        if not self._decision.HasValue(context):
            return
        decision = self._decision.Eval(context)
        profile = self.profile(context)
        if decision is None or not hasattr(decision, "speed_command_mps"):
            return
        if float(decision.time_s) <= profile.last_decision_time_s:
            return  # already taken in
        m = self._motion
        look = float(getattr(decision, "look_m", decision.position_m))
        if not math.isfinite(look):
            look = float(decision.position_m)
        x = self._state(context)[0]
        if m.combines:
            # the counting rule's looks are the ticks' own certified ranges: the dwell time
            # (DESIGN 6.5) holds a narrowing back with a wider join, and a look that is wider
            # than its tick's set costs the rule an excluding look (docs/design.md 6.3)
            requested = int(getattr(decision, "requested_design_index", -1))
            new = profile.with_combined_decision(
                look, requested if requested >= 0 else int(decision.design_index),
                float(decision.time_s), x, rule=m.combination_rule)
        else:
            new = profile.with_decision(float(decision.position_m),
                                        m.speed_command(decision.speed_command_mps),
                                        int(decision.design_index), float(decision.time_s), x,
                                        m.join_entry, look_m=look)
        state.get_mutable_abstract_state(self._profile).set_value(new)

    def _calc_acceleration(self, context, output):
        x, v = self._state(context)
        output.SetAtIndex(0, self._motion.acceleration(self.profile(context), x, v))

    def _calc_design(self, context, output):
        output.SetAtIndex(0, float(self.profile(context).in_force(self._state(context)[0])[1]))

    def _calc_reference(self, context, output):
        m = self._motion
        v_ref, _ = m.reference(self.profile(context), self._state(context)[0])
        output.SetAtIndex(0, v_ref)


def _kinematics_system(x0: float, v0: float) -> SymbolicVectorSystem:
    """``x' = max(v, 0)``, ``v' = a`` (input), output ``[x, max(v, 0)]``, evaluated in C++.

    The state is the deviation from (x0, v0), so the default (zero) state is the initial one.
    """
    dx, dv, a = sym.Variable("dx"), sym.Variable("dv"), sym.Variable("a")
    speed = sym.max(v0 + dv, 0.0)
    return SymbolicVectorSystem(state=[dx, dv], input=[a], dynamics=[speed, sym.Expression(a)],
                                output=[x0 + dx, speed])


def _check_motion_limits(motion: MotionSettings, tracking: TrackingSettings,
                         rate_hz: float) -> None:
    """:class:`LongitudinalMotion`'s checks of its rates, speeds and margins, in order."""
    max_decel_mps2, max_accel_mps2 = motion.max_decel_mps2, motion.max_accel_mps2
    stop_speed_mps, initial_speed_mps = motion.stop_speed_mps, motion.initial_speed_mps
    speed_gain_per_s, creep_speed_mps = tracking.speed_gain_per_s, tracking.creep_speed_mps
    envelope_decel_fraction = tracking.envelope_decel_fraction
    braking_margin_m = tracking.braking_margin_m
    for name, value in (("max_decel_mps2", max_decel_mps2),
                        ("max_accel_mps2", max_accel_mps2),
                        ("speed_gain_per_s", speed_gain_per_s), ("rate_hz", rate_hz),
                        ("stop_speed_mps", stop_speed_mps),
                        ("creep_speed_mps", creep_speed_mps)):
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"longitudinal: {name} = {value!r} must be positive")
    if not (math.isfinite(initial_speed_mps) and initial_speed_mps >= 0):
        raise ConfigError(f"longitudinal: initial_speed_mps = {initial_speed_mps!r} must "
                          "be >= 0")
    if not 0 < envelope_decel_fraction < 1:
        raise ConfigError("longitudinal: envelope_decel_fraction = "
                          f"{envelope_decel_fraction!r} must be in (0, 1)")
    if not (math.isfinite(braking_margin_m) and braking_margin_m >= 0):
        raise ConfigError(f"longitudinal: braking_margin_m = {braking_margin_m!r} must be "
                          ">= 0")


def _check_decision_options(designs: "ProfileDesigns") -> None:
    """:class:`LongitudinalMotion`'s checks of its join table, frontier speed and combined
    decisions, in order."""
    join, design_speeds_mps = designs.join, designs.design_speeds_mps
    frontier_speed_mps, window_m = designs.frontier_speed_mps, designs.window_m
    spans, envelope_index = designs.spans, designs.envelope_index
    tolerance, looks_per_side = designs.tolerance, designs.looks_per_side
    if (join is None) != (design_speeds_mps is None):
        raise ConfigError("longitudinal: join and design_speeds_mps go together")
    if frontier_speed_mps is not None and not (math.isfinite(frontier_speed_mps)
                                               and frontier_speed_mps >= 0):
        raise ConfigError(f"longitudinal: frontier_speed_mps = {frontier_speed_mps!r} must "
                          "be >= 0")
    if not (math.isfinite(window_m) and window_m >= 0):
        raise ConfigError(f"longitudinal: window_m = {window_m!r} must be >= 0")
    if (spans is not None) != (window_m > 0) or (spans is not None and (
            join is None or envelope_index is None)):
        raise ConfigError("longitudinal: combined decisions need spans, window_m > 0, the "
                          "join table and envelope_index together")
    if isinstance(tolerance, bool) or not isinstance(tolerance, int) or tolerance < 0:
        raise ConfigError(f"longitudinal: tolerance = {tolerance!r} must be an integer >= 0")
    if isinstance(looks_per_side, bool) or not isinstance(looks_per_side, int) or \
            looks_per_side <= tolerance:
        raise ConfigError(f"longitudinal: looks_per_side = {looks_per_side!r} must be an "
                          f"integer above the tolerance {tolerance}")


class LongitudinalMotion(Diagram):
    """Speed and arc length of the car under the certified speed commands (module docstring).

    A :class:`SpeedPlanner` (Python: profile and tracking law) drives the kinematics
    ``[x, v]``, a C++ ``SymbolicVectorSystem`` (the arc length and speed, read by the plant,
    the route and the controller at every integrator stage, cost no Python call).

    Args:
        motion: the scenario's motion block; reads ``max_decel_mps2``, ``max_accel_mps2``
            (m/s^2), ``initial_speed_mps`` (the speed at t = 0 itself: the builder puts the
            envelope design's speed in for the scenario's 0) and ``stop_speed_mps`` (m/s).
        camera: the scenario's camera block; reads ``rate_hz``, the profile update's rate.
        tracking: the tracking law's gain, braking margin, envelope share and creep speed.
        designs: the design table's speeds and joins and the combination of decisions
            (:class:`ProfileDesigns`); None: each decision's command on its own.
        initial_design_index: the design in force before any decision.
        initial_arc_length_m: x at t = 0 (m; the builder starts the car a look-ahead before
            the route).
    """

    def __init__(self, motion: MotionSettings | None = None,
                 camera: CameraSettings | None = None,
                 tracking: TrackingSettings | None = None, *,
                 designs: ProfileDesigns | None = None, initial_design_index: int = 0,
                 initial_arc_length_m: float = 0.0):
        super().__init__()
        motion = motion if motion is not None else MotionSettings()
        rate_hz = (camera if camera is not None else CameraSettings()).rate_hz
        t = tracking if tracking is not None else TrackingSettings()
        d = designs if designs is not None else ProfileDesigns()
        _check_motion_limits(motion, t, rate_hz)
        _check_decision_options(d)
        self._keep_settings(motion, t, d)
        period = 1.0 / rate_hz
        self.offset_s = OFFSET_FRACTION * period
        initial = SpeedProfile(((-math.inf, self.speed_command(motion.initial_speed_mps),
                                 int(initial_design_index)),))
        self._build(SpeedPlanner(self, initial, period), float(initial_arc_length_m),
                    float(motion.initial_speed_mps))
        self.set_name("longitudinal_motion")

    def _keep_settings(self, motion: MotionSettings, t: TrackingSettings,
                       d: ProfileDesigns) -> None:
        """The tracking law's and the decision rule's numbers, read by :class:`SpeedPlanner`."""
        self.max_decel_mps2 = float(motion.max_decel_mps2)
        self.max_accel_mps2 = float(motion.max_accel_mps2)
        self.speed_gain_per_s = float(t.speed_gain_per_s)
        self.stop_speed_mps = float(motion.stop_speed_mps)
        self.envelope_decel_mps2 = t.envelope_decel_fraction * self.max_decel_mps2
        self.braking_margin_m = float(t.braking_margin_m)
        self.creep_speed_mps = float(t.creep_speed_mps)
        self._join, self._speeds = d.join, d.design_speeds_mps
        self._spans = None if d.spans is None else [tuple(map(int, s)) for s in d.spans]
        self._design_of_span = (None if d.spans is None
                                else {s: i for i, s in enumerate(self._spans)})
        self.tolerance = int(d.tolerance)
        self.looks_per_side = int(d.looks_per_side)
        self.frontier_speed_mps = (None if d.frontier_speed_mps is None
                                   else self.speed_command(d.frontier_speed_mps))
        self.window_m = float(d.window_m)
        self.envelope_index = None if d.envelope_index is None else int(d.envelope_index)

    def _build(self, planner: SpeedPlanner, initial_arc_length_m: float,
               initial_speed_mps: float) -> None:
        """The planner and the kinematics [x, v], with the ports this block exports."""
        builder = DiagramBuilder()
        self._planner = builder.AddNamedSystem("speed_planner", planner)
        kin = builder.AddNamedSystem("kinematics", _kinematics_system(initial_arc_length_m,
                                                                      initial_speed_mps))
        builder.Connect(self._planner.GetOutputPort("acceleration_mps2"), kin.get_input_port(0))
        builder.Connect(kin.get_output_port(0), self._planner.GetInputPort("kinematics"))
        demux = builder.AddSystem(Demultiplexer([1, 1]))
        builder.Connect(kin.get_output_port(0), demux.get_input_port(0))
        builder.ExportInput(self._planner.GetInputPort("decision"), "decision")
        builder.ExportOutput(demux.get_output_port(0), "arc_length_m")
        builder.ExportOutput(demux.get_output_port(1), "speed_mps")
        builder.ExportOutput(self._planner.GetOutputPort("design_index"), "design_index")
        builder.ExportOutput(self._planner.GetOutputPort("speed_reference_mps"),
                             "speed_reference_mps")
        builder.BuildInto(self)

    @property
    def join_entry(self) -> Callable[[int, int], tuple[float, int]] | None:
        """(command, design) of the join of two designs (see :meth:`SpeedProfile.with_decision`),
        or None when the block was built without a join table."""
        if self._join is None:
            return None
        return lambda a, b: (self.speed_command(self._speeds[self._join[(a, b)]]),
                             self._join[(a, b)])

    @property
    def combination_rule(self) -> CombinationRule:
        """The rule :meth:`SpeedProfile.with_combined_decision` combines decisions by (the
        block's spans, commands, envelope, window and tolerance); only when it
        :attr:`combines`."""
        return CombinationRule(self._spans, self._design_of_span, self.design_command,
                               self.envelope_index, self.window_m, self.tolerance,
                               self.looks_per_side)

    @property
    def combines(self) -> bool:
        """Decisions are combined over ``window_m``
        (:meth:`SpeedProfile.with_combined_decision`)."""
        return self._spans is not None

    def design_command(self, design_index: int) -> float:
        """The speed command (m/s, 0 = stop) of a design: its safe speed."""
        return self.speed_command(self._speeds[int(design_index)])

    def speed_command(self, speed_command_mps: float) -> float:
        """A command below the stop speed (or not finite) means stop: 0."""
        c = float(speed_command_mps)
        return c if (math.isfinite(c) and c >= self.stop_speed_mps) else 0.0

    def braking_distance_m(self, from_speed_mps: float, to_speed_mps: float) -> float:
        """Distance (m) ahead at which an entry must be known for the car at ``from`` to reach
        ``to`` before it on the envelope: ``(from^2 - to^2) / (2 a) + m``."""
        to = self.speed_command(to_speed_mps)
        return max(from_speed_mps**2 - to**2, 0.0) / (2.0 * self.envelope_decel_mps2) + \
            self.braking_margin_m

    def planner(self) -> SpeedPlanner:
        """The leaf holding the profile."""
        return self._planner

    def profile(self, root_context) -> SpeedProfile:
        """The current :class:`SpeedProfile`, from the ROOT context of the simulation."""
        return self._planner.profile(self._planner.GetMyContextFromRoot(root_context))

    def reference(self, profile: SpeedProfile, x: float) -> tuple[float, float]:
        """``(v_ref, dv_ref/dx)`` at x: the profile's entries and, with a frontier speed, the
        frontier (the last look point, at the slowest command a decision can give)."""
        frontier = (None if self.frontier_speed_mps is None
                    else (profile.last_look_m, self.frontier_speed_mps))
        return speed_reference(profile.entries, x, decel_mps2=self.envelope_decel_mps2,
                               margin_m=self.braking_margin_m, frontier=frontier)

    def acceleration(self, profile: SpeedProfile, x: float, v: float) -> float:
        """dv/dt of the tracking law (module docstring) at (x, v) for a profile."""
        v_ref, slope = self.reference(profile, x)
        target = v_ref - (self.creep_speed_mps if v_ref <= 0.0 else 0.0)
        a = self.speed_gain_per_s * (target - v) + slope * max(v, 0.0)
        a = min(max(a, -self.max_decel_mps2), self.max_accel_mps2)
        if v <= 0.0 and a < 0.0:
            return 0.0  # at rest: no braking into reverse
        return a
