"""The L1 adaptive controller (DESIGN 4) as Drake systems, and the closed loop it makes."""

import dataclasses

import numpy as np
import pytest
from design_fixtures import lqr_design
from pydrake.systems.analysis import SimulatorConfig

from drake_cert import metrics
from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.systems import l1_law
from drake_cert.systems.closed_loop import EpisodeOptions, simulate
from drake_cert.systems.l1_controller import L1AdaptiveController
from drake_cert.systems.road import Road

CAR = load_vehicle()
SETTINGS = load_settings()
SPEED = 12.0
DESIGN = lqr_design(CAR, 40_000.0, 60_000.0, SPEED)


@pytest.fixture(scope="module")
def heavy_rain_design(default_design_table):
    """The synthesized design (corner-LMI gain, filter gain, safe speed) for heavy rain."""
    (design,) = [d for d in default_design_table.designs if d.labels == ["heavy_rain"]]
    assert design.has_safe_speed
    assert design.friction_mu_lo == load_conditions().condition("heavy_rain").friction_mu
    return design


def _controller_context(law):
    ctrl = L1AdaptiveController(vehicle=CAR, design=DESIGN, settings=SETTINGS,
                                speed_mps=SPEED, options=l1_law.L1Options(law=law))
    ctx = ctrl.CreateDefaultContext()
    s = np.array([0.2, -0.3, 0.05, 0.1])
    kappa = 1 / 60
    ctrl.GetInputPort("state").FixValue(ctx, s)
    ctrl.GetInputPort("curvature_per_m").FixValue(ctx, [kappa])
    return ctrl, ctx, s, kappa


def test_gradient_law_system_evaluates_the_reference_equations():
    ctrl, ctx, s, kappa = _controller_context("gradient")
    p = ctrl.parameters
    rng = np.random.default_rng(1)
    # An estimate near the projection boundary, so the projection branch is exercised.
    z = np.concatenate([s + rng.normal(0, 0.05, 4), [p.w_centre + 0.99 * p.w_radius],
                        0.99 * p.theta_max * np.array([0.6, 0.0, 0.8, 0.0]),
                        [-0.5 * p.sigma_max], [0.01]])
    ctrl.core().GetMyMutableContextFromRoot(ctx).SetContinuousState(z)
    expected = l1_law.gradient_controller_derivatives(p, z, s, kappa).astype(float)
    np.testing.assert_allclose(ctrl.EvalTimeDerivatives(ctx).CopyToVector(), expected,
                               rtol=1e-12, atol=1e-12)
    u = ctrl.GetOutputPort("steering_rad").Eval(ctx)[0]
    assert u == pytest.approx(l1_law.steering_command(p, s, z[10], kappa), rel=1e-13)


def test_piecewise_constant_system_evaluates_the_reference_update():
    ctrl, ctx, s, kappa = _controller_context("piecewise_constant")
    p = ctrl.parameters
    z = np.array([0.25, -0.2, 0.04, 0.12, 0.003])
    ctrl.core().GetMyMutableContextFromRoot(ctx).SetDiscreteState(z)
    s_hat_next, u_ad_next = l1_law.piecewise_constant_update(p, z[:4], z[4], s, kappa)
    update = ctrl.EvalUniquePeriodicDiscreteUpdate(ctx).get_vector().CopyToVector()
    np.testing.assert_allclose(update, np.append(s_hat_next, u_ad_next), rtol=1e-10,
                               atol=1e-12)
    u = ctrl.GetOutputPort("steering_rad").Eval(ctx)[0]
    assert u == pytest.approx(l1_law.steering_command(p, s, z[4], kappa), rel=1e-13)


@pytest.mark.parametrize("law", ["piecewise_constant",
                                 pytest.param("gradient", marks=pytest.mark.slow)])  # ~90 s
def test_cpp_controller_matches_the_python_reference_leaf_system(law):
    road = Road.curve(radius_m=50.0, straight_m=5.0, transition_m=10.0, curve_m=30.0)
    kw = dict(vehicle=CAR, design=DESIGN, settings=SETTINGS, stiffness_n_per_rad=42_000.0,
              friction_mu=0.6, speed_mps=SPEED, road=road)
    episode = EpisodeOptions(plant="nonlinear", law=law, t_final_s=3.0,
                             initial_state=[0.2, 0.0, 0.01, 0.0])
    tolerance = 1e-11  # piecewise-constant: the same fixed steps, only roundoff differs
    if law == "gradient":  # error-controlled steps: agreement to the integration accuracy
        config = SimulatorConfig(integration_scheme="runge_kutta3", accuracy=1e-8,
                                 use_error_control=True, publish_every_time_step=False)
        episode = dataclasses.replace(episode, config=config, t_final_s=1.5)
        tolerance = 1e-6
    fast = simulate(episode=episode, **kw)
    reference = simulate(episode=dataclasses.replace(episode, reference_controller=True), **kw)
    assert metrics.peak_lateral_offset(fast) > 0.05
    np.testing.assert_allclose(fast.states, reference.states, rtol=0, atol=tolerance)
    np.testing.assert_allclose(fast.steering_rad, reference.steering_rad, rtol=0, atol=tolerance)


