"""The gradient adaptation law in the switching L1 controller (``SwitchingL1Controller(law=
"gradient")``): the single-design gradient controller when nothing switches, bumpless through
a design switch and a speed ramp, held steering when stopped, and an implicit integrator.

Designs are the shipped table's (``default_design_table``); the plant is the Fiala
``NonlinearLateralPlant``. Speed, curvature (and its road preview) and the design request are
time trajectories computed here from a road and a speed profile, as the route and the
longitudinal block would give them.
"""

import numpy as np
import pytest
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import (
    ConstantVectorSource,
    LogVectorOutput,
    Saturation,
    TrajectorySource,
)
from pydrake.trajectories import PiecewisePolynomial

from drake_cert.config import load_settings, load_vehicle
from drake_cert.errors import ConfigError
from drake_cert.systems import l1_law
from drake_cert.systems.closed_loop import EpisodeOptions, simulate, simulator_config
from drake_cert.systems.plants import NonlinearLateralPlant, body_state_from_error
from drake_cert.systems.road import Road
from drake_cert.systems.switching_controller import (
    GradientConstants,
    SwitchingGradientL1Law,
    SwitchingL1Controller,
    SwitchingL1Law,
    SwitchingOptions,
    gradient_derivatives_fast,
)

CAR = load_vehicle()
SETTINGS = load_settings()
CTL = SETTINGS.controller
PREVIEW = CTL.preview_window_s > 0  # the road preview, as the driving Diagram runs it
STIFFNESS = 45_000.0  # N/rad: inside both designs' intervals below
MU = 0.6


def implicit_config(step_s=CTL.sample_period_s):
    """What the gradient law needs: the implicit Radau3 (the law is stiff), steps <= T_s."""
    cfg = simulator_config(SETTINGS, "gradient")
    cfg.max_step_size = step_s
    return cfg


@pytest.fixture(scope="module")
def designs(default_design_table):
    """[rain (C in [40, 80] kN/rad), rain+snow ([20, 80] kN/rad)] of the robotcar-like preset."""
    table = default_design_table.designs
    pick = [next(d for d in table if d.labels == labels)
            for labels in (["rain"], ["rain", "snow"])]
    assert all(d.has_safe_speed for d in pick)
    return pick


def _profiles(road, speed, t_final, dt=0.002):
    """Speed, curvature and preview trajectories along ``road``; ``speed`` a number (m/s; the
    trajectories of drake_cert.systems.closed_loop) or a function of time (sampled every dt; at
    rest the preview is NaN, a mean over no distance, as the route source gives it)."""
    if not callable(speed):
        return [PiecewisePolynomial.ZeroOrderHold([0.0, 2 * t_final], [[speed, speed]]),
                road.curvature_trajectory(speed, t_final),
                road.preview_curvature_trajectory(speed, t_final, ahead_s=CTL.preview_ahead_s,
                                                  window_s=CTL.preview_window_s)]
    t = np.arange(0.0, t_final + dt / 2, dt)
    v = np.array([speed(ti) for ti in t])
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
    kappa = road.curvature_at(x)
    with np.errstate(invalid="ignore"):
        ahead = road.preview_curvature_at(x, v * CTL.preview_ahead_s, v * CTL.preview_window_s)
    return [PiecewisePolynomial.FirstOrderHold(t, y.reshape(1, -1)) for y in (v, kappa, ahead)]


