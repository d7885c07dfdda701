"""Camera, attacker, perception smoothing and certified interval as Drake systems (DESIGN 6.1)."""

import dataclasses
import math

import pytest
import torch
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from drake_cert.config import load_conditions
from drake_cert.perception.models import load_model
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.systems.attacker import Attacker
from drake_cert.systems.camera import CameraSource
from drake_cert.systems.certified_interval import STATUS_CODES, CertifiedInterval, IntervalInputs
from drake_cert.systems.perception_smoothing import (
    PerceptionInputs,
    PerceptionResult,
    PerceptionSmoothing,
)
from drake_cert.systems.route import Route, SegmentSpec
from drake_cert.systems.scenario import (
    AttackSettingsYaml,
    CameraSettings,
    ControllerScenario,
    PerceptionSettings,
)

PRESET = "robotcar-like"
SIGMA = 0.25
EPS = 0.1
CERTIFIED = PerceptionSettings(preset=PRESET, sigma=SIGMA, eps=EPS)
BASE = dataclasses.replace(CERTIFIED, pipeline="base")


@pytest.fixture(scope="module")
def conditions():
    return load_conditions()


@pytest.fixture(scope="module")
def labels(conditions):
    return tuple(conditions.preset(PRESET).labels)


@pytest.fixture(scope="module")
def route(conditions):
    specs = [SegmentSpec(50.0, 0.0, "sunny"), SegmentSpec(50.0, 0.01, "snow"),
             SegmentSpec(100.0, 0.0, "rain")]
    return Route.build(specs, conditions, PRESET, seed=5)


@pytest.fixture(scope="module")
def designs(conditions):
    """One design per contiguous label range; safe speeds made up (no synthesis needed)."""
    out = []
    for rng in conditions.contiguous_ranges(PRESET):
        lo, hi = conditions.hull(rng)
        out.append(ControllerDesign(list(rng), lo, hi, 0.5 * (lo + hi),
                                    conditions.least_friction(rng), [0.0] * 4, 30.0, 100.0,
                                    speed_mps=20.0 - 3.0 * len(rng) - rng.index(rng[-1])))
    return out


@pytest.fixture(scope="module")
def smoothed_model():
    return load_model(PRESET, "classify", SIGMA)


def _pipeline(route, conditions, labels, designs, model, *, kind="none", seed=0, n=200,
              mode="certified", dwell=0.3, attack_steps=5):
    builder = DiagramBuilder()
    camera = builder.AddSystem(CameraSource(route, conditions, PRESET, seed=seed))
    settings = PerceptionSettings(preset=PRESET, pipeline=mode, sigma=SIGMA, eps=EPS, n0=20,
                                  n=n, batch_size=n, decision="fixed")
    attacker = builder.AddSystem(Attacker(
        AttackSettingsYaml(kind, eps=EPS, target="base", steps=attack_steps), settings,
        model=model, seed=seed))
    perception = builder.AddSystem(PerceptionSmoothing(
        model, settings, seed=seed, inputs=PerceptionInputs(label_names=labels)))
    interval = builder.AddSystem(CertifiedInterval(designs, conditions, settings,
                                                   ControllerScenario(dwell_time_s=dwell)))
    builder.Connect(camera.GetOutputPort("frame"), attacker.GetInputPort("frame"))
    builder.Connect(attacker.GetOutputPort("frame"), perception.GetInputPort("frame"))
    builder.Connect(perception.GetOutputPort("perception"), interval.GetInputPort("perception"))
    builder.ExportInput(camera.GetInputPort("arc_length_m"), "arc_length_m")
    diagram = builder.Build()
    simulator = Simulator(diagram)
    diagram.get_input_port(0).FixValue(simulator.get_mutable_context(), [0.0])
    return diagram, simulator, camera, attacker, perception, interval


def _eval(system, port, simulator):
    return system.GetOutputPort(port).Eval(
        system.GetMyContextFromRoot(simulator.get_context()))