def test_piecewise_constant_estimate_cancels_the_prediction_error_in_one_period():
    # If the plant follows the nominal model exactly, the estimate computed from any
    # prediction error makes the predictor meet the plant at the next sample.
    p = l1_law.l1_parameters(CAR, DESIGN, SETTINGS, SPEED)
    s, s_hat, u_ad, kappa = (np.array([0.1, 0.0, 0.02, 0.0]), np.array([0.3, 0.1, -0.01, 0.05]),
                             0.002, 1 / 80)
    s_hat_next, u_ad_next = l1_law.piecewise_constant_update(p, s_hat, u_ad, s, kappa)
    psidot = SPEED * kappa
    forcing = p.b_m * (u_ad_next + p.k_ff * psidot) + p.g_hat * psidot
    s_next = p.pc_exp @ s + p.pc_phi @ forcing  # nominal plant, u = -k_m s + u_ad + u_ff
    # The predictor is held as q = s_hat + V kappa e4 (l1_law.predictor_memory).
    np.testing.assert_allclose(l1_law.predicted_measurement(p, s_hat_next, kappa), s_next,
                               atol=1e-12)


def test_adaptation_sets_contain_the_true_parameters_of_the_interval():
    p = l1_law.l1_parameters(CAR, DESIGN, SETTINGS, SPEED)
    from drake_cert.synthesis.uncertainty import matched_uncertainty

    for c in np.linspace(*DESIGN.interval, 7):
        w, theta, _ = matched_uncertainty(CAR, c, DESIGN.nominal_stiffness_n_per_rad, SPEED,
                                          DESIGN.k_m_array)
        assert abs(w - p.w_centre) <= p.w_radius * (1 + 1e-12)
        assert np.linalg.norm(theta) <= p.theta_max / SETTINGS.controller.bound_factor * (1 + 1e-9)


def test_adaptive_loop_removes_the_offset_left_by_a_wrong_stiffness():
    # Linear plant, constant left curve, true C at the interval's lower end: the feedforward
    # alone (computed for C_hat) leaves an offset; the adaptive loop drives it back.
    road = Road((0.0,), (1 / 50,))
    start = dataclasses.replace(DESIGN)
    tape = simulate(vehicle=CAR, design=start, settings=SETTINGS, stiffness_n_per_rad=40_000.0,
                    friction_mu=0.9, speed_mps=SPEED, road=road,
                    episode=EpisodeOptions(plant="linear_sampled", law="piecewise_constant",
                                           t_final_s=8.0))
    assert abs(metrics.final_offset(tape)) < 0.01
    assert not metrics.left_lane(tape)


def test_sampled_and_continuous_linear_plants_agree():
    road = Road.curve(radius_m=50.0, straight_m=10.0, curve_m=30.0)
    kw = dict(vehicle=CAR, design=DESIGN, settings=SETTINGS, stiffness_n_per_rad=45_000.0,
              friction_mu=0.9, speed_mps=SPEED, road=road)
    sampled = simulate(episode=EpisodeOptions(plant="linear_sampled", law="piecewise_constant",
                                              t_final_s=6.0), **kw)
    continuous = simulate(episode=EpisodeOptions(plant="linear", law="piecewise_constant",
                                                 t_final_s=6.0), **kw)
    peak = metrics.peak_lateral_offset(continuous)
    assert peak > 1e-3
    np.testing.assert_allclose(sampled.states[:, 0], continuous.states[:, 0], atol=0.02 * peak)


def test_default_sample_period_is_converged():
    # Halving T_s from the shipped default moves the peak offset by well under 1 %
    # (benchmarks/bench_sample_period.py prints the full halving sequence).
    road = Road.curve(radius_m=50.0, straight_m=10.0, curve_m=40.0)
    peaks = []
    for factor in (1.0, 0.5):
        ctl = dataclasses.replace(SETTINGS.controller,
                                  sample_period_s=SETTINGS.controller.sample_period_s * factor)
        tape = simulate(vehicle=CAR, design=DESIGN,
                        settings=dataclasses.replace(SETTINGS, controller=ctl),
                        stiffness_n_per_rad=40_000.0, friction_mu=0.9, speed_mps=SPEED, road=road,
                        episode=EpisodeOptions(plant="linear_sampled", t_final_s=8.0))
        peaks.append(metrics.peak_lateral_offset(tape))
    assert abs(peaks[0] - peaks[1]) < 0.01 * peaks[1]


