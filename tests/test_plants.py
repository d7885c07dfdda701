"""The plants: eq. 2.45 in Drake, the Fiala single track reduces to it, exact simulation."""

import numpy as np
import pytest
import scipy.linalg
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator, SimulatorConfig
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, LogVectorOutput, MatrixGain

from drake_cert.config import VehicleParams
from drake_cert.dynamics import lateral_error_dynamics
from drake_cert.systems.plants import (
    PLANT_INPUTS,
    ExactDiscreteLinearPlant,
    LinearLateralPlant,
    NonlinearLateralPlant,
    PlantInputs,
    body_state_from_error,
    error_state_from_body,
    exact_discretisation,
    fiala_lateral_force,
    nonlinear_error_derivatives,
    static_tire_loads,
)

CAR = VehicleParams()
K = np.array([0.3, 0.05, 1.2, 0.1])  # a stabilising state feedback at C = 50k, V = 20


def _fix_inputs(system, context, values):
    for name, value in zip(PLANT_INPUTS, values, strict=True):
        system.GetInputPort(name).FixValue(context, [value])


@pytest.mark.parametrize("c, v", [(50_000.0, 20.0), (25_000.0, 8.0), (110_000.0, 28.0)])
def test_nonlinear_plant_linearises_to_eq_2_45_on_a_straight_road(c, v):
    def f(z):  # z = [s, u, kappa] -> sdot
        return nonlinear_error_derivatives(CAR, z[:4],
                                           PlantInputs(z[4], c, 0.9, v, z[5])).astype(float)

    # Small h: the Fiala |tan a| tan a term makes central differences O(h C / (mu Fz)).
    h = 1e-8
    jac = np.column_stack([(f(h * e) - f(-h * e)) / (2 * h) for e in np.eye(6)])
    a, b, g = lateral_error_dynamics(CAR, c, v)
    scale = np.abs(np.column_stack([a, b, g * v])).max()
    np.testing.assert_allclose(jac[:, :4] / scale, a / scale, atol=1e-6)
    np.testing.assert_allclose(jac[:, 4] / scale, b / scale, atol=1e-6)
    np.testing.assert_allclose(jac[:, 5] / scale, g * v / scale, atol=1e-6)  # psidot = V kappa
    np.testing.assert_allclose(f(np.zeros(6)), 0.0, atol=1e-12)


def test_nonlinear_plant_differs_from_eq_2_45_at_large_slip():
    s = np.array([0.0, 0.0, 0.0, 0.0])
    a, b, _ = lateral_error_dynamics(CAR, 50_000.0, 20.0)
    linear = b * 0.2
    nonlinear = nonlinear_error_derivatives(CAR, s, PlantInputs(0.2, 50_000.0, 0.3, 20.0,
                                                                0.0)).astype(float)
    fz_f = static_tire_loads(CAR)[0]
    # Saturated front axle: lateral acceleration bounded by 2 mu Fz_f cos(u) / m.
    assert abs(nonlinear[1]) <= 2 * 0.3 * fz_f / CAR.mass_kg + 1e-9
    assert abs(linear[1]) > 3 * abs(nonlinear[1])


def test_fiala_tire_is_linear_for_small_slip_and_saturates_at_mu_fz():
    c, mu, fz = 50_000.0, 0.6, static_tire_loads(CAR)[0]
    h = 1e-7
    slope = (fiala_lateral_force(h, c, mu, fz) - fiala_lateral_force(-h, c, mu, fz)) / (2 * h)
    assert slope == pytest.approx(-c, rel=1e-6)
    slide = np.arctan(3 * mu * fz / c)
    for a in (slide * 1.0001, 0.3, 1.0):
        assert fiala_lateral_force(a, c, mu, fz) == pytest.approx(-mu * fz)
        assert fiala_lateral_force(-a, c, mu, fz) == pytest.approx(mu * fz)
    # Continuous at the sliding limit, monotone and bounded by mu Fz below it.
    assert fiala_lateral_force(slide * 0.9999, c, mu, fz) == pytest.approx(-mu * fz, rel=1e-6)
    grid = np.linspace(-slide, slide, 401)
    forces = np.array([fiala_lateral_force(a, c, mu, fz) for a in grid])
    assert np.all(np.diff(forces) <= 1e-9)
    assert np.abs(forces).max() <= mu * fz * (1 + 1e-12)


@pytest.mark.parametrize("slip", [-0.075, -0.02, 0.004, 0.03, 0.07])
def test_fiala_tire_follows_the_brush_formula_below_sliding(slip):
    c, mu, fz = 60_000.0, 0.5, static_tire_loads(CAR)[1]
    t = np.tan(slip)
    assert abs(t) < 3 * mu * fz / c  # still adhering
    brush = (-c * t + c**2 / (3 * mu * fz) * abs(t) * t - c**3 / (27 * mu**2 * fz**2) * t**3)
    assert fiala_lateral_force(slip, c, mu, fz) == pytest.approx(brush, rel=1e-12)


def test_static_loads_add_up_to_the_weight():
    f, r = static_tire_loads(CAR)
    assert 2 * (f + r) == pytest.approx(CAR.mass_kg * 9.81)
    assert f * CAR.lf_m == pytest.approx(r * CAR.lr_m)  # moment balance about the CG


