"""The certified closed loop, camera frame to steering, in one Drake Diagram (DESIGN 6).

Claims checked on drives (Fiala plant, shipped models and scenarios):
- under a stability attack inside its certificate, the certified car stays in its lane, where
  the non-robust car under the same attack is fooled into the grippy design's speed on snow and
  leaves it;
- under an efficiency attack the certified car keeps moving;
- NaN and mis-shaped frames give the family envelope, never a crash or a nominal value;
- the same seed gives the same summary; design switches respect the dwell time; the speed of a
  slower segment is reached before the segment starts.
"""

import copy
import dataclasses

import numpy as np
import pytest

from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.errors import ConfigError
from drake_cert.synthesis.selection import envelope_design_index, preset_designs
from drake_cert.synthesis.table import synthesize_table
from drake_cert.systems.driving import (
    build_certified_driving_diagram,
    drive,
    drive_scenario,
    time_left_lane,
    with_overrides,
)
from drake_cert.systems.route import SegmentSpec
from drake_cert.systems.scenario import SHIPPED_SCENARIOS, load_scenario
from drake_cert.threads import available_cores

VOLATILE = ("wall_s", "real_time_factor")


@pytest.fixture(scope="module")
def setup():
    vehicle, conditions, settings = load_vehicle(), load_conditions(), load_settings()
    designs = synthesize_table(vehicle, conditions, settings)
    return dict(vehicle=vehicle, conditions=conditions, settings=settings, designs=designs)


def within_test_budget(scenario, n=300):
    """The scenario with at most ``n`` samples per decision (the test budget; shipped: 1000 on
    robotcar-like). The conformal calibration is the shipped one (its votes ship with the model
    and do not depend on the run-time n)."""
    return dataclasses.replace(scenario, perception=dataclasses.replace(scenario.perception, n=n))


def snow_curve():
    """The end of dry-to-snow: rain, then snow with a 50 m-radius curve; camera at 10 Hz as
    shipped, at most 300 samples per decision (test budget; the shipped scenario: 1000)."""
    sc = load_scenario("dry_to_snow")
    route = [SegmentSpec(60.0, 0.0, "rain"), SegmentSpec(20.0, 0.0, "snow"),
             SegmentSpec(50.0, 1 / 50, "snow"), SegmentSpec(10.0, 0.0, "snow")]
    return within_test_budget(dataclasses.replace(sc, route=route))


def short(scenario, seconds):
    return dataclasses.replace(scenario, t_final_s=seconds)


@pytest.fixture(scope="module")
def under_sa(setup):
    """The certified and the base pipeline on the same route under the same attack."""
    scenario = snow_curve()
    assert scenario.attack.eps <= scenario.perception.eps  # the attack is inside the budget
    out = {}
    for pipeline in ("base", "certified"):
        sc = with_overrides(scenario, pipeline=pipeline, attack="sa")
        built = build_certified_driving_diagram(sc, **setup)
        out[pipeline] = (built, drive(built))
    return out


def test_certified_car_stays_in_lane_where_the_base_car_is_fooled_on_snow(under_sa):
    base, certified = under_sa["base"][1], under_sa["certified"][1]
    # The base car is fooled (below: most of its intervals miss, seconds unprotected). On this
    # 140 m route at 10 Hz it enters the curve slowly enough to keep its lane (peak 0.16 m,
    # measured); on the whole dry_to_snow route it leaves it (make run, the seed study).
    assert not certified.summary["left_lane"], certified.summary
    assert certified.summary["ending"] == "route end"
    # Every tick's interval holds the true stiffness of the segment it saw, and at every
    # instant the design in force holds the stiffness under the car, the car no faster than
    # its safe speed (the rain -> snow boundary included).
    assert certified.summary["interval_covers_true_fraction"] == 1.0
    assert certified.summary["time_unprotected_s"] == 0.0
    assert certified.summary["design_covers_true_fraction"] == 1.0
    assert base.summary["interval_covers_true_fraction"] < 0.5
    assert base.summary["time_unprotected_s"] > 1.0
    # switching among the preset's state-feedback loops is certified at any rate (jointly
    # synthesized gains); so are the L1 loops with their filter state (the estimate is carried
    # across a switch, docs/design.md 5.6 (b)): the drive's switching met its certificate
    assert certified.summary["switching_method"] == "common"
    assert certified.summary["loop_switching_decay_per_s"] > 0.0
    assert certified.summary["design_switches"] > 0
    assert certified.summary["switching_certificate_met"] is True
    assert "switching_note" not in certified.summary
    # the designs that were in force, in the order they took over (the front tire's C)
    intervals = certified.summary["design_intervals_n_per_rad"]
    assert len(intervals) >= 2 and len({tuple(r) for r in intervals}) == len(intervals)
    assert intervals[0] == [float(x) for x in certified.tape.design_interval_n_per_rad[0]]