def test_camera_shows_the_segment_at_the_look_ahead_point(route, conditions):
    camera = CameraSource(route, conditions, PRESET, CameraSettings(look_ahead_m=40.0), seed=1)
    context = camera.CreateDefaultContext()
    simulator = Simulator(camera, context)
    for k, (s, index) in enumerate([(5.0, 0), (10.0, 1), (15.0, 1), (70.0, 2)]):
        camera.GetInputPort("arc_length_m").FixValue(simulator.get_mutable_context(), [s])
        simulator.AdvanceTo(k * 0.1 + 0.01)  # one camera tick at t = k / 10
        frame = camera.GetOutputPort("frame").Eval(context)
        seg = route.segments[index]
        assert frame.tick == k and frame.position_m == s + 40.0  # s = 10: exactly a boundary
        assert (frame.label_index, frame.stiffness_n_per_rad) == (seg.label_index,
                                                                  seg.stiffness_n_per_rad)
        assert camera.GetOutputPort("seen_stiffness_n_per_rad").Eval(context)[0] == \
            seg.stiffness_n_per_rad
        assert frame.image.shape == (3, 64, 64) and 0 <= frame.image.min() <= 1
    again = camera.capture(0.3, 70.0, 3)
    assert torch.equal(again.image, frame.image)  # deterministic by (seed, tick)
    assert not torch.equal(camera.capture(0.4, 70.0, 4).image, frame.image)


@pytest.mark.parametrize("kind", ["nan", "misshaped"])
def test_a_bad_frame_gives_the_envelope_and_is_reported(kind, route, conditions, labels,
                                                        designs, smoothed_model):
    diagram, simulator, _, attacker, perception, interval = _pipeline(
        route, conditions, labels, designs, smoothed_model, kind=kind)
    simulator.AdvanceTo(0.35)
    seen = _eval(attacker, "frame", simulator)
    assert seen.attack == kind
    result = _eval(perception, "perception", simulator)
    assert result.tick == 3 and not result.frame_ok and result.error  # ticks at 0, .., 0.3
    decision = _eval(interval, "decision", simulator)
    envelope = conditions.envelope(PRESET)
    assert decision.status == "envelope" and decision.interval == envelope
    assert decision.labels == labels and decision.radius == 0.0
    assert list(_eval(interval, "interval_n_per_rad", simulator)) == list(envelope)
    assert _eval(interval, "status", simulator)[0] == STATUS_CODES["envelope"]


def test_the_attackers_output_is_computed_once_per_frame(route, conditions, labels, designs,
                                                        smoothed_model):
    _, simulator, _, attacker, _, _ = _pipeline(route, conditions, labels, designs,
                                                smoothed_model, kind="misshaped")
    simulator.AdvanceTo(0.01)
    first = _eval(attacker, "frame", simulator)
    assert _eval(attacker, "frame", simulator) is first
    simulator.AdvanceTo(0.11)
    assert _eval(attacker, "frame", simulator).tick == 1


def test_a_clean_frame_is_certified_with_an_interval_holding_the_true_stiffness(
        route, conditions, labels, designs, smoothed_model):
    _, simulator, _, _, _, interval = _pipeline(route, conditions, labels, designs,
                                                smoothed_model)
    simulator.AdvanceTo(0.06)  # camera at 0, perception at 0.025, interval at 0.05
    decision = _eval(interval, "decision", simulator)
    assert decision.frame_ok and decision.tick == 0
    assert decision.status == "certified" and decision.radius > EPS
    lo, hi = decision.interval
    assert lo <= decision.true_stiffness_n_per_rad <= hi
    assert hi - lo < conditions.envelope(PRESET)[1] - conditions.envelope(PRESET)[0]
    assert designs[decision.design_index].interval == decision.interval
    assert decision.speed_command_mps == designs[decision.design_index].speed_mps


