"""Longitudinal motion: the car's speed follows the certified speed command (issue 7, item 5).

Input port:
  ``decision``             abstract; any object with ``position_m`` (the look point from which
                           it applies, m of arc length), ``speed_command_mps`` (0 = stop),
                           ``design_index`` and ``time_s`` (``systems.certified_interval.Decision``)
Continuous state:         ``[x, v]``: arc length along the route (m) and forward speed (m/s)
                           (in a C++ ``SymbolicVectorSystem``, as deviations from the initial
                           values; ``speed_planner`` computes dv/dt in Python)
Abstract state:           the speed/design profile along the route, entries
                           ``(position_m, speed_command_mps, design_index)`` sorted by position,
                           the first one at -inf (the initial command), and the time of the
                           last decision taken in
Output ports (size 1):
  ``arc_length_m``         x (m)
  ``speed_mps``            max(v, 0) (m/s): never negative
  ``design_index``         the design of the latest profile entry with position <= x
  ``speed_reference_mps``  v_ref(x) below (m/s)

Profile (a periodic unrestricted update at the camera rate, offset 3T/4 by default): with a
join table, the road between the previous decision's look point q and this one's p, which no
frame showed, gets from q on the join of the two designs (the design of the hull of their
label ranges: it holds the stiffness wherever in (q, p) a boundary lies, given segments
longer than that gap); a decision at position p supersedes the entries at positions >= p (a
newer decision about the same stretch of road, e.g. a dwell-delayed design whose look point is
that of the tick that first asked for it), entries the car has passed are dropped except the
one in force, and an entry equal to its predecessor in (command, design) is not added. A
command below ``stop_speed_mps`` is 0.

Speed reference at x (the braking envelope, a = ``envelope_decel_fraction`` * a_dec):
  ``v_ref(x) = min(c(x), min_{p_i > x} sqrt(c_i^2 + 2 a max(p_i - m - x, 0)))``
with c(x) the command in force at x and m = ``braking_margin_m``: the command of a point ahead
is reached m metres before it. The envelope keeps (1 - fraction) of the braking authority for
the tracking law, so the car catches up with it after a late (too close) entry.

Tracking law (feedforward of the reference's rate along the motion plus proportional gain k):
  ``dv/dt = clip(k (v_ref - v - v_creep [v_ref = 0]) + (dv_ref/dx) v, -a_dec, a_acc)``
  ``dx/dt = max(v, 0)``; at v <= 0 no further braking (the car rests, speed never negative).
On the envelope ``dv_ref/dx = -a / v_env``, so a car on the envelope stays on it exactly and
decelerates at a < a_dec; off it, the error decays at rate k once out of saturation. A stop
reference aims ``v_creep`` below zero, so the car comes to rest in finite time.
A late entry (closer than :meth:`LongitudinalMotion.braking_distance_m`) cannot be met: the car
then brakes at a_dec and reaches the point faster than its command (the scenario's look-ahead
must exceed the braking distance plus the perception latency times the speed).
"""

import dataclasses
import math
from collections.abc import Callable

import pydrake.symbolic as sym
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import Demultiplexer, SymbolicVectorSystem

from drake_cert.errors import ConfigError

STOP_SPEED_MPS = 5.0  # DESIGN 2: below this the car is stopped (lateral dynamics frozen)


@dataclasses.dataclass(frozen=True)
class SpeedProfile:
    """Abstract state of :class:`LongitudinalMotion` (immutable; a new one per update).

    ``entries``: ``(position_m, speed_command_mps, design_index)`` sorted by position, the
    first at -inf. ``last_decision_time_s``: time of the last decision taken in (-inf if none).
    """

    entries: tuple[tuple[float, float, int], ...]
    last_decision_time_s: float = -math.inf
    last_look_m: float = -math.inf  # look point of the last decision taken in (m)

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
                      join: Callable[[int, int], tuple[float, int]] | None = None
                      ) -> "SpeedProfile":
        """The profile after one decision (see the module docstring for the rules).

        ``join(d_prev, d_new)``: the (command, design) that holds both designs' stiffness; when
        given, the road between the previous look point and this one (which no frame showed:
        a condition boundary may lie anywhere in it) gets the join of the designs on either
        side, from the previous look point on.
        """
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
        return SpeedProfile(tuple(kept), float(time_s), float(position_m))