def test_under_an_efficiency_attack_the_certified_car_keeps_moving(setup):
    scenario = with_overrides(snow_curve(), pipeline="certified", attack="ea")
    result = drive_scenario(short(scenario, 8.0), **setup)
    assert not result.summary["left_lane"]
    assert result.summary["min_speed_mps"] >= scenario.motion.stop_speed_mps
    assert result.summary["ending"] in ("time limit", "route end")


@pytest.mark.parametrize("fault", ["nan", "misshaped"])
def test_bad_frames_fall_back_to_the_envelope_never_to_a_nominal(setup, fault):
    import torch

    scenario = with_overrides(snow_curve(), pipeline="certified", attack=fault)
    threads = torch.get_num_threads()
    result = drive_scenario(short(scenario, 2.0), **setup)
    assert torch.get_num_threads() == threads  # the drive's one thread does not outlive it
    envelope = setup["conditions"].envelope("robotcar-like")
    ticks = result.ticks
    assert len(ticks.times_s) >= 9  # 2 s at 5 Hz
    assert np.all(ticks.status == 1)
    assert result.summary["abstention_fraction"] == 1.0  # each frame's own decision
    assert np.allclose(ticks.interval_n_per_rad, envelope)
    table = preset_designs(setup["designs"], setup["conditions"], "robotcar-like")
    assert np.all(ticks.design_index == envelope_design_index(table, setup["conditions"],
                                                              "robotcar-like"))
    assert not result.summary["left_lane"]


def test_the_same_seed_gives_the_same_summary(setup):
    scenario = short(with_overrides(snow_curve(), pipeline="certified", attack="sa"), 1.5)
    first = drive_scenario(scenario, **setup).summary
    second = drive_scenario(scenario, **setup).summary
    for key in VOLATILE:
        first.pop(key), second.pop(key)
    assert first == second
    other = drive_scenario(with_overrides(scenario, seed=scenario.seed + 1), **setup).summary
    assert other["seed"] != first["seed"]


def test_noise_drawn_ahead_between_frames_leaves_every_number_of_the_drive(setup):
    # The next tick's first noise is drawn on a worker thread while the simulation runs
    # (DESIGN 3.8): the drive with it is the drive without it, sample for sample.
    scenario = short(with_overrides(snow_curve(), pipeline="certified", attack="sa"), 1.5)
    results = []
    for ahead in (True, False):
        built = build_certified_driving_diagram(scenario, **setup)
        perception = built.systems["perception"]
        assert bool(perception.draw_ahead_samples) == (available_cores() >= 2)
        if not ahead:
            perception.draw_ahead_samples = 0
        results.append(drive(built))
    with_ahead, without = (r.summary for r in results)
    for key in VOLATILE:
        with_ahead.pop(key), without.pop(key)
    assert with_ahead == without
    assert list(results[0].ticks.samples) == list(results[1].ticks.samples)


def test_every_drive_shares_one_conformal_calibration_whatever_its_seed(setup):
    # The calibration is the model's (DESIGN 3.6): another seed, or fresh noise from the OS,
    # drives with the same thresholds, so a seed study calibrates once and a fresh-noise drive
    # replays exactly from the seed it records.
    scenario = short(snow_curve(), 0.2)
    assert scenario.perception.interval == "conformal"  # the shipped default
    built = [build_certified_driving_diagram(dataclasses.replace(scenario, seed=seed), **setup)
             for seed in (1, 7, None)]  # None: fresh noise from the OS
    assert built[2].seed_source == "os-entropy"
    calibrations = [b.systems["perception"].conformal for b in built]
    assert calibrations[0] is not None
    assert calibrations[1] == calibrations[0] and calibrations[2] == calibrations[0]


