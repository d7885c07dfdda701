"""The switching, speed-scheduled L1 controller (DESIGN 5.6) and the speed-varying plants."""


import numpy as np
import pytest
from design_fixtures import FakeDecision, lqr_design
from pydrake.common.value import AbstractValue
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import (
    ConstantValueSource,
    ConstantVectorSource,
    LogVectorOutput,
    Saturation,
    TrajectorySource,
)

from drake_cert.config import load_settings, load_vehicle
from drake_cert.errors import ConfigError
from drake_cert.systems.closed_loop import EpisodeOptions, simulate
from drake_cert.systems.longitudinal import LongitudinalMotion
from drake_cert.systems.plants import (
    LinearLateralPlant,
    NonlinearLateralPlant,
    body_state_from_error,
)
from drake_cert.systems.road import Road
from drake_cert.systems.scenario import MotionSettings
from drake_cert.systems.switching_controller import (
    SwitchingL1Controller,
    SwitchingL1Law,
    SwitchingOptions,
)

CAR = load_vehicle()
SETTINGS = load_settings()
SPEED = 12.0
DESIGNS = [lqr_design(CAR, 40_000.0, 60_000.0, SPEED),
           lqr_design(CAR, 25_000.0, 45_000.0, 10.0, labels=("wet",))]


class CurvatureAlongRoad(LeafSystem):
    """kappa at the car's arc length (the role of the route source in the full diagram)."""

    def __init__(self, road: Road):
        super().__init__()
        self._road = road
        self._x = self.DeclareVectorInputPort("arc_length_m", 1)
        self.DeclareVectorOutputPort(
            "curvature_per_m", 1,
            lambda c, o: o.SetAtIndex(0, float(road.curvature_at(self._x.Eval(c)[0]))))


PREVIEW = SETTINGS.controller.preview_window_s > 0  # the road preview, as simulate runs it


def _fixed_speed_loop(controller, road, t_final, stiffness=42_000.0, mu=0.6):
    """Nonlinear plant + switching controller at constant speed (as drake_cert.systems.closed_loop,
    with its road preview when the controller has the port)."""
    builder = DiagramBuilder()
    ctrl = builder.AddSystem(controller)
    if ctrl.HasInputPort("curvature_preview_per_m"):
        ctl = SETTINGS.controller
        ahead = builder.AddSystem(TrajectorySource(road.preview_curvature_trajectory(
            SPEED, t_final, ahead_s=ctl.preview_ahead_s, window_s=ctl.preview_window_s)))
        builder.Connect(ahead.get_output_port(), ctrl.GetInputPort("curvature_preview_per_m"))
    plant = builder.AddSystem(NonlinearLateralPlant(CAR))
    limit = CAR.steering_limit_rad
    sat = builder.AddSystem(Saturation([-limit], [limit]))
    kappa = builder.AddSystem(TrajectorySource(road.curvature_trajectory(SPEED, t_final)))
    for port in ("curvature_per_m",):
        builder.Connect(kappa.get_output_port(), ctrl.GetInputPort(port))
        builder.Connect(kappa.get_output_port(), plant.GetInputPort(port))
    for name, value in (("stiffness_n_per_rad", stiffness), ("friction_mu", mu),
                        ("speed_mps", SPEED)):
        src = builder.AddSystem(ConstantVectorSource([value]))
        builder.Connect(src.get_output_port(), plant.GetInputPort(name))
        if name == "speed_mps":
            builder.Connect(src.get_output_port(), ctrl.GetInputPort("speed_mps"))
    design = builder.AddSystem(ConstantVectorSource([0.0]))
    builder.Connect(design.get_output_port(), ctrl.GetInputPort("design_index"))
    builder.Connect(plant.GetOutputPort("state"), ctrl.GetInputPort("state"))
    builder.Connect(ctrl.GetOutputPort("steering_rad"), sat.get_input_port())
    builder.Connect(sat.get_output_port(), plant.GetInputPort("steering_rad"))
    state_log = LogVectorOutput(plant.GetOutputPort("state"), builder, 0.01)
    steer_log = LogVectorOutput(sat.get_output_port(), builder, 0.01)
    return builder.Build(), plant, ctrl, state_log, steer_log