def test_drake_linear_plant_evaluates_eq_2_45():
    plant = LinearLateralPlant(CAR)
    ctx = plant.CreateDefaultContext()
    _fix_inputs(plant, ctx, [0.02, 42_000.0, 0.5, 17.0, 0.01])
    s = np.array([0.3, -0.1, 0.02, 0.05])
    ctx.SetContinuousState(s)
    a, b, g = lateral_error_dynamics(CAR, 42_000.0, 17.0)
    np.testing.assert_allclose(plant.EvalTimeDerivatives(ctx).CopyToVector(),
                               a @ s + b * 0.02 + g * 17.0 * 0.01, rtol=1e-13)
    np.testing.assert_array_equal(plant.GetOutputPort("state").Eval(ctx), s)


def test_drake_nonlinear_plant_outputs_the_error_state_of_its_body_state():
    plant = NonlinearLateralPlant(CAR)
    ctx = plant.CreateDefaultContext()
    _fix_inputs(plant, ctx, [0.02, 42_000.0, 0.5, 17.0, 0.01])
    s = np.array([0.3, -0.1, 0.02, 0.05])
    x = body_state_from_error(s, 17.0, 0.01)
    plant.body_state_subsystem().GetMyMutableContextFromRoot(ctx).SetContinuousState(x)
    np.testing.assert_allclose(plant.GetOutputPort("state").Eval(ctx), s, rtol=1e-12)
    np.testing.assert_allclose(error_state_from_body(x, 17.0, 0.01), s, rtol=1e-12)


def _closed_loop_with_state_feedback(plant, c, v, kappa):
    builder = DiagramBuilder()
    plant = builder.AddSystem(plant)
    gain = builder.AddSystem(MatrixGain(-K.reshape(1, 4)))
    builder.Connect(plant.GetOutputPort("state"), gain.get_input_port())
    builder.Connect(gain.get_output_port(), plant.GetInputPort("steering_rad"))
    for name, value in (("stiffness_n_per_rad", c), ("friction_mu", 0.8), ("speed_mps", v),
                        ("curvature_per_m", kappa)):
        if plant.HasInputPort(name):
            src = builder.AddSystem(ConstantVectorSource([value]))
            builder.Connect(src.get_output_port(), plant.GetInputPort(name))
    logger = LogVectorOutput(plant.GetOutputPort("state"), builder, 0.25)
    return builder.Build(), plant, logger


def _exact_solution(s0, c, v, kappa, times):
    a, b, g = lateral_error_dynamics(CAR, c, v)
    m = np.zeros((5, 5))
    m[:4, :4] = a - np.outer(b, K)
    m[:4, 4] = g * v * kappa  # constant forcing as an augmented state equal to 1
    z0 = np.append(s0, 1.0)
    return np.array([(scipy.linalg.expm(m * t) @ z0)[:4] for t in times])


def test_drake_linear_closed_loop_matches_the_matrix_exponential():
    c, v, kappa = 50_000.0, 20.0, 1 / 80
    s0 = np.array([0.4, 0.0, -0.05, 0.0])
    diagram, plant, logger = _closed_loop_with_state_feedback(LinearLateralPlant(CAR), c, v,
                                                              kappa)
    sim = Simulator(diagram)
    cfg = SimulatorConfig(integration_scheme="runge_kutta3", accuracy=1e-10,
                          use_error_control=True, publish_every_time_step=False)
    ApplySimulatorConfig(cfg, sim)
    plant.GetMyMutableContextFromRoot(sim.get_mutable_context()).SetContinuousState(s0)
    sim.AdvanceTo(5.0)
    log = logger.FindLog(sim.get_context())
    exact = _exact_solution(s0, c, v, kappa, log.sample_times())
    scale = np.abs(exact).max(axis=0)
    np.testing.assert_allclose(log.data().T / scale, exact / scale, atol=1e-7)
    assert np.abs(exact[-1, 0]) > 1e-3  # the curvature leaves a visible offset to compare


def test_exact_discrete_plant_matches_the_matrix_exponential_at_samples():
    c, v, kappa, period = 50_000.0, 20.0, 1 / 80, 0.01
    ad, bd = exact_discretisation(CAR, c, v, period)
    a, b, g = lateral_error_dynamics(CAR, c, v)
    m = np.zeros((6, 6))
    m[:4, :4], m[:4, 4], m[:4, 5] = a, b, g * v
    e = scipy.linalg.expm(m * period)
    np.testing.assert_allclose(ad, e[:4, :4], rtol=1e-12)
    np.testing.assert_allclose(bd, e[:4, 4:], rtol=1e-12)
    # Drake's discrete system steps s[k+1] = Ad s[k] + Bd [u, kappa] with a held input.
    plant = ExactDiscreteLinearPlant(CAR, c, v, period)
    ctx = plant.CreateDefaultContext()
    plant.GetInputPort("steering_rad").FixValue(ctx, [0.01])
    plant.GetInputPort("curvature_per_m").FixValue(ctx, [kappa])
    s0 = np.array([0.1, 0.2, 0.0, -0.1])
    ctx.SetDiscreteState(s0)
    sim = Simulator(plant, ctx)
    sim.AdvanceTo(10 * period + period / 2)
    expected = s0
    for _ in range(11):  # updates at t = 0, T, ..., 10 T
        expected = ad @ expected + bd @ np.array([0.01, kappa])
    np.testing.assert_allclose(ctx.get_discrete_state_vector().CopyToVector(), expected,
                               rtol=1e-10)