def test_an_abstention_shows_the_envelope_at_once_and_the_dwell_adds_held_ticks(under_sa):
    """A tick whose own decision is the envelope (abstained) has the envelope in force at its
    look point at once (a widening); the dwell time may hold the envelope a little longer, so
    the envelope share of the ticks is at least the abstention share."""
    built, result = under_sa["certified"]
    ticks, summary = result.ticks, result.summary
    envelope = built.systems["interval"].envelope_index
    abstained = ticks.requested_design_index == envelope
    assert np.all(ticks.status[abstained] == 1)
    assert summary["abstention_fraction"] == pytest.approx(np.mean(abstained))
    assert summary["abstention_fraction"] <= summary["envelope_fraction"]
    # a certified tick whose interval misses the frame's true stiffness is certified wrong
    seen = ticks.seen_stiffness_n_per_rad
    missed = (seen < ticks.interval_n_per_rad[:, 0]) | (seen > ticks.interval_n_per_rad[:, 1])
    assert summary["certified_wrong_fraction"] == pytest.approx(np.mean(missed & ~abstained))
    held = (ticks.status == 1) & ~abstained  # the envelope held by the dwell time
    assert np.all(ticks.design_index[held] == envelope)


def test_switches_respect_the_dwell_time_and_slower_speeds_come_before_the_segment(under_sa):
    built, result = under_sa["certified"]
    ticks = result.ticks
    labels = [tuple(d.labels) for d in built.designs]
    family = max(labels, key=len)  # the envelope's range: the whole family, friction order
    span = [(family.index(r[0]), family.index(r[-1])) for r in labels]
    changes = np.nonzero(np.diff(ticks.design_index) != 0)[0] + 1
    assert len(changes) >= 1
    dwell = built.scenario.controller.dwell_time_s
    for previous, k in zip(changes[:-1], changes[1:], strict=True):
        old, new = span[ticks.design_index[k - 1]], span[ticks.design_index[k]]
        widening = new[0] <= old[0] and old[1] <= new[1]  # holds all the old design held
        if not widening:  # narrowing or moving: at least the dwell after the last switch
            assert ticks.times_s[k] - ticks.times_s[previous] >= dwell - 1e-9
    # Where the snow starts the car is no faster than the snow design's speed: the command of
    # the snow segment (or a slower, uncertified one) was reached before the segment.
    tape = result.tape
    snow_start = built.route.segments[1].start_m
    at_start = np.searchsorted(tape.arc_length_m, snow_start)
    snow_speed = max(d.speed_mps for d in built.designs if d.labels == ["snow"])
    assert tape.speed_mps[at_start] <= snow_speed + 0.05


def _speed_of(designs, labels):
    return max(d.speed_mps for d in designs if d.labels == labels)


@pytest.mark.slow  # ~50 s on 2 cores (test_longitudinal.py checks the rule itself)
def test_entering_snow_at_full_sunny_speed_the_car_brakes_inside_what_it_has_seen(setup):
    # The shipped sunny_into_snow with its sunny straight cut to 180 m (test budget; from the
    # route's start the car needs 84 m to reach 19.36 m/s at 2 m/s^2, and some 55 m to brake
    # to snow's 10.2 m/s), then snow in a curve; 5 Hz
    # camera 60 m ahead, under SA at the certified budget. The car reaches the sunny design's
    # speed on the straight and is down to a design that holds snow, at its safe speed, by the
    # first metre of snow. (The paper's safe-set interval: within the test budget, n <= 300
    # and 20 calibration frames a label, the conformal sets of sunny frames keep rain, and the
    # car would never reach the sunny speed this test is about.)
    shipped = load_scenario("sunny_into_snow")
    shipped = dataclasses.replace(shipped, perception=dataclasses.replace(
        shipped.perception, interval="safe_set"))
    route = [dataclasses.replace(shipped.route[0], length_m=180.0), *shipped.route[1:]]
    attack = dataclasses.replace(shipped.attack, steps=3, noise_draws=2)  # test budget
    scenario = with_overrides(within_test_budget(dataclasses.replace(shipped, route=route,
                                                                     attack=attack)),
                              attack="sa")
    assert scenario.attack.eps <= scenario.perception.eps
    result = drive_scenario(scenario, **setup)
    s, tape = result.summary, result.tape
    assert not s["left_lane"] and s["ending"] == "route end", s
    assert s["time_unprotected_s"] == 0.0 and s["design_covers_true_fraction"] == 1.0
    straight = (tape.arc_length_m > 40.0) & (tape.arc_length_m < 175.0)
    assert tape.speed_mps[straight].max() >= 0.95 * _speed_of(setup["designs"], ["sunny"])
    at_snow = np.searchsorted(tape.arc_length_m, 180.0)
    assert tape.speed_mps[at_snow] <= _speed_of(setup["designs"], ["snow"]) + 0.1