def closed_loop(controller, road, speed, design_request, t_final, config, s0=None):
    """Fiala plant + controller + Saturation with speed(t), the design request (a
    ZeroOrderHold trajectory) and the road's curvature along the travelled arc length; the car
    starts at s0 with the predictor on it. Returns (simulator, logs of plant state, steering,
    active design, scheduled speed, every 1 ms)."""
    b = DiagramBuilder()
    ctrl = b.AddSystem(controller)
    plant = b.AddSystem(NonlinearLateralPlant(CAR))
    limit = CAR.steering_limit_rad
    sat = b.AddSystem(Saturation([-limit], [limit]))
    v, kappa, ahead = (b.AddSystem(TrajectorySource(tr))
                       for tr in _profiles(road, speed, t_final))
    for name, source in (("speed_mps", v), ("curvature_per_m", kappa)):
        b.Connect(source.get_output_port(), ctrl.GetInputPort(name))
        b.Connect(source.get_output_port(), plant.GetInputPort(name))
    if ctrl.HasInputPort("curvature_preview_per_m"):
        b.Connect(ahead.get_output_port(), ctrl.GetInputPort("curvature_preview_per_m"))
    request = b.AddSystem(TrajectorySource(design_request))
    b.Connect(request.get_output_port(), ctrl.GetInputPort("design_index"))
    for name, value in (("stiffness_n_per_rad", STIFFNESS), ("friction_mu", MU)):
        b.Connect(b.AddSystem(ConstantVectorSource([value])).get_output_port(),
                  plant.GetInputPort(name))
    b.Connect(plant.GetOutputPort("state"), ctrl.GetInputPort("state"))
    b.Connect(ctrl.GetOutputPort("steering_rad"), sat.get_input_port())
    b.Connect(sat.get_output_port(), plant.GetInputPort("steering_rad"))
    ports = {"state": plant.GetOutputPort("state"), "steering": sat.get_output_port(),
             "design": ctrl.GetOutputPort("active_design_index"),
             "speed": ctrl.GetOutputPort("scheduled_speed_mps")}
    logs = {k: LogVectorOutput(port, b, 0.001) for k, port in ports.items()}
    simulator = Simulator(b.Build())
    ApplySimulatorConfig(config, simulator)
    ctx = simulator.get_mutable_context()
    v0 = speed(0.0) if callable(speed) else speed
    kappa0 = float(road.curvature_at(0.0))
    s0 = np.zeros(4) if s0 is None else np.asarray(s0, float)
    plant.body_state_subsystem().GetMyMutableContextFromRoot(ctx).SetContinuousState(
        body_state_from_error(s0, v0, kappa0))
    ctrl.set_initial_state(ctx, s0, kappa0)
    return simulator, logs


def _read(simulator, logs):
    ctx = simulator.get_context()
    out = {k: log.FindLog(ctx).data() for k, log in logs.items()}
    out["t"] = logs["state"].FindLog(ctx).sample_times()
    return out


def _gradient_controller(designs, speed, **kw):
    return SwitchingL1Controller(vehicle=CAR, designs=designs, settings=SETTINGS,
                                 options=SwitchingOptions(law="gradient", initial_speed_mps=speed,
                                                          curvature_preview=PREVIEW, **kw))


def _constant(value):
    return PiecewisePolynomial.ZeroOrderHold([0.0, 1e3], [[value, value]])


# ------------------------------------------------------------------------------ the law


def test_it_has_the_ports_of_the_piecewise_constant_controller(designs):
    kw = dict(vehicle=CAR, designs=designs, settings=SETTINGS)

    def options(law=None):
        return SwitchingOptions(law=law, curvature_preview=True)

    pc = SwitchingL1Controller(options=options(), **kw)
    gradient = SwitchingL1Controller(options=options("gradient"), **kw)
    for kind in ("input", "output"):
        def names(system, kind=kind):
            count = getattr(system, f"num_{kind}_ports")()
            return [getattr(system, f"get_{kind}_port")(i).get_name() for i in range(count)]
        assert names(gradient) == names(pc)
    with pytest.raises(ConfigError, match="law 'bogus'"):
        SwitchingL1Controller(options=options("bogus"), **kw)
    with pytest.raises(ConfigError, match="SwitchingL1Controller"):
        SwitchingL1Law(options=options("gradient"), **kw)  # the gradient leaf: its own class


