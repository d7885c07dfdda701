"""Longitudinal motion (DESIGN 6.3-6.4): speed follows the certified command, bounded."""

import math

import numpy as np
import pytest
from design_fixtures import FakeDecision
from pydrake.common.value import AbstractValue
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantValueSource, LogVectorOutput

from drake_cert.errors import ConfigError
from drake_cert.systems.longitudinal import (
    CombinationRule,
    LongitudinalMotion,
    SpeedProfile,
    speed_reference,
)
from drake_cert.systems.scenario import MotionSettings

A_DEC, A_ACC = 4.0, 2.0
TOL = 1e-6  # integration roundoff on the bounds


class ScriptedDecisions(LeafSystem):
    """Outputs the latest of a list of decisions whose time_s <= t (a stand-in for the
    certified-interval block)."""

    def __init__(self, decisions):
        super().__init__()
        self._decisions = sorted(decisions, key=lambda d: d.time_s)
        self.DeclareAbstractOutputPort("decision", lambda: AbstractValue.Make(object()),
                                       self._calc, prerequisites_of_calc={self.time_ticket()})

    def _calc(self, context, output):
        now = [d for d in self._decisions if d.time_s <= context.get_time()]
        output.set_value(now[-1] if now else None)


def _drive(decisions, *, initial_speed, t_final, initial_design=0):
    builder = DiagramBuilder()
    motion = builder.AddSystem(LongitudinalMotion(MotionSettings(initial_speed_mps=initial_speed),
                                                  initial_design_index=initial_design))
    source = builder.AddSystem(ScriptedDecisions(decisions))
    builder.Connect(source.get_output_port(), motion.GetInputPort("decision"))
    logs = {name: LogVectorOutput(motion.GetOutputPort(name), builder, 0.01)
            for name in ("arc_length_m", "speed_mps", "design_index", "speed_reference_mps")}
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.get_mutable_integrator().set_fixed_step_mode(True)
    simulator.get_mutable_integrator().set_maximum_step_size(1e-3)
    simulator.AdvanceTo(t_final)
    ctx = simulator.get_context()
    data = {k: v.FindLog(ctx).data()[0] for k, v in logs.items()}
    data["t"] = logs["speed_mps"].FindLog(ctx).sample_times()
    return motion, data


def _accelerations(data):
    return np.diff(data["speed_mps"]) / np.diff(data["t"])


def test_the_command_of_a_slower_point_ahead_is_reached_before_the_car_gets_there():
    p, slow = 60.0, 10.0
    _, d = _drive([FakeDecision(0.05, p, slow, 1)], initial_speed=20.0, t_final=6.0)
    x, v = d["arc_length_m"], d["speed_mps"]
    assert x[-1] > p + 5.0
    # reached (to 1 cm/s) before p, by the braking margin's end, and held there
    assert np.all(v[x >= p - 1.0] <= slow + 0.01)
    assert v[0] == pytest.approx(20.0)
    acc = _accelerations(d)
    assert acc.min() >= -A_DEC - TOL and acc.max() <= A_ACC + TOL
    # the design switches where the car reaches the entry, not before
    assert np.all(d["design_index"][x < p - 0.3] == 0)
    assert np.all(d["design_index"][x > p + 0.3] == 1)


def test_a_late_entry_brakes_at_the_deceleration_bound_and_never_beyond():
    _, d = _drive([FakeDecision(0.05, 20.0, 5.0, 0)], initial_speed=20.0, t_final=4.0)
    acc = _accelerations(d)
    assert acc.min() == pytest.approx(-A_DEC, abs=1e-6)  # saturated
    assert acc.min() >= -A_DEC - TOL


def test_a_faster_command_accelerates_at_most_at_the_acceleration_bound():
    _, d = _drive([FakeDecision(0.05, 5.0, 15.0, 2)], initial_speed=8.0, t_final=8.0)
    acc = _accelerations(d)
    assert acc.max() == pytest.approx(A_ACC, abs=1e-6)
    assert acc.max() <= A_ACC + TOL
    assert d["speed_mps"][-1] == pytest.approx(15.0, abs=0.01)
    assert d["speed_reference_mps"][-1] == 15.0