def _rk2(simulator):
    integrator = simulator.get_mutable_integrator()
    integrator.set_fixed_step_mode(True)
    integrator.set_maximum_step_size(SETTINGS.controller.sample_period_s)


def _run_reference_comparison(fast):
    road = Road.curve(radius_m=50.0, straight_m=5.0, transition_m=10.0, curve_m=30.0)
    s0 = np.array([0.2, 0.0, 0.01, 0.0])
    t_final = 3.0
    fixed = simulate(vehicle=CAR, design=DESIGNS[0], settings=SETTINGS,
                     stiffness_n_per_rad=42_000.0, friction_mu=0.6, speed_mps=SPEED, road=road,
                     episode=EpisodeOptions(plant="nonlinear", law="piecewise_constant",
                                            t_final_s=t_final, initial_state=s0))
    ctrl = SwitchingL1Controller(vehicle=CAR, designs=DESIGNS, settings=SETTINGS,
                                 options=SwitchingOptions(initial_speed_mps=SPEED, fast=fast,
                                                          curvature_preview=PREVIEW))
    diagram, plant, ctrl, state_log, steer_log = _fixed_speed_loop(ctrl, road, t_final)
    simulator = Simulator(diagram)
    from pydrake.systems.analysis import ApplySimulatorConfig

    from drake_cert.systems.closed_loop import simulator_config
    ApplySimulatorConfig(simulator_config(SETTINGS, "piecewise_constant"), simulator)
    ctx = simulator.get_mutable_context()
    plant.body_state_subsystem().GetMyMutableContextFromRoot(ctx).SetContinuousState(
        body_state_from_error(s0, SPEED, 0.0))
    ctrl.set_initial_state(ctx, s0)
    simulator.AdvanceTo(t_final)
    states = state_log.FindLog(ctx).data().T
    steering = steer_log.FindLog(ctx).data()[0]
    n = min(len(states), len(fixed.states))
    assert n >= 300
    assert np.max(np.abs(fixed.steering_rad)) > 0.01  # a real manoeuvre, not all zeros
    np.testing.assert_allclose(states[:n], fixed.states[:n], rtol=0, atol=1e-8)
    np.testing.assert_allclose(steering[:n], fixed.steering_rad[:n], rtol=0, atol=1e-8)


@pytest.mark.parametrize("fast", [True, False])
def test_constant_design_and_speed_reproduce_the_fixed_parameter_controller(fast):
    _run_reference_comparison(fast)


def _controller_context(**kw):
    ctrl = SwitchingL1Law(vehicle=CAR, designs=DESIGNS, settings=SETTINGS,
                          options=SwitchingOptions(initial_speed_mps=SPEED, **kw))
    ctx = ctrl.CreateDefaultContext()
    s = np.array([0.2, -0.3, 0.05, 0.1])
    ctrl.GetInputPort("state").FixValue(ctx, s)
    ctrl.GetInputPort("curvature_per_m").FixValue(ctx, [1 / 60])
    if ctrl.curvature_preview:  # the road ahead bends more than the road under the car
        ctrl.GetInputPort("curvature_preview_per_m").FixValue(ctx, [1 / 52])
    ctrl.GetInputPort("speed_mps").FixValue(ctx, [SPEED])
    ctrl.GetInputPort("design_index").FixValue(ctx, [0.0])
    return ctrl, ctx, s