def speed_reference(entries, arc_length_m: float, *, decel_mps2: float,
                    margin_m: float) -> tuple[float, float]:
    """``(v_ref, dv_ref/dx)`` at x for a profile's entries (module docstring equation).

    ``dv_ref/dx`` is the slope of the active branch (0 on a command, ``-a / v_env`` on a
    braking envelope), used as the tracking law's feedforward.
    """
    x = arc_length_m
    v_ref, slope = entries[0][1], 0.0
    for position, command, _ in entries:
        if position <= x:
            v_ref, slope = command, 0.0  # entries are sorted: the last one <= x is in force
            continue
        distance = position - margin_m - x
        if distance <= 0.0:
            envelope, envelope_slope = command, 0.0
        else:
            envelope = math.sqrt(command * command + 2.0 * decel_mps2 * distance)
            envelope_slope = -decel_mps2 / envelope
        if envelope < v_ref:
            v_ref, slope = envelope, envelope_slope
    return v_ref, slope


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
        new = profile.with_decision(float(decision.position_m),
                                    m.speed_command(decision.speed_command_mps),
                                    int(decision.design_index), float(decision.time_s),
                                    self._state(context)[0], m.join_entry)
        state.get_mutable_abstract_state(self._profile).set_value(new)

    def _calc_acceleration(self, context, output):
        x, v = self._state(context)
        output.SetAtIndex(0, self._motion.acceleration(self.profile(context).entries, x, v))

    def _calc_design(self, context, output):
        output.SetAtIndex(0, float(self.profile(context).in_force(self._state(context)[0])[1]))

    def _calc_reference(self, context, output):
        m = self._motion
        v_ref, _ = speed_reference(self.profile(context).entries, self._state(context)[0],
                                   decel_mps2=m.envelope_decel_mps2, margin_m=m.braking_margin_m)
        output.SetAtIndex(0, v_ref)


def _kinematics_system(x0: float, v0: float) -> SymbolicVectorSystem:
    """``x' = max(v, 0)``, ``v' = a`` (input), output ``[x, max(v, 0)]``, evaluated in C++.

    The state is the deviation from (x0, v0), so the default (zero) state is the initial one.
    """
    dx, dv, a = sym.Variable("dx"), sym.Variable("dv"), sym.Variable("a")
    speed = sym.max(v0 + dv, 0.0)
    return SymbolicVectorSystem(state=[dx, dv], input=[a], dynamics=[speed, sym.Expression(a)],
                                output=[x0 + dx, speed])


class LongitudinalMotion(Diagram):
    """Speed and arc length of the car under the certified speed commands (module docstring).

    A :class:`SpeedPlanner` (Python: profile and tracking law) drives the kinematics
    ``[x, v]``, a C++ ``SymbolicVectorSystem`` (the arc length and speed, read by the plant,
    the route and the controller at every integrator stage, cost no Python call).
    """

    def __init__(self, *, max_decel_mps2: float = 4.0, max_accel_mps2: float = 2.0,
                 speed_gain_per_s: float = 2.0, initial_speed_mps: float,
                 initial_design_index: int = 0, stop_speed_mps: float = STOP_SPEED_MPS,
                 rate_hz: float = 10.0, offset_s: float | None = None,
                 braking_margin_m: float = 2.0, envelope_decel_fraction: float = 0.9,
                 creep_speed_mps: float = 0.1, initial_arc_length_m: float = 0.0,
                 join: dict[tuple[int, int], int] | None = None,
                 design_speeds_mps: list[float] | None = None):
        super().__init__()
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
        self.max_decel_mps2 = float(max_decel_mps2)
        self.max_accel_mps2 = float(max_accel_mps2)
        self.speed_gain_per_s = float(speed_gain_per_s)
        self.stop_speed_mps = float(stop_speed_mps)
        self.envelope_decel_mps2 = envelope_decel_fraction * self.max_decel_mps2
        self.braking_margin_m = float(braking_margin_m)
        self.creep_speed_mps = float(creep_speed_mps)
        if (join is None) != (design_speeds_mps is None):
            raise ConfigError("longitudinal: join and design_speeds_mps go together")
        self._join, self._speeds = join, design_speeds_mps
        period = 1.0 / rate_hz
        self.offset_s = 0.75 * period if offset_s is None else float(offset_s)

        initial = SpeedProfile(((-math.inf, self.speed_command(initial_speed_mps),
                                 int(initial_design_index)),))
        builder = DiagramBuilder()
        self._planner = builder.AddNamedSystem("speed_planner",
                                               SpeedPlanner(self, initial, period))
        kin = builder.AddNamedSystem("kinematics", _kinematics_system(
            float(initial_arc_length_m), float(initial_speed_mps)))
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
        self.set_name("longitudinal_motion")

    @property
    def join_entry(self) -> Callable[[int, int], tuple[float, int]] | None:
        """(command, design) of the join of two designs (see :meth:`SpeedProfile.with_decision`),
        or None when the block was built without a join table."""
        if self._join is None:
            return None
        return lambda a, b: (self.speed_command(self._speeds[self._join[(a, b)]]),
                             self._join[(a, b)])

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

    def acceleration(self, entries, x: float, v: float) -> float:
        """dv/dt of the tracking law (module docstring) at (x, v) for a profile's entries."""
        v_ref, slope = speed_reference(entries, x, decel_mps2=self.envelope_decel_mps2,
                                       margin_m=self.braking_margin_m)
        target = v_ref - (self.creep_speed_mps if v_ref <= 0.0 else 0.0)
        a = self.speed_gain_per_s * (target - v) + slope * max(v, 0.0)
        a = min(max(a, -self.max_decel_mps2), self.max_accel_mps2)
        if v <= 0.0 and a < 0.0:
            return 0.0  # at rest: no braking into reverse
        return a