def test_both_laws_keep_the_linear_car_in_its_lane_on_a_curve():
    road = Road.curve(radius_m=50.0, straight_m=10.0, curve_m=30.0)
    for law in l1_law.LAWS:
        tape = simulate(vehicle=CAR, design=DESIGN, settings=SETTINGS,
                        stiffness_n_per_rad=58_000.0, friction_mu=0.9, speed_mps=SPEED, road=road,
                        episode=EpisodeOptions(plant="linear", law=law, t_final_s=6.0))
        assert not metrics.left_lane(tape), law
        assert metrics.peak_lateral_offset(tape) < 0.1, law


def test_car_stays_in_lane_on_the_nonlinear_plant_at_the_design_speed(default_design_table):
    # Every single-label design of the shipped table, true stiffness at both interval ends,
    # friction of the label, on the design curve at the design speed (Fiala tires).
    road = Road.curve(radius_m=SETTINGS.synthesis.design_radius_m, straight_m=20.0,
                      curve_m=60.0)
    singles = [d for d in default_design_table.designs if len(d.labels) == 1]
    assert len(singles) >= 6 and all(d.has_safe_speed for d in singles)
    for d in singles:
        for stiffness in d.interval:
            tape = simulate(vehicle=CAR, design=d, settings=SETTINGS,
                            stiffness_n_per_rad=stiffness, friction_mu=d.friction_mu_lo,
                            speed_mps=d.speed_mps, road=road,
                            episode=EpisodeOptions(plant="nonlinear",
                                                   t_final_s=110.0 / d.speed_mps))
            assert not metrics.left_lane(tape), (d.labels, stiffness,
                                                 metrics.peak_lateral_offset(tape))


def test_car_leaves_the_lane_far_above_the_grip_limit(heavy_rain_design):
    d = heavy_rain_design
    radius = SETTINGS.synthesis.design_radius_m
    grip_limit = np.sqrt(d.friction_mu_lo * 9.81 * radius)  # a_y = mu g on the curve
    speed = 1.5 * grip_limit
    road = Road.curve(radius_m=radius, straight_m=20.0, curve_m=60.0)
    tape = simulate(vehicle=CAR, design=d, settings=SETTINGS,
                    stiffness_n_per_rad=d.stiffness_lo_n_per_rad, friction_mu=d.friction_mu_lo,
                    speed_mps=speed, road=road,
                    episode=EpisodeOptions(plant="nonlinear", t_final_s=110.0 / speed))
    assert metrics.left_lane(tape)
    assert metrics.peak_lateral_offset(tape) > CAR.lane_margin_m


# The C_hi end takes ~90 s (the stiff gradient law near its projection bound): slow target.
@pytest.mark.parametrize("end", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_gradient_law_settles_at_the_synthesis_steady_state(heavy_rain_design, end):
    # The simulated loop on a constant curve ends where drake_cert.synthesis.equilibrium predicts
    # (the offset the design's steady-state condition is computed from); the piecewise-constant
    # law, compensating the unmatched estimate at DC, ends on the lane centre.
    from drake_cert.synthesis.equilibrium import SteadyCornering, adaptive_steady_state

    d = heavy_rain_design
    stiffness = d.certified_interval[end]  # far from C_hat: a visible gradient-law offset
    kappa = 1 / SETTINGS.synthesis.design_radius_m
    expected = adaptive_steady_state(CAR, d.k_m_array, d.nominal_stiffness_n_per_rad, stiffness,
                                     SteadyCornering(d.speed_mps, kappa),
                                     SETTINGS.controller.q_ad_diag)
    kw = dict(vehicle=CAR, design=d, settings=SETTINGS, stiffness_n_per_rad=stiffness,
              friction_mu=0.9, speed_mps=d.speed_mps, road=Road((0.0,), (kappa,)))
    gradient = simulate(episode=EpisodeOptions(plant="linear", law="gradient", t_final_s=40.0),
                        **kw)
    assert abs(expected.lateral_offset_m) > 0.01
    assert metrics.final_offset(gradient) == pytest.approx(expected.lateral_offset_m, rel=0.02)
    piecewise = simulate(episode=EpisodeOptions(plant="linear", law="piecewise_constant",
                                                t_final_s=40.0), **kw)
    assert abs(metrics.final_offset(piecewise)) < 0.05 * abs(expected.lateral_offset_m)