def test_the_fast_derivative_is_the_law_evaluated_directly(designs):
    rng = np.random.default_rng(7)
    for design in designs:
        p = l1_law.l1_parameters(CAR, design, SETTINGS, 12.0, curvature_preview=True)
        c = GradientConstants.of(p)
        for _ in range(300):  # estimates inside, near and on their sets' boundaries
            x = np.concatenate([rng.normal(0, 0.3, 4),
                                [p.w_centre + rng.uniform(-1, 1) * p.w_radius],
                                rng.normal(0, 1, 4) * p.theta_max * rng.uniform(0.3, 0.55),
                                [rng.uniform(-1, 1) * p.sigma_max], rng.normal(0, 0.05, 1)])
            s = rng.normal(0, 0.3, 4)
            kappa, ahead = rng.uniform(-0.02, 0.02, 2)
            np.testing.assert_allclose(
                gradient_derivatives_fast(c, x, s, kappa, ahead),
                l1_law.gradient_controller_derivatives(p, x, s, kappa, ahead).astype(float),
                rtol=1e-9, atol=1e-9)
    leaves = [SwitchingGradientL1Law(vehicle=CAR, designs=designs, settings=SETTINGS,
                                     options=SwitchingOptions(initial_speed_mps=12.0,
                                                              curvature_preview=True, fast=fast))
              for fast in (True, False)]
    contexts = [leaf.CreateDefaultContext() for leaf in leaves]
    for leaf, ctx in zip(leaves, contexts, strict=True):  # the leaf: derivative and steering
        for name, value in (("state", s), ("curvature_per_m", [kappa]), ("speed_mps", [12.0]),
                            ("curvature_preview_per_m", [ahead]), ("design_index", [1.0])):
            leaf.GetInputPort(name).FixValue(ctx, value)
        ctx.SetContinuousState(x)
    np.testing.assert_allclose(*(leaf.EvalTimeDerivatives(ctx).CopyToVector()
                                 for leaf, ctx in zip(leaves, contexts, strict=True)),
                               rtol=1e-9, atol=1e-9)
    fast_u, slow_u = (leaf.GetOutputPort("steering_rad").Eval(ctx)[0]
                      for leaf, ctx in zip(leaves, contexts, strict=True))
    assert fast_u == pytest.approx(slow_u, abs=1e-14)


def test_with_one_design_at_constant_speed_it_is_the_single_design_gradient_controller(
        designs):
    design, speed, t_final = designs[0], 14.0, 2.0  # 14.0 m/s: a point of the speed grid
    road = Road.curve(radius_m=50.0, straight_m=5.0, transition_m=10.0, curve_m=40.0)
    s0 = np.array([0.2, 0.0, 0.01, 0.0])
    fixed = simulate(vehicle=CAR, design=design, settings=SETTINGS, stiffness_n_per_rad=STIFFNESS,
                     friction_mu=MU, speed_mps=speed, road=road,
                     episode=EpisodeOptions(plant="nonlinear", law="gradient", t_final_s=t_final,
                                            initial_state=s0, tape_period_s=0.01,
                                            config=implicit_config()))
    simulator, logs = closed_loop(_gradient_controller([design], speed), road, speed,
                                  _constant(0.0), t_final, implicit_config(), s0=s0)
    simulator.AdvanceTo(t_final)
    out = _read(simulator, logs)
    states, steering = out["state"].T[::10], out["steering"][0][::10]  # the tape's 10 ms
    n = min(len(states), len(fixed.states))
    assert n >= 200
    assert np.max(np.abs(fixed.steering_rad)) > 0.02  # a real manoeuvre
    np.testing.assert_allclose(states[:n], fixed.states[:n], rtol=0, atol=1e-7)
    np.testing.assert_allclose(steering[:n], fixed.steering_rad[:n], rtol=0, atol=1e-7)