def test_a_design_switch_acts_at_the_sample_after_the_request():
    ctrl = SwitchingL1Controller(vehicle=CAR, designs=DESIGNS, settings=SETTINGS,
                                 options=SwitchingOptions(initial_speed_mps=SPEED))
    builder = DiagramBuilder()
    builder.AddSystem(ctrl)
    for name in ("state", "curvature_per_m", "speed_mps"):
        builder.ExportInput(ctrl.GetInputPort(name), name)
    # request design 1 at t = 10.5 ms, between the samples at 10 and 11 ms
    from pydrake.trajectories import PiecewisePolynomial
    step = PiecewisePolynomial.ZeroOrderHold([0.0, 0.0105, 1.0], [[0.0, 1.0, 1.0]])
    request = builder.AddSystem(TrajectorySource(step))
    builder.Connect(request.get_output_port(), ctrl.GetInputPort("design_index"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    ctx = simulator.get_mutable_context()
    for name, value in (("state", [0.1, 0.0, 0.0, 0.0]), ("curvature_per_m", [0.0]),
                        ("speed_mps", [SPEED])):
        diagram.GetInputPort(name).FixValue(ctx, value)
    active = ctrl.GetOutputPort("active_design_index")
    mine = ctrl.GetMyContextFromRoot(ctx)
    leaf = ctrl.law_system()
    simulator.AdvanceTo(0.0109)
    assert active.Eval(mine)[0] == 0.0  # requested at 10.5 ms, still the old design
    simulator.AdvanceTo(0.0111)
    assert active.Eval(mine)[0] == 1.0  # switched by the sample at 11 ms
    law = leaf.law_at(1, leaf.grid_index(1, SPEED))
    assert law.parameters.k_m.tolist() == DESIGNS[1].k_m
    z = mine.get_discrete_state_vector().CopyToVector()  # the C++ output: the new k_m
    u = ctrl.GetOutputPort("steering_rad").Eval(mine)[0]
    assert u == pytest.approx(-(DESIGNS[1].k_m_array @ [0.1, 0, 0, 0]) + z[4], abs=1e-12)


@pytest.mark.parametrize("preview", [False, True])
def test_a_switch_keeps_the_steering_and_carries_the_estimate_exactly(preview):
    """docs/design.md 5.6 (b): at a switch the steering is the same under both designs and the
    new design reads, from its placed predictor, exactly the uncertainty it has on the plant
    (here eq. 2.45 at a stiffness both intervals hold, on a curve, the preview bending more),
    given that the old design read its own exactly. The controller's update at the switch is
    the hand-over followed by the new design's sample."""
    from drake_cert.dynamics import lateral_error_dynamics
    from drake_cert.systems import l1_law

    ctrl, ctx, s = _controller_context(curvature_preview=preview)
    kappa, kappa_ff = 1 / 60, (1 / 52 if preview else 1 / 60)
    old, new = (ctrl.law_at(i, ctrl.grid_index(i, SPEED)).parameters for i in (0, 1))
    a, b, g = lateral_error_dynamics(CAR, 42_000.0, SPEED)

    def truth(p, u_ad):
        u = l1_law.steering_command(p, s, u_ad, kappa, kappa_ff)
        s_dot = a @ s + b * u + g * SPEED * kappa
        return u, (s_dot - p.a_m @ s - p.b_m * (u_ad + l1_law.curvature_feedforward(p, kappa_ff))
                   - p.g_hat * p.speed_mps * kappa)

    u_ad = 0.004
    u_old, sigma_old = truth(old, u_ad)
    q = l1_law.predictor_memory(old, s + l1_law.piecewise_constant_inverse_estimate(old,
                                                                                 sigma_old),
                                kappa)
    q_new, u_ad_new = l1_law.piecewise_constant_hand_over(
        old, new, q, u_ad, l1_law.SwitchSample(s, kappa, kappa_ff if preview else None))
    u_new, sigma_new = truth(new, u_ad_new)
    assert u_new == pytest.approx(u_old, abs=1e-15)  # bumpless
    read = l1_law.piecewise_constant_estimate(
        new, l1_law.predicted_measurement(new, q_new, kappa) - s)
    np.testing.assert_allclose(read, sigma_new, rtol=1e-9, atol=1e-12)
    assert not np.allclose(sigma_new, sigma_old)  # the designs' uncertainties differ
    ctx.SetDiscreteState(np.concatenate([q, [u_ad, 0, ctrl.grid_index(0, SPEED), 0, 0]]))
    ctrl.GetInputPort("design_index").FixValue(ctx, [1.0])
    after = ctrl.EvalUniquePeriodicDiscreteUpdate(ctx).get_vector().CopyToVector()
    expected = l1_law.piecewise_constant_update(new, q_new, u_ad_new, s, kappa,
                                                kappa_ff if preview else None)
    np.testing.assert_allclose(after[:4], expected[0], rtol=1e-9, atol=1e-12)
    assert after[4] == pytest.approx(expected[1], rel=1e-9, abs=1e-12)
    assert after[5] == 1.0


@pytest.mark.parametrize("preview", [False, True])
def test_the_fast_update_is_the_law_evaluated_directly(preview):
    fast, ctx_f, s = _controller_context(fast=True, curvature_preview=preview)
    slow, ctx_s, _ = _controller_context(fast=False, curvature_preview=preview)
    z = np.array([0.25, -0.2, 0.04, 0.12, 0.003, 0, 70, 0, 0])
    for ctx in (ctx_f, ctx_s):
        ctx.SetDiscreteState(z)
    np.testing.assert_allclose(
        fast.EvalUniquePeriodicDiscreteUpdate(ctx_f).get_vector().CopyToVector(),
        slow.EvalUniquePeriodicDiscreteUpdate(ctx_s).get_vector().CopyToVector(),
        rtol=1e-12, atol=1e-14)
    assert fast.GetOutputPort("steering_rad").Eval(ctx_f)[0] == pytest.approx(
        slow.GetOutputPort("steering_rad").Eval(ctx_s)[0], rel=1e-12)


@pytest.mark.parametrize("preview", [False, True])
def test_the_cpp_steering_output_equals_the_law_output(preview):
    options = SwitchingOptions(initial_speed_mps=SPEED, curvature_preview=preview)
    leaf = SwitchingL1Law(vehicle=CAR, designs=DESIGNS, settings=SETTINGS, options=options)
    ctrl = SwitchingL1Controller(vehicle=CAR, designs=DESIGNS, settings=SETTINGS,
                                 options=options)
    ctx_l, ctx_c = leaf.CreateDefaultContext(), ctrl.CreateDefaultContext()
    z = np.array([0.25, -0.2, 0.04, 0.12, 0.003, 1, 70, 0, 0])
    inputs = [("state", [0.2, -0.3, 0.05, 0.1]), ("curvature_per_m", [0.02]),
              ("speed_mps", [SPEED]), ("design_index", [1.0])]
    if preview:
        inputs.append(("curvature_preview_per_m", [0.007]))
    for system, ctx in ((leaf, ctx_l), (ctrl, ctx_c)):
        for name, value in inputs:
            system.GetInputPort(name).FixValue(ctx, value)
    ctx_l.SetDiscreteState(z)
    ctrl.law_system().GetMyMutableContextFromRoot(ctx_c).SetDiscreteState(z)
    assert ctrl.GetOutputPort("steering_rad").Eval(ctx_c)[0] == pytest.approx(
        leaf.GetOutputPort("steering_rad").Eval(ctx_l)[0], rel=1e-12)
    z[7], z[8] = 1.0, 0.123  # stopped: both hold the held steering
    ctx_l.SetDiscreteState(z)
    ctrl.law_system().GetMyMutableContextFromRoot(ctx_c).SetDiscreteState(z)
    assert ctrl.GetOutputPort("steering_rad").Eval(ctx_c)[0] == 0.123
    assert leaf.GetOutputPort("steering_rad").Eval(ctx_l)[0] == 0.123


def test_with_the_preview_the_feedforward_follows_the_road_ahead_not_the_road_under_the_car():
    ctrl, ctx, _ = _controller_context(curvature_preview=True)
    law = ctrl.law_at(0, ctrl.grid_index(0, SPEED)).parameters
    steering = ctrl.GetOutputPort("steering_rad")
    u_ahead = steering.Eval(ctx)[0]  # kappa = 1/60 under the car, 1/52 ahead
    ctrl.GetInputPort("curvature_per_m").FixValue(ctx, [0.0])  # straight under the car
    assert steering.Eval(ctx)[0] == pytest.approx(u_ahead, abs=1e-15)
    ctrl.GetInputPort("curvature_preview_per_m").FixValue(ctx, [0.0])
    assert u_ahead - steering.Eval(ctx)[0] == pytest.approx(law.k_ff * SPEED / 52, rel=1e-12)
    assert law.k_ff != 0.0


def test_speed_is_scheduled_on_the_grid_and_clipped_to_the_design_range():
    ctrl, ctx, _ = _controller_context()
    assert ctrl.grid_speed(ctrl.grid_index(0, 12.04)) == 12.0
    assert ctrl.grid_speed(ctrl.grid_index(0, 2.0)) == SETTINGS.synthesis.speed_min_mps
    assert ctrl.grid_speed(ctrl.grid_index(0, 99.0)) == DESIGNS[0].gain_speed_max_mps
    ctrl.GetInputPort("speed_mps").FixValue(ctx, [8.73])
    ctx.SetDiscreteState(ctrl.EvalUniquePeriodicDiscreteUpdate(ctx).get_vector().CopyToVector())
    assert ctrl.GetOutputPort("scheduled_speed_mps").Eval(ctx)[0] == pytest.approx(8.7)


def test_below_the_stop_speed_the_steering_is_held_and_nothing_adapts():
    ctrl, ctx, _ = _controller_context()
    ctrl.GetInputPort("speed_mps").FixValue(ctx, [3.0])
    z0 = ctx.get_discrete_state_vector().CopyToVector()
    u_before = ctrl.GetOutputPort("steering_rad").Eval(ctx)[0]
    ctx.SetDiscreteState(ctrl.EvalUniquePeriodicDiscreteUpdate(ctx).get_vector().CopyToVector())
    z1 = ctx.get_discrete_state_vector().CopyToVector()
    np.testing.assert_array_equal(z1[:5], z0[:5])  # no adaptation
    ctrl.GetInputPort("state").FixValue(ctx, [1.0, 1.0, 0.3, 0.2])  # s changes: u does not
    assert ctrl.GetOutputPort("steering_rad").Eval(ctx)[0] == u_before
    ctx.SetDiscreteState(ctrl.EvalUniquePeriodicDiscreteUpdate(ctx).get_vector().CopyToVector())
    assert ctrl.GetOutputPort("steering_rad").Eval(ctx)[0] == u_before


def test_a_bad_design_index_is_a_config_error():
    ctrl, ctx, _ = _controller_context()
    ctrl.GetInputPort("design_index").FixValue(ctx, [2.0])
    with pytest.raises(ConfigError, match="design_index"):
        ctrl.EvalUniquePeriodicDiscreteUpdate(ctx)


@pytest.mark.parametrize("plant_class", [LinearLateralPlant, NonlinearLateralPlant])
def test_plants_freeze_below_the_stop_speed_without_dividing_by_zero(plant_class):
    plant = plant_class(CAR)
    ctx = plant.CreateDefaultContext()
    for name, value in (("steering_rad", 0.05), ("stiffness_n_per_rad", 50_000.0),
                        ("friction_mu", 0.8), ("curvature_per_m", 0.02)):
        plant.GetInputPort(name).FixValue(ctx, [value])
    x = [0.3, 0.1, 0.05, 0.02]
    if plant_class is NonlinearLateralPlant:  # body state [e1, vy, e2, r] + a dummy state
        plant.body_state_subsystem().GetMyMutableContextFromRoot(ctx).SetContinuousState(x)
    else:
        ctx.SetContinuousState(x)
    for v in (0.0, 1e-9, 4.99):
        plant.GetInputPort("speed_mps").FixValue(ctx, [v])
        d = plant.EvalTimeDerivatives(ctx).CopyToVector()
        np.testing.assert_array_equal(d, np.zeros_like(d))
        assert np.all(np.isfinite(plant.GetOutputPort("state").Eval(ctx)))
    plant.GetInputPort("speed_mps").FixValue(ctx, [5.0])
    assert np.linalg.norm(plant.EvalTimeDerivatives(ctx).CopyToVector()) > 0


def build_motion_loop(road, decisions, *, initial_speed, stiffness, mu, fast=True):
    """Fiala plant + SwitchingL1Controller + LongitudinalMotion, curvature by arc length."""
    builder = DiagramBuilder()
    motion = builder.AddSystem(LongitudinalMotion(MotionSettings(initial_speed_mps=initial_speed)))
    if isinstance(decisions, FakeDecision):
        source = builder.AddSystem(ConstantValueSource(AbstractValue.Make(decisions)))
    else:
        source = builder.AddSystem(decisions)
    builder.Connect(source.get_output_port(), motion.GetInputPort("decision"))
    ctrl = builder.AddSystem(SwitchingL1Controller(
        vehicle=CAR, designs=DESIGNS, settings=SETTINGS,
        options=SwitchingOptions(initial_speed_mps=initial_speed, fast=fast)))
    plant = builder.AddSystem(NonlinearLateralPlant(CAR))
    limit = CAR.steering_limit_rad
    sat = builder.AddSystem(Saturation([-limit], [limit]))
    kappa = builder.AddSystem(CurvatureAlongRoad(road))
    builder.Connect(motion.GetOutputPort("arc_length_m"), kappa.get_input_port())
    builder.Connect(kappa.get_output_port(), ctrl.GetInputPort("curvature_per_m"))
    builder.Connect(kappa.get_output_port(), plant.GetInputPort("curvature_per_m"))
    builder.Connect(motion.GetOutputPort("speed_mps"), ctrl.GetInputPort("speed_mps"))
    builder.Connect(motion.GetOutputPort("speed_mps"), plant.GetInputPort("speed_mps"))
    builder.Connect(motion.GetOutputPort("design_index"), ctrl.GetInputPort("design_index"))
    for name, value in (("stiffness_n_per_rad", stiffness), ("friction_mu", mu)):
        src = builder.AddSystem(ConstantVectorSource([value]))
        builder.Connect(src.get_output_port(), plant.GetInputPort(name))
    builder.Connect(plant.GetOutputPort("state"), ctrl.GetInputPort("state"))
    builder.Connect(ctrl.GetOutputPort("steering_rad"), sat.get_input_port())
    builder.Connect(sat.get_output_port(), plant.GetInputPort("steering_rad"))
    logs = {"state": LogVectorOutput(plant.GetOutputPort("state"), builder, 0.01),
            "speed": LogVectorOutput(motion.GetOutputPort("speed_mps"), builder, 0.01),
            "design": LogVectorOutput(ctrl.GetOutputPort("active_design_index"), builder,
                                      0.01)}
    return builder.Build(), logs


def test_a_speed_ramp_14_to_8_with_a_design_switch_on_a_50m_curve_stays_in_lane():
    road = Road.curve(radius_m=50.0, straight_m=10.0, transition_m=10.0, curve_m=120.0)
    # at 60 m (in the curve) slow to 8 m/s with the wet design: the car brakes in the curve
    diagram, logs = build_motion_loop(road, FakeDecision(0.0, 60.0, 8.0, 1),
                                      initial_speed=14.0, stiffness=42_000.0, mu=0.6)
    simulator = Simulator(diagram)
    _rk2(simulator)
    simulator.AdvanceTo(10.0)
    ctx = simulator.get_context()
    e1 = logs["state"].FindLog(ctx).data()[0]
    speed = logs["speed"].FindLog(ctx).data()[0]
    design = logs["design"].FindLog(ctx).data()[0]
    assert speed[0] == pytest.approx(14.0) and speed[-1] == pytest.approx(8.0, abs=0.01)
    assert design[0] == 0 and design[-1] == 1
    assert np.max(np.abs(e1)) < CAR.lane_margin_m