def test_a_stop_command_brings_the_car_to_rest_before_the_point_and_speed_stays_nonnegative():
    p = 50.0
    _, d = _drive([FakeDecision(0.05, p, 0.0, 3)], initial_speed=15.0, t_final=10.0)
    x, v = d["arc_length_m"], d["speed_mps"]
    assert v[-1] == 0.0 and v.min() >= 0.0
    assert x[-1] < p  # stopped before the point
    assert np.all(v[-100:] == 0.0)  # at rest for the last second, not creeping
    assert _accelerations(d).min() >= -A_DEC - TOL


def test_a_command_below_the_stop_speed_means_stop():
    _, d = _drive([FakeDecision(0.05, 30.0, 3.0, 0)], initial_speed=10.0, t_final=10.0)
    assert d["speed_mps"][-1] == 0.0 and d["arc_length_m"][-1] < 30.0


def test_a_newer_decision_supersedes_the_entries_at_or_beyond_its_position():
    prof = SpeedProfile(((-math.inf, 20.0, 0),))
    prof = prof.with_decision(40.0, 12.0, 1, 0.1, 0.0)
    prof = prof.with_decision(45.0, 12.0, 1, 0.2, 1.0)  # same command: not added
    prof = prof.with_decision(50.0, 10.0, 2, 0.3, 2.0)
    assert [e[0] for e in prof.entries] == [-math.inf, 40.0, 50.0]
    prof = prof.with_decision(42.0, 15.0, 3, 0.4, 3.0)  # dwell-delayed: from its look point
    assert prof.entries == ((-math.inf, 20.0, 0), (40.0, 12.0, 1), (42.0, 15.0, 3))
    prof = prof.with_decision(60.0, 15.0, 3, 0.5, 41.0)  # the car passed 40: it stays in force
    assert prof.entries == ((40.0, 12.0, 1), (42.0, 15.0, 3))
    assert prof.in_force(41.0) == (12.0, 1) and prof.in_force(43.0) == (15.0, 3)


def test_speed_reference_is_the_braking_envelope_with_margin():
    entries = ((-math.inf, 20.0, 0), (100.0, 10.0, 1))
    v, slope = speed_reference(entries, 80.0, decel_mps2=3.6, margin_m=2.0)
    assert v == pytest.approx(math.sqrt(100.0 + 2 * 3.6 * 18.0))
    assert slope == pytest.approx(-3.6 / v)
    assert speed_reference(entries, 98.5, decel_mps2=3.6, margin_m=2.0) == (10.0, 0.0)
    assert speed_reference(entries, 0.0, decel_mps2=3.6, margin_m=2.0) == (20.0, 0.0)