def test_a_design_switch_keeps_the_steering_and_restarts_the_predictor_at_the_plant(designs):
    leaf = SwitchingGradientL1Law(vehicle=CAR, designs=designs, settings=SETTINGS,
                                  options=SwitchingOptions(initial_speed_mps=12.0,
                                                           curvature_preview=True))
    grid = leaf.grid_index(0, 12.0)
    old, new = leaf.law_at(0, grid).parameters, leaf.law_at(1, grid).parameters
    s, curvatures = np.array([0.2, -0.1, 0.03, 0.05]), np.array([1 / 60, 1 / 55])
    x = np.concatenate([[0.25, -0.05, 0.02, 0.3], [old.w_centre + 0.9 * old.w_radius],
                        [0.9 * old.theta_max, 0, 0, 0], [0.95 * old.sigma_max], [0.012]])
    y = leaf.hand_over((0, grid), (1, grid), x, s, curvatures)

    def steering(p, state):
        return l1_law.steering_command(p, s, state[10], *curvatures)

    assert steering(new, y) == pytest.approx(steering(old, x), abs=1e-14)  # bumpless
    np.testing.assert_allclose(l1_law.predicted_measurement(new, y[0:4], curvatures[0]), s,
                               atol=1e-14)  # the new predictor starts at the plant
    c_hat = [d.nominal_stiffness_n_per_rad for d in designs]
    w = np.clip(x[4] * c_hat[0] / c_hat[1], new.w_centre - new.w_radius,
                new.w_centre + new.w_radius)
    assert y[4] == pytest.approx(w)  # the same stiffness estimate, in the new set
    assert np.linalg.norm(y[5:9]) <= new.theta_max * (1 + 1e-12)
    assert abs(y[9]) <= new.sigma_max
    # a grid change within a design (gain scheduling) keeps u_ad and the prediction s_hat
    z = leaf.hand_over((0, grid), (0, grid + 5), x, s, curvatures)
    faster = leaf.law_at(0, grid + 5).parameters
    assert z[10] == x[10]
    np.testing.assert_allclose(l1_law.predicted_measurement(faster, z[0:4], curvatures[0]),
                               l1_law.predicted_measurement(old, x[0:4], curvatures[0]),
                               atol=1e-14)


# ------------------------------------------------------------------------------ closed loops


def test_through_a_design_switch_and_a_4_mps2_speed_ramp_on_a_curve_the_car_stays_in_lane(
        designs):
    # 14 m/s under the rain design; at 1.5 s, in the 60 m arc, the rain+snow design is
    # requested and the car brakes at 4 m/s^2 to 9 m/s, in the curve.
    road = Road.curve(radius_m=60.0, straight_m=5.0, transition_m=10.0, curve_m=100.0)
    t_switch, t_final = 1.5, 3.0

    def speed(t):
        return float(np.clip(14.0 - 4.0 * (t - t_switch), 9.0, 14.0))

    request = PiecewisePolynomial.ZeroOrderHold([0.0, t_switch, 1e3], [[0.0, 1.0, 1.0]])
    runs = {}
    for law, config in (("piecewise_constant", simulator_config(SETTINGS, "piecewise_constant")),
                        ("gradient", implicit_config())):
        ctrl = SwitchingL1Controller(vehicle=CAR, designs=designs, settings=SETTINGS,
                                     options=SwitchingOptions(law=law, initial_speed_mps=14.0,
                                                              curvature_preview=PREVIEW))
        simulator, logs = closed_loop(ctrl, road, speed, request, t_final, config)
        simulator.AdvanceTo(t_final)
        runs[law] = _read(simulator, logs)
    out = runs["gradient"]
    e1, u, t = out["state"][0], out["steering"][0], out["t"]
    assert np.all(np.isfinite(out["state"]))
    assert np.max(np.abs(e1)) < CAR.lane_margin_m
    assert np.max(np.abs(e1)) < np.max(np.abs(runs["piecewise_constant"]["state"][0])) + 0.05
    assert out["design"][0][t < t_switch - 1e-9].max() == 0.0 and out["design"][0][-1] == 1.0
    assert out["speed"][0][0] == 14.0 and out["speed"][0][-1] == 9.0  # scheduled along
    # every 0.1 m/s grid point on the way inside the rain+snow design's gain box (the
    # controller clips the speed it schedules on to [speed_min, gain_speed_max])
    after = out["speed"][0][t > t_switch + 1e-3]
    assert after.max() <= designs[1].gain_speed_max_mps + 1e-9
    assert len(np.unique(after)) > 20
    around = (t > t_switch - 0.01) & (t < t_switch + 0.05)
    step = np.max(np.abs(np.diff(u[around])))  # the steering's largest change in 1 ms
    pc = runs["piecewise_constant"]["steering"][0]
    assert step < 0.005  # bumpless
    assert np.max(np.abs(np.diff(pc[around]))) < 0.005  # the pc law keeps the steering too