@pytest.mark.slow
@pytest.mark.parametrize("name", SHIPPED_SCENARIOS)
@pytest.mark.parametrize("attack", ["none", "sa"])
def test_every_shipped_scenario_keeps_the_design_in_force_on_the_truth(setup, name, attack):
    # As shipped (sample budgets included): no attack and SA within the certified budget.
    scenario = with_overrides(load_scenario(name), pipeline="certified", attack=attack)
    assert scenario.attack.eps <= scenario.perception.eps
    s = drive_scenario(scenario, **setup).summary
    assert not s["left_lane"] and s["ending"] == "route end", s
    assert s["time_unprotected_s"] == 0.0, s


@pytest.mark.slow
def test_on_the_snow_route_the_certified_car_keeps_its_speed_under_attack(setup):
    # dry_to_snow as shipped: under SA the certified car keeps >= 80% of its own unattacked
    # mean speed, unattacked >= 90% of the base car's; the base car leaves its lane under SA
    # in most drives (whether a frame the attack did not fool lies just before the snow curve
    # is chance: measured, seeds 2-9 left, the shipped seed 1 did not; here: seeds 1-5, >= 3).
    runs = {}
    for pipeline, attack in (("certified", "none"), ("certified", "sa"), ("base", "none"),
                             ("base", "sa")):
        scenario = with_overrides(load_scenario("dry_to_snow"), pipeline=pipeline,
                                  attack=attack)
        runs[pipeline, attack] = drive_scenario(scenario, **setup).summary
    speed = {k: v["mean_speed_mps"] for k, v in runs.items()}
    assert speed["certified", "sa"] >= 0.8 * speed["certified", "none"], speed
    assert speed["certified", "none"] >= 0.9 * speed["base", "none"], speed
    shipped = load_scenario("dry_to_snow")
    left = [runs["base", "sa"]["left_lane"]]
    for seed in range(shipped.seed + 1, shipped.seed + 5):
        scenario = with_overrides(shipped, pipeline="base", attack="sa", seed=seed)
        left.append(drive_scenario(scenario, **setup).summary["left_lane"])
    assert sum(left) >= 3, left


def hand_tape(truth, lo, hi, speed, design_speed, dt=0.05):
    """A DriveTape from per-sample arrays: only the fields the protection metrics read matter."""
    from drake_cert.systems.driving import DriveTape

    n = len(truth)
    zeros = np.zeros(n)
    return DriveTape(times_s=np.arange(n) * dt, states=np.zeros((n, 4)), steering_rad=zeros,
                     speed_mps=np.asarray(speed, float), speed_command_mps=zeros,
                     arc_length_m=zeros, curvature_per_m=zeros,
                     interval_n_per_rad=np.zeros((n, 2)),
                     true_stiffness_n_per_rad=np.asarray(truth, float),
                     design_index=np.zeros(n, int), certified_radius=zeros,
                     status=np.zeros(n, int), lane_margin_m=0.85,
                     design_interval_n_per_rad=np.column_stack([lo, hi]).astype(float),
                     design_speed_mps=np.asarray(design_speed, float))


def test_unprotected_time_counts_a_design_missing_the_truth_or_a_car_too_fast_for_it():
    from drake_cert.systems.driving import protection

    n = 21  # 20 intervals of 50 ms
    truth = np.full(n, 50e3)
    lo, hi = np.full(n, 40e3), np.full(n, 60e3)
    lo[4:8] = 60e3  # 4 samples (0.2 s) under a design for 60-120 kN/rad: truth outside
    speed, design_speed = np.full(n, 10.0), np.full(n, 10.0)
    speed[12:14] = 10.2  # 2 samples (0.1 s) faster than the design's speed + 0.1 m/s
    speed[15] = 10.05  # within the 0.1 m/s slack: protected
    covers, unprotected = protection(hand_tape(truth, lo, hi, speed, design_speed))
    assert covers == pytest.approx(16 / 20)
    assert unprotected == pytest.approx(0.3)
    all_good = protection(hand_tape(truth, np.full(n, 40e3), hi, np.full(n, 9.0), design_speed))
    assert all_good == (1.0, 0.0)