def test_base_mode_gives_the_raw_labels_own_interval(route, conditions, labels, designs):
    base_model = load_model(PRESET, "classify", 0.0)
    _, simulator, _, _, perception, interval = _pipeline(
        route, conditions, labels, designs, base_model, mode="base")
    simulator.AdvanceTo(0.06)
    result = _eval(perception, "perception", simulator)
    assert result.certificate is None and result.base_label is not None
    decision = _eval(interval, "decision", simulator)
    name = labels[result.base_label]
    assert decision.status == "base" and decision.labels == (name,)
    assert decision.interval == conditions.condition(name).interval
    assert _eval(interval, "status", simulator)[0] == STATUS_CODES["base"]


def _scripted(label: int, tick: int, position_m: float) -> PerceptionResult:
    return PerceptionResult(time_s=0.1 * tick + 0.025, tick=tick, position_m=position_m,
                            frame_ok=True, error="", mode="base", task="classify",
                            base_label=label, label_index=label, stiffness_n_per_rad=5e4)


def test_the_dwell_time_holds_back_a_narrowing_with_the_join_of_both_in_force(conditions,
                                                                              labels, designs):
    block = CertifiedInterval(designs, conditions, BASE, ControllerScenario(dwell_time_s=0.3))
    context = block.CreateDefaultContext()
    simulator = Simulator(block, context)
    index = {tuple(d.labels): i for i, d in enumerate(designs)}
    sunny, snow = index[("sunny",)], index[("snow",)]
    envelope = index[tuple(conditions.preset(PRESET).labels)]  # sunny..snow: the join
    seen = []
    script = [0, 2, 2, 2, 2, 2]  # sunny at tick 0, then snow from tick 1 on
    for tick, label in enumerate(script):
        block.GetInputPort("perception").FixValue(context, _scripted(label, tick, 40.0 + tick))
        simulator.AdvanceTo(0.1 * tick + 0.06)  # the update at 0.1 k + 0.05
        seen.append(block.GetOutputPort("decision").Eval(context))
        # the request behind the decision (the drive's abstention count reads this port)
        assert _eval(block, "requested_design_index", simulator)[0] == \
            seen[-1].requested_design_index == index[(labels[label],)]
    assert seen[0].design_index == sunny and not seen[0].held  # the first switch is free
    # t = 0.15: snow is not a widening of sunny and comes 0.1 s after a switch: held back, and
    # meanwhile the join (the envelope, holding sunny and snow alike) is in force at once.
    for d in seen[1:4]:  # t = 0.15, 0.25, 0.35: within 0.3 s of the switch to the join
        assert d.held and d.design_index == envelope and d.requested_design_index == snow
        assert d.speed_command_mps == min(designs[envelope].speed_mps, designs[snow].speed_mps)
        assert d.position_m == 41.0  # the look point of the first request
    assert seen[4].design_index == snow and not seen[4].held  # t = 0.45: dwell elapsed
    assert seen[4].position_m == 41.0 and seen[4].time_s == pytest.approx(0.45)
    assert seen[5].design_index == snow and seen[5].position_m == 45.0


def test_a_widening_applies_at_once_whatever_the_dwell(conditions, labels, designs):
    block = CertifiedInterval(designs, conditions, BASE, ControllerScenario(dwell_time_s=10.0))
    context = block.CreateDefaultContext()
    simulator = Simulator(block, context)
    envelope = [tuple(d.labels) for d in designs].index(tuple(conditions.preset(PRESET).labels))
    block.GetInputPort("perception").FixValue(context, _scripted(0, 0, 40.0))
    simulator.AdvanceTo(0.06)
    bad = dataclasses.replace(_scripted(0, 1, 41.0), frame_ok=False, error="NaN")
    block.GetInputPort("perception").FixValue(context, bad)
    simulator.AdvanceTo(0.16)  # 0.1 s after the switch to sunny, far inside the dwell
    decision = block.GetOutputPort("decision").Eval(context)
    assert decision.design_index == envelope and not decision.held