def test_braking_to_rest_on_a_curve_it_holds_its_steering_and_stops_adapting(designs):
    road = Road.curve(radius_m=60.0, straight_m=5.0, transition_m=10.0, curve_m=100.0)
    t_final = 3.8

    def speed(t):  # 9 m/s, braking at 4 m/s^2 from 1 s: below 5 m/s at 2 s, at rest at 3.25 s
        return float(np.clip(9.0 - 4.0 * (t - 1.0), 0.0, 9.0))

    # the rain+snow design, and at rest (3.5 s) a switch to the rain design
    request = PiecewisePolynomial.ZeroOrderHold([0.0, 3.5, 1e3], [[1.0, 0.0, 0.0]])
    ctrl = _gradient_controller(designs, 9.0, initial_design_index=1)
    simulator, logs = closed_loop(ctrl, road, speed, request, t_final, implicit_config())
    leaf = ctrl.law_system()
    leaf_ctx = leaf.GetMyContextFromRoot(simulator.get_context())
    x_at = {}
    for t_stop in (2.1, 3.4, t_final):
        simulator.AdvanceTo(t_stop)
        x_at[t_stop] = leaf_ctx.get_continuous_state_vector().CopyToVector()
    np.testing.assert_array_equal(x_at[2.1], x_at[3.4])  # nothing adapts while stopped
    out = _read(simulator, logs)
    t, u = out["t"], out["steering"][0]
    held = u[t > 2.01]  # from the first sample below the stop speed, a switch at rest included
    assert abs(held[0]) > 0.01  # held in the turn, not zero
    assert np.all(held == held[0])
    assert out["design"][0][-1] == 0.0  # the switch at rest took place
    x = x_at[t_final]  # after the switch at rest: u_ad kept, the predictor at the plant
    assert np.all(np.isfinite(x)) and x[10] == x_at[3.4][10]
    z = leaf_ctx.get_discrete_state_vector().CopyToVector()
    p = leaf.law_at(int(z[5]), int(z[6])).parameters  # the rain design's
    s = leaf.GetInputPort("state").Eval(leaf_ctx)
    kappa = leaf.GetInputPort("curvature_per_m").Eval(leaf_ctx)[0]
    np.testing.assert_allclose(l1_law.predicted_measurement(p, x[0:4], kappa), s, atol=1e-12)
    assert np.max(np.abs(out["state"][0])) < CAR.lane_margin_m


def test_the_gradient_law_needs_an_implicit_integrator_fixed_step_rk2_at_1ms_diverges(designs):
    # The adaptation loop has a lightly damped mode at about sqrt(Gamma b_m' P b_m) rad/s,
    # 1.5e4 here: far outside RK2's stability region at h = T_s = 1 ms (module docstring of
    # drake_cert.systems.switching_controller); Radau3 (the other closed loops here) is stable.
    p = l1_law.l1_parameters(CAR, designs[0], SETTINGS, 14.0)
    assert np.sqrt(p.adaptation_gain * p.b_m @ p.p_ad @ p.b_m) * CTL.sample_period_s > 2.0
    road = Road.curve(radius_m=60.0, straight_m=5.0, transition_m=10.0, curve_m=40.0)
    rk2 = simulator_config(SETTINGS, "piecewise_constant")  # the driving Diagram's RK2, 1 ms
    simulator, logs = closed_loop(_gradient_controller(designs, 14.0), road, 14.0,
                                  _constant(0.0), 1.0, rk2, s0=np.array([0.1, 0, 0, 0]))
    with np.errstate(all="ignore"):
        simulator.AdvanceTo(1.0)
    e1 = _read(simulator, logs)["state"][0]
    assert not np.all(np.abs(e1) < CAR.lane_margin_m)  # diverged (to inf or NaN)