def test_the_drive_summary_reports_the_design_in_force_beside_the_look_ahead_figure(setup):
    scenario = dataclasses.replace(with_overrides(snow_curve(), pipeline="certified",
                                                  attack="sa"), t_final_s=3.0)
    result = drive_scenario(scenario, **setup)
    s, tape = result.summary, result.tape
    assert {"interval_covers_true_fraction", "design_covers_true_fraction",
            "time_unprotected_s", "attack_within_certified_budget"} <= set(s)
    assert s["attack_within_certified_budget"]  # the shipped attack is inside the budget
    lo, hi = tape.design_interval_n_per_rad.T
    table = {i: d for i, d in enumerate(preset_designs(setup["designs"], setup["conditions"],
                                                       scenario.perception.preset))}
    for i, a, b in zip(tape.design_index, lo, hi, strict=True):
        assert (a, b) == tuple(table[int(i)].interval)
    over = with_overrides(scenario, eps=scenario.perception.eps * 1.5)
    assert not drive_scenario(dataclasses.replace(over, t_final_s=0.5),
                              **setup).summary["attack_within_certified_budget"]


@pytest.mark.slow  # ~40 s (test_switching_gradient.py drives the law in the fast suite)
def test_the_gradient_law_drives_the_switching_controller_with_an_implicit_integrator(setup):
    sc = load_scenario("dry_to_snow")
    gradient = dataclasses.replace(sc.controller, law="gradient")
    with pytest.raises(ConfigError, match="needs an implicit integrator"):
        dataclasses.replace(sc, controller=gradient).validate("scenario")  # RK2 at 1 ms
    radau = copy.copy(sc.simulator)  # a pydrake SimulatorConfig
    radau.integration_scheme = "radau3"
    scenario = short(dataclasses.replace(snow_curve(), controller=gradient, simulator=radau), 14.0)
    result = drive_scenario(with_overrides(scenario, pipeline="certified", attack="none"),
                            **setup)
    assert np.all(np.isfinite(result.tape.states))
    assert not result.summary["left_lane"] and result.summary["time_unprotected_s"] == 0.0
    assert result.summary["design_switches"] >= 1  # past the lead-in: designs switch


def test_a_diverged_drive_is_not_in_its_lane():
    tape = hand_tape([50e3] * 4, [40e3] * 4, [60e3] * 4, [10.0] * 4, [12.0] * 4)
    tape.states[2, 0] = np.nan
    assert time_left_lane(tape) == pytest.approx(tape.times_s[2])


def inject_wrong_frame(built, wrong_label: str, where) -> dict:
    """Make the certified-interval block certify ``wrong_label`` (a label the frame does not
    show) for the first good frame whose look point satisfies ``where(position_m)``: a frame
    certified wrong, as when g is wrong on the clean frame or a certificate fails. Returns a
    dict that receives the tick and the true label of that frame."""
    block = built.systems["interval"]
    original, done = block.request, {}

    def request(p):
        if p.frame_ok and not done and where(p.position_m):
            done.update(tick=p.tick, true_label=block.label_names[p.label_index])
            return block._decision(p, block._by_labels[(wrong_label,)], "certified", 2.0)
        return original(p)

    block.request = request
    return done