def test_the_decision_port_takes_a_constant_value_source_and_duplicates_are_ignored():
    builder = DiagramBuilder()
    motion = builder.AddSystem(LongitudinalMotion(MotionSettings(initial_speed_mps=12.0)))
    src = builder.AddSystem(ConstantValueSource(AbstractValue.Make(
        FakeDecision(0.0, 30.0, 8.0, 4))))
    builder.Connect(src.get_output_port(), motion.GetInputPort("decision"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.AdvanceTo(1.0)  # ten ticks of the same decision: one entry
    assert motion.profile(simulator.get_context()).entries[1:] == ((30.0, 8.0, 4),)


def test_invalid_settings_are_config_errors():
    with pytest.raises(ConfigError, match="max_decel_mps2"):
        LongitudinalMotion(MotionSettings(initial_speed_mps=10.0, max_decel_mps2=0.0))
    with pytest.raises(ConfigError, match="initial_speed_mps"):
        LongitudinalMotion(MotionSettings(initial_speed_mps=-1.0))


def test_the_unseen_road_between_two_look_points_gets_the_join_of_their_designs():
    # Designs 0 (sunny, 19 m/s), 1 (snow, 10 m/s), 2 (their join: the envelope, 6 m/s).
    join = {(0, 0): 0, (1, 1): 1, (2, 2): 2, (0, 1): 2, (1, 0): 2, (0, 2): 2, (2, 0): 2,
            (1, 2): 2, (2, 1): 2}
    speeds = [19.0, 10.0, 6.0]

    def entry(a, b):
        return speeds[join[(a, b)]], join[(a, b)]

    prof = SpeedProfile(((-math.inf, 6.0, 2),))
    prof = prof.with_decision(40.0, 19.0, 0, 0.1, 0.0, entry)  # the first frame: no gap yet
    prof = prof.with_decision(41.2, 19.0, 0, 0.2, 1.2, entry)  # sunny again: nothing changes
    assert prof.entries == ((-math.inf, 6.0, 2), (40.0, 19.0, 0))
    # The next frame sees snow 1.2 m further: the boundary lies somewhere in (41.2, 42.4], so
    # from the previous look point on the join holds, then snow from the new look point.
    prof = prof.with_decision(42.4, 10.0, 1, 0.3, 2.4, entry)
    assert prof.entries == ((-math.inf, 6.0, 2), (40.0, 19.0, 0), (41.2, 6.0, 2),
                            (42.4, 10.0, 1))
    assert prof.in_force(41.0) == (19.0, 0) and prof.in_force(42.0) == (6.0, 2)
    assert prof.in_force(50.0) == (10.0, 1)
    # Without a join table the old rule: the new design from its own look point.
    old = SpeedProfile(((-math.inf, 6.0, 2),)).with_decision(41.2, 19.0, 0, 0.2, 1.2)
    assert old.with_decision(42.4, 10.0, 1, 0.3, 2.4).in_force(42.0) == (19.0, 0)


# Three labels in friction order: sunny (0), rain (1), snow (2); designs are label ranges.
RANGES = [(0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (0, 2)]  # index 5: the envelope
RANGE_SPEEDS = [19.0, 16.0, 10.0, 15.0, 9.5, 6.0]


SPANS = {r: i for i, r in enumerate(RANGES)}


def _rule(window_m, tolerance, **more):
    return CombinationRule(spans=RANGES, design_of_span=SPANS,
                           command_of=lambda d: RANGE_SPEEDS[d], envelope_index=5,
                           window_m=window_m, tolerance=tolerance, **more)


def _combine(looks_designs, window_m=30.0, x=0.0, tolerance=1):
    prof = SpeedProfile(((-math.inf, 6.0, 5),))
    for k, (look, design) in enumerate(looks_designs):
        prof = prof.with_combined_decision(look, design, 0.1 * (k + 1), x,
                                           rule=_rule(window_m, tolerance))
    return prof


def test_an_abstention_between_two_sunny_decisions_gets_sunny_not_the_envelope():
    # Within 30 m (no stretch of one condition is shorter) at most one boundary lies between
    # two look points: sunny on both sides means sunny all along, whatever the frame at 42
    # said; with one wrong frame tolerated, two sunny frames on each side are needed.
    prof = _combine([(38.0, 0), (40.0, 0), (42.0, 5), (44.0, 0), (46.0, 0)])
    assert prof.in_force(42.5) == (19.0, 0) and prof.in_force(41.0) == (19.0, 0)
    assert prof.last_look_m == 46.0
    # tolerating none, one frame on each side suffices (the rule of the paper's reading)
    prof = _combine([(40.0, 0), (42.0, 5), (44.0, 0)], tolerance=0)
    assert prof.in_force(42.5) == (19.0, 0) and prof.in_force(41.0) == (19.0, 0)


def test_one_frame_alone_narrows_nothing_when_one_wrong_frame_is_tolerated():
    prof = _combine([(40.0, 0), (42.0, 0)])
    assert prof.in_force(41.0) == (6.0, 5)  # if 42 were wrong, 40 alone bounds nothing
    prof = _combine([(40.0, 0), (42.0, 0), (44.0, 0)])
    assert prof.in_force(41.0) == (6.0, 5)  # ...and if 40 were wrong: left needs two too
    prof = _combine([(38.0, 0), (40.0, 0), (42.0, 0), (44.0, 0)])
    assert prof.in_force(41.0) == (19.0, 0) and prof.in_force(43.0) == (6.0, 5)


def test_a_wide_decision_between_two_narrow_ones_is_narrowed_and_never_widened():
    prof = _combine([(38.0, 0), (40.0, 0), (42.0, 3), (44.0, 0), (46.0, 0)])
    assert prof.in_force(42.5) == (19.0, 0)
    # A later abstention does not undo what the pairs before it established.
    prof2 = _combine([(38.0, 0), (40.0, 0), (42.0, 3), (44.0, 0), (46.0, 0), (48.0, 5)])
    assert prof2.in_force(42.5) == (19.0, 0) and prof2.in_force(47.0) == (6.0, 5)


def test_a_boundary_between_two_look_points_gets_the_join_of_both_sides():
    prof = _combine([(40.0, 0), (42.0, 0), (44.0, 2)], tolerance=0)  # sunny, sunny, snow
    assert prof.in_force(41.0) == (19.0, 0)  # the pair (40, 42) is all sunny...
    assert prof.in_force(43.0) == (6.0, 5)  # ...the boundary lies in (42, 44): sunny..snow
    assert prof.in_force(44.5) == (10.0, 2)
    # tolerating one wrong frame, the last frame on each side of the boundary could be the
    # wrong one: the join reaches one look point further on each side
    prof = _combine([(36.0, 0), (38.0, 0), (40.0, 0), (42.0, 0), (44.0, 2), (46.0, 2),
                     (48.0, 2), (50.0, 2)])
    assert prof.in_force(39.0) == (19.0, 0) and prof.in_force(41.0) == (6.0, 5)
    assert prof.in_force(43.0) == (6.0, 5) and prof.in_force(45.0) == (6.0, 5)
    assert prof.in_force(47.0) == (10.0, 2)


def test_decisions_a_window_apart_do_not_pair():
    # 40 sunny, abstentions until 75, sunny at 75: 35 m > 30 m, two boundaries could lie
    # between, so the stretch keeps the envelope.
    prof = _combine([(38.0, 0), (40.0, 0), (50.0, 5), (60.0, 5), (75.0, 0), (77.0, 0)])
    assert prof.in_force(55.0) == (6.0, 5) and prof.in_force(65.0) == (6.0, 5)


def test_a_wrong_frame_on_a_straight_before_a_boundary_does_not_turn_the_sunny_road():
    # The reported drive: sunny road, one clean frame certified {snow} (g wrong), three
    # right sunny frames after it, then the true boundary at 27 m and snow frames. Each
    # stretch must hold the truth: sunny before 27, snow after.
    frames = ([(float(x), 0) for x in range(0, 20, 2)] + [(20.0, 2)]
              + [(22.0, 0), (24.0, 0), (26.0, 0)] + [(28.0 + 2 * i, 2) for i in range(6)])
    prof = _combine(frames, window_m=60.0)
    for x in np.arange(2.5, 36.0, 0.5):
        design = prof.in_force(float(x))[1]
        lo, hi = RANGES[design]
        truth = 0 if x < 27.0 else 2
        assert lo <= truth <= hi, (x, RANGES[design])
    assert prof.in_force(21.0) == (19.0, 0)  # the wrong frame's own stretch stays sunny
    # the meet of the paper's reading (no wrong frame tolerated) puts snow on sunny road
    old = _combine(frames, window_m=60.0, tolerance=0)
    assert RANGES[old.in_force(26.5)[1]] == (2, 2)


def test_a_wrong_frame_at_a_curve_entry_cannot_reach_behind_its_look_point():
    # rain from 115 m on; an attacked rain frame at 116 certified {sunny}: the stretch behind
    # it, which holds the boundary, must not be narrowed to sunny
    frames = ([(100.0 + 1.5 * i, 0) for i in range(10)] + [(116.0, 0)]
              + [(117.5 + 1.5 * i, 1) for i in range(8)])
    prof = _combine(frames, window_m=60.0)
    for x in np.arange(101.0, 127.0, 0.25):
        lo, hi = RANGES[prof.in_force(float(x))[1]]
        truth = 0 if x < 115.0 else 1
        assert lo <= truth <= hi, (x, (lo, hi))


def _random_look(rng, condition, wrong):
    """A random design for a look at ``condition``: one whose range misses it (``wrong``), else
    one holding it (an abstention one time in five)."""
    if wrong:
        return int(rng.choice([i for i, (lo, hi) in enumerate(RANGES)
                               if not lo <= condition <= hi]))
    holding = [i for i, (lo, hi) in enumerate(RANGES) if lo <= condition <= hi]
    return int(rng.choice(holding)) if rng.random() < 0.8 else 5


def _combined_step(prof, look, design, k, x, **rule):
    """The profile after tick k's look, combined by the rule of ``rule`` (window, tolerance)."""
    return prof.with_combined_decision(look, design, 0.1 * (k + 1), x, rule=_rule(**rule))


@pytest.mark.parametrize("tolerance", [1, 2])
def test_with_at_most_the_tolerated_wrong_frames_in_a_window_every_point_keeps_the_truth(
        tolerance):
    # Random routes (stretches of one condition >= the window), frames every 1-4 m with right
    # ranges (the truth or a range holding it, or an abstention) and at most `tolerance`
    # wrong ones (a range without the truth) in any window: the design in force holds the
    # condition at every point behind the newest frames (DESIGN 6.3, the rule's claim).
    rng = np.random.default_rng(11)
    window = 30.0
    for _ in range(24 if tolerance == 1 else 8):
        bounds = np.cumsum(rng.uniform(window, 2.5 * window, size=6))
        conds = rng.integers(0, 3, size=7)

        def truth(x, bounds=bounds, conds=conds):
            return int(conds[np.searchsorted(bounds, x)])

        wrong, prof = [], SpeedProfile(((-math.inf, 6.0, 5),))
        look = 0.0
        for k in range(120):
            look += float(rng.uniform(1.0, 4.0))
            recent = [w for w in wrong if w > look - 2 * window]
            is_wrong = len(recent) < tolerance and rng.random() < 0.15
            design = _random_look(rng, truth(look), is_wrong)
            if is_wrong:
                wrong.append(look)
            prof = _combined_step(prof, look, design, k, look - 40.0, window_m=window,
                                  tolerance=tolerance)
            for x in np.linspace(look - 40.0, look, 41):
                lo, hi = RANGES[prof.in_force(float(x))[1]]
                assert lo <= truth(x) <= hi, (x, k, (lo, hi), wrong)


def test_the_frontier_brakes_for_the_slowest_command_at_the_last_look_point():
    entries = ((-math.inf, 19.0, 0),)
    free, _ = speed_reference(entries, 0.0, decel_mps2=3.6, margin_m=2.0)
    capped, slope = speed_reference(entries, 0.0, decel_mps2=3.6, margin_m=2.0,
                                    frontier=(40.0, 6.23))
    assert free == 19.0
    assert capped == pytest.approx(math.sqrt(6.23**2 + 2 * 3.6 * 38.0)) and slope < 0
    at_margin, _ = speed_reference(entries, 38.5, decel_mps2=3.6, margin_m=2.0,
                                   frontier=(40.0, 6.23))
    assert at_margin == 6.23


def test_the_supported_speed_brakes_to_the_floor_on_a_frontier_that_has_not_moved():
    from drake_cert.systems.longitudinal import (
        BrakingLimits,
        frontier_latency_s,
        look_ahead_needed_m,
        supported_speed_mps,
    )

    braking = BrakingLimits(decel_mps2=3.6, margin_m=2.0, floor_speed_mps=6.23)
    v = supported_speed_mps(60.0, 5.0, braking=braking)
    tau = frontier_latency_s(5.0)
    assert tau == pytest.approx(0.35)
    # at v the car has 60 - 2 - tau v left when the frontier is about to move: exactly its
    # braking distance to 6.23 m/s at 3.6 m/s^2
    assert (v**2 - 6.23**2) / 7.2 == pytest.approx(60.0 - 2.0 - tau * v)
    assert look_ahead_needed_m(v, 5.0, braking=braking) == pytest.approx(60.0)


def test_a_window_longer_than_the_look_ahead_reaches_behind_the_car():
    # 60 m window, the car at 45 m already past the first look points: the stretches behind
    # it may be rewritten, the one in force at the car stays decided.
    prof = SpeedProfile(((-math.inf, 6.0, 5),))
    for k, (look, design, x) in enumerate([(38.0, 0, 0.0), (40.0, 0, 0.0), (42.0, 0, 44.0),
                                            (44.0, 5, 45.0), (46.0, 0, 45.5), (48.0, 0, 45.5)]):
        prof = prof.with_combined_decision(look, design, 0.1 * (k + 1), x,
                                           rule=_rule(60.0, 1))
    assert prof.in_force(45.5) == (19.0, 0) and prof.in_force(43.0) == (19.0, 0)
    assert prof.in_force(47.0) == (6.0, 5)  # the newest stretch: one frame bounds it so far


@pytest.mark.parametrize("window_m", [30.0, 60.0])
def test_any_sequence_of_decisions_builds_a_sorted_profile_of_lattice_ranges(window_m):
    # Random decisions every 1-4 m (the car 40 m behind): the profile is always built (no
    # error, no endless retry on contradictions) and sorted, and every entry is a range of
    # the lattice.
    rng = np.random.default_rng(7)
    prof, look = SpeedProfile(((-math.inf, 6.0, 5),)), 40.0
    for k in range(400):
        look += float(rng.uniform(1.0, 4.0))
        prof = prof.with_combined_decision(look, int(rng.integers(0, 6)), 0.1 * (k + 1),
                                           look - 40.0, rule=_rule(window_m, 1))
        positions = [e[0] for e in prof.entries]
        assert positions == sorted(positions)
        assert all(e[2] in range(6) and e[1] == RANGE_SPEEDS[e[2]] for e in prof.entries[1:])


def test_a_side_keeps_the_labels_that_all_but_the_tolerated_looks_support():
    from drake_cert.systems.decision_combination import counted_span, side_keeps

    full = (0, 2)
    side = [(0.0, (0, 0))] * 5 + [(0.0, (0, 2))] * 2 + [(0.0, (2, 2))] * 2  # 9 looks
    assert side_keeps(side, tolerance=2, full=full) == {0}  # sunny 7 of 9; snow 4
    assert side_keeps(side, tolerance=5, full=full) == {0, 2}  # 4 >= 9 - 5
    assert side_keeps(side[:2], tolerance=2, full=full) == {0, 1, 2}  # too few: all kept
    # the stretch gets the hull of what either side keeps; a contradiction, the envelope
    assert counted_span(side, [(1.0, (2, 2))] * 9, tolerance=2, full=full) == (0, 2)
    assert counted_span(side, [(1.0, (1, 1))] * 4 + [(1.0, (0, 0))] * 5, tolerance=2,
                        full=full) == (0, 0)
    assert counted_span([(0.0, (0, 0))] * 3 + [(0.0, (2, 2))] * 3,
                        [(1.0, (1, 1))] * 3 + [(1.0, (2, 2))] * 3, tolerance=1,
                        full=full) == (0, 2)


@pytest.mark.parametrize("tolerance,looks_per_side", [(8, 14), (3, 6)])
def test_with_at_most_j_wrong_looks_in_any_run_of_ticks_every_point_keeps_the_truth(
        tolerance, looks_per_side):
    # The counting rule's claim (docs/design.md 6.3): random routes whose stretches of one
    # condition are at least the window long, a look every 1-4 m that holds the truth (or is
    # an abstention) except at most `tolerance` wrong ones in any run of looks_per_side
    # consecutive ticks: the design in force holds the condition at every point behind the
    # newest look.
    rng = np.random.default_rng(12)
    window = 60.0
    for _ in range(6):
        bounds = np.cumsum(rng.uniform(window, 2.0 * window, size=5))
        conds = rng.integers(0, 3, size=6)

        def truth(x, bounds=bounds, conds=conds):
            return int(conds[np.searchsorted(bounds, x)])

        wrong, prof, look = [], SpeedProfile(((-math.inf, 6.0, 5),)), 0.0
        for k in range(160):
            look += float(rng.uniform(1.0, 4.0))
            is_wrong = sum(1 for w in wrong if w > k - looks_per_side) < tolerance and \
                rng.random() < 0.4
            design = _random_look(rng, truth(look), is_wrong)
            if is_wrong:
                wrong.append(k)
            prof = _combined_step(prof, look, design, k, look - 60.0, window_m=window,
                                  tolerance=tolerance, looks_per_side=looks_per_side)
            for x in np.linspace(look - 60.0, look, 61):
                lo, hi = RANGES[prof.in_force(float(x))[1]]
                assert lo <= truth(x) <= hi, (x, k, (lo, hi))
        assert len(wrong) > 10  # the rule was tested against wrong looks


def test_the_run_bound_holds_when_each_ticks_miss_chance_depends_on_the_past():
    # Each tick is wrong with a probability chosen from the history (here: p after a clean
    # tick, p / 2 after a wrong one, 0 every fifth tick), never above p: the count in a run
    # of m ticks is dominated by Bin(m, p) (docs/design.md 6.2, the coupling argument).
    from drake_cert.systems.decision_combination import run_failure_bound

    rng = np.random.default_rng(13)
    p, m, j, trials = 0.3, 8, 4, 40000
    tail = run_failure_bound(p, m, j)
    assert tail == pytest.approx(sum(math.comb(m, i) * p**i * (1 - p)**(m - i)
                                     for i in range(j + 1, m + 1)))
    wrong = np.zeros((trials, m), dtype=bool)
    for t in range(m):
        chance = np.where(wrong[:, t - 1], p / 2, p) if t else np.full(trials, p)
        if t % 5 == 4:
            chance = np.zeros(trials)
        wrong[:, t] = rng.random(trials) < chance
    assert float(np.mean(wrong.sum(axis=1) > j)) <= tail