def test_a_design_without_safe_speed_commands_a_stop(conditions, labels, designs):
    stopped = [dataclasses.replace(d, speed_mps=0.0, failed_condition="grip")
               if tuple(d.labels) == labels else d for d in designs]
    block = CertifiedInterval(stopped, conditions, CERTIFIED)
    context = block.CreateDefaultContext()  # the initial state: the envelope
    assert block.GetOutputPort("speed_command_mps").Eval(context)[0] == 0.0
    assert block.GetOutputPort("status").Eval(context)[0] == STATUS_CODES["stop"]
    assert block.GetOutputPort("decision").Eval(context).interval == conditions.envelope(PRESET)


def test_same_seed_gives_identical_frames_attacks_and_decisions(route, conditions, labels,
                                                                designs, smoothed_model):
    runs = []
    for _ in range(2):
        diagram, simulator, _, attacker, _, interval = _pipeline(
            route, conditions, labels, designs, smoothed_model, kind="sa", seed=11, n=100,
            attack_steps=3)
        decisions, images = [], []
        for tick in range(2):
            simulator.AdvanceTo(0.1 * tick + 0.06)
            decisions.append(_eval(interval, "decision", simulator))
            images.append(_eval(attacker, "frame", simulator).image.clone())
        runs.append((decisions, images))
    assert runs[0][0] == runs[1][0]
    assert all(torch.equal(a, b) for a, b in zip(runs[0][1], runs[1][1], strict=True))
    assert all(math.isfinite(d.true_stiffness_n_per_rad) for d in runs[0][0])


def test_a_regression_interval_never_takes_a_design_with_more_friction_than_it_can_mean():
    """rtk-like: asphalt (mu 0.8) and cobblestone (mu 0.6) share 40-60 kN/rad, so a stiffness
    interval inside it may be cobblestone: the asphalt-only design is not sound for it."""
    table = load_conditions()
    rtk = []
    for rng in table.contiguous_ranges("rtk-like"):
        lo, hi = table.hull(rng)
        rtk.append(ControllerDesign(list(rng), lo, hi, 0.5 * (lo + hi),
                                    table.least_friction(rng), [0.0] * 4, 30.0, 100.0, 10.0))
    block = CertifiedInterval(rtk, table, PerceptionSettings(preset="rtk-like", eps=EPS,
                                                             task="regress"),
                              inputs=IntervalInputs(regression_beta=1000.0))
    result = PerceptionResult(time_s=0.025, tick=0, position_m=40.0, frame_ok=True, error="",
                              mode="certified", task="regress",
                              regression=(50_000.0, 48_000.0, 52_000.0))
    decision = block.request(result)
    assert decision.status == "certified"
    assert decision.interval == (47_000.0, 53_000.0)  # clear of sand's 30-45
    chosen = rtk[decision.design_index]
    assert chosen.friction_mu_lo <= 0.6 and chosen.labels != ["asphalt"]
    assert chosen.stiffness_lo_n_per_rad <= 47_000.0 and 53_000.0 <= chosen.stiffness_hi_n_per_rad


def test_certified_regression_at_a_clean_frame_runs_in_the_diagram(route, conditions, labels,
                                                                   designs):
    regressor = load_model(PRESET, "regress", SIGMA)
    regress = dataclasses.replace(CERTIFIED, task="regress", n=200, batch_size=200)
    block = PerceptionSmoothing(regressor, regress, seed=3)
    frame = CameraSource(route, conditions, PRESET, seed=3).capture(0.0, 0.0, 0)
    result = block.perceive(frame, 0.025)
    assert result.frame_ok and result.regression is not None
    median, lower, upper = result.regression
    assert lower <= median <= upper
    decision = CertifiedInterval(designs, conditions, regress,
                                 inputs=IntervalInputs(regression_beta=math.inf)).request(result)
    assert decision.status == "envelope"  # an infinite beta certifies nothing narrower