@pytest.mark.slow
@pytest.mark.parametrize("name, attack, wrong, where", [
    # a clean sunny frame certified {snow} on the straight before the snow
    ("sunny_straight_to_snow", "none", "snow", lambda x: 140.0 <= x < 160.0),
    # the first rain frame after a curve entry certified {sunny} (attacked rain frame)
    ("curve_entry_changes", "sa", "sunny", lambda x: 90.0 <= x < 95.0),
])
@pytest.mark.parametrize("interval", ["conformal", "safe_set"])
def test_an_injected_wrong_frame_leaves_the_design_in_force_on_the_truth(setup, name, attack,
                                                                         wrong, where, interval):
    # One wrong certified frame among right ones is within the rule's tolerance (DESIGN 6.3),
    # with the default interval and with the paper's: the design in force holds the stiffness
    # under the car all along.
    shipped = load_scenario(name)
    shipped = dataclasses.replace(shipped, perception=dataclasses.replace(
        shipped.perception, interval=interval))
    scenario = with_overrides(shipped, pipeline="certified", attack=attack)
    built = build_certified_driving_diagram(scenario, **setup)
    injected = inject_wrong_frame(built, wrong, where)
    s = drive(built).summary
    assert injected and injected["true_label"] != wrong, injected
    assert not s["left_lane"] and s["ending"] == "route end", s
    assert s["time_unprotected_s"] == 0.0 and s["design_covers_true_fraction"] == 1.0, s


def test_the_guarantee_failure_bound_is_delta_cal_plus_a_binomial_tail_per_run_of_ticks():
    # docs/design.md 6.2: given a good calibration (probability >= 1 - delta_cal) each tick
    # misses with probability at most p whatever came before, so a run of m consecutive
    # ticks holds more than j misses with probability at most P(Bin(m, p) > j); the counting
    # rule fails only if a side (such a run) does; R = P - m + 1 runs in P planned ticks.
    from scipy.stats import binom

    from drake_cert.systems.driving import guarantee_failure_bound, guarantee_summary

    class Design:  # only the speeds matter to the plan
        def __init__(self, speed):
            self.speed_mps, self.has_safe_speed = speed, True

    class Calibration:
        alpha_total, delta_cal = 0.2518, 0.001

    class Marginal:  # a marginal calibration gives no per-run statement: Markov only
        alpha_total, delta_cal = 0.2518, 0.0

    table = [Design(19.4), Design(16.0), Design(6.2)]
    conformal = load_scenario("dry_to_snow")  # the shipped default interval
    m, j = conformal.looks_per_side, conformal.tolerated_wrong_frames
    g = guarantee_summary(conformal, table, Calibration())
    planned = g["planned_ticks"]
    assert g["standing_assumption"] is False and g["interval"] == "conformal"
    assert g["frame_miscoverage"] == 0.2518 and g["calibration_failure_bound"] == 0.001
    assert g["guarantee_failure_bound"] == pytest.approx(
        0.001 + (planned - m + 1) * binom.sf(j, m, 0.2518))
    assert g["guarantee_failure_bound"] <= 0.01
    assert guarantee_failure_bound(conformal, planned, 0.2518, Marginal()) == 1.0
    one = dataclasses.replace(conformal, tolerated_wrong_frames=1)
    assert guarantee_failure_bound(one, planned, 0.2518, Calibration()) == 1.0  # vacuous: says so
    sc = dataclasses.replace(conformal, perception=dataclasses.replace(
        conformal.perception, interval="safe_set"))
    safe = guarantee_summary(sc, table)
    assert safe["interval"] == "safe_set" and safe["standing_assumption"] is True
    assert safe["frame_miscoverage"] == 0.0 and safe["tolerated_wrong_frames"] == j
    assert safe["guarantee_failure_bound"] == pytest.approx(sc.perception.alpha / (j + 1))
    per_decision = dataclasses.replace(sc, perception=dataclasses.replace(
        sc.perception, alpha_scope="decision", alpha=0.001))
    assert guarantee_failure_bound(per_decision, 100, 0.0) == pytest.approx(0.1 / (j + 1))
    base = with_overrides(sc, pipeline="base")
    assert guarantee_summary(base, table)["guarantee_failure_bound"] is None


def test_a_regression_drive_whose_calibration_gives_the_envelope_says_so():
    import math

    from drake_cert.systems.driving import _calibration_warnings

    sc = load_scenario("dry_to_snow")
    regress = dataclasses.replace(sc, perception=dataclasses.replace(sc.perception,
                                                                     task="regress"))
    (warning,) = _calibration_warnings(regress, math.inf)
    assert "20 calibration frames per label" in warning and "at least 99" in warning
    assert _calibration_warnings(regress, 4000.0) == []
    assert _calibration_warnings(sc, math.inf) == []  # classification: no regression beta
