"""Safe-speed search (DESIGN 5.3) and the design table (DESIGN 5.4)."""

import dataclasses

import numpy as np
import pytest
import scipy.linalg

from drake_cert.config import GRAVITY_MPS2, load_conditions, load_settings, load_vehicle
from drake_cert.dynamics import lateral_error_dynamics
from drake_cert.synthesis import conditions as cond
from drake_cert.synthesis.design import VEHICLE_LIMIT_KEYS
from drake_cert.synthesis.equilibrium import SteadyCornering, adaptive_steady_state
from drake_cert.synthesis.speed import (
    L1_MARGIN_MIN,
    SPEED_RESOLUTION_MPS,
    sample_period_filter_gain_limit,
)
from drake_cert.synthesis.table import (
    design_label_ranges,
    friction_lower_bound,
    synthesize_design,
    synthesize_label_range,
)
from drake_cert.synthesis.verify import cornering_slip_angles


def _design(table, *labels):
    return next(d for d in table.designs if tuple(d.labels) == labels)


def test_single_label_safe_speeds_are_strictly_lower_for_lower_friction(default_design_table):
    speeds = [_design(default_design_table, label).speed_mps
              for label in ("snow", "heavy_rain", "light_rain", "sunny")]
    assert 0.0 < speeds[0] < speeds[1] < speeds[2] < speeds[3]


def test_table_has_one_design_per_contiguous_label_range(default_design_table):
    conditions = load_conditions()
    labels = [tuple(d.labels) for d in default_design_table.designs]
    assert len(labels) == len(set(labels)) == len(design_label_ranges(conditions))
    for preset in conditions.presets:
        for run in conditions.contiguous_ranges(preset.name):
            assert tuple(run) in labels
    for d in default_design_table.designs:
        assert d.interval == conditions.hull(d.labels)
        assert d.friction_mu_lo == conditions.least_friction(d.labels)


def test_every_safe_speed_meets_all_four_conditions_at_that_speed(default_design_table):
    vehicle, settings = load_vehicle(), load_settings()
    syn = settings.synthesis
    for d in default_design_table.designs:
        assert d.has_safe_speed, d.labels
        v, k = d.speed_mps, d.filter_gain
        assert syn.speed_min_mps <= v <= d.gain_speed_max_mps
        w_max = d.certified_interval[1] / d.nominal_stiffness_n_per_rad  # the sampled law's limit
        assert 0 < k * w_max * settings.controller.sample_period_s <= 1.0 + 1e-12
        box = d.certified_interval  # the label interval widened to the tire's secant stiffness
        assert box[0] < d.stiffness_lo_n_per_rad and box[1] == d.stiffness_hi_n_per_rad
        assert cond.l1_condition_margin(vehicle, d.k_m, box, v, k, 9, 9) > 0.0
        assert cond.reference_stability_margin(
            vehicle, d.k_m, cond.OperatingBox(box, syn.speed_min_mps, v), k, (9, 25)) > 0.0
        assert cond.steady_state_offset_margin(vehicle, d.k_m, box, v,
                                               syn.design_radius_m, settings.controller.q_ad_diag,
                                               9) > 0.0
        slip, accel = cond.grip_margins(d.friction_mu_lo, v, syn.design_radius_m,
                                        d.tire_slip_bound, syn.lateral_accel_fraction)
        assert slip >= 0.0 and accel >= 0.0
        # the shipped car gives no CG height and the settings no comfort limit: no condition e
        assert set(d.margins) == set(cond.MARGIN_KEYS) - set(VEHICLE_LIMIT_KEYS)
        assert d.speed_limited_by in ("grip", "l1_condition", "reference_stability")


def test_safe_speed_is_at_most_the_grip_limit_and_close_to_it_when_grip_binds(default_design_table):
    syn = load_settings().synthesis
    for d in default_design_table.designs:
        limit = cond.grip_speed_limit_mps(d.friction_mu_lo, syn.design_radius_m,
                                          d.tire_slip_bound, syn.lateral_accel_fraction)
        assert d.speed_mps <= limit
        if min(d.margins["grip_normalised_slip"],
               d.margins["grip_lateral_accel_mps2"]) < 1e-3:  # grip is the binding condition
            assert d.speed_mps >= limit - syn.speed_grid_step_mps / 16


def test_friction_limit_is_sqrt_of_fraction_mu_g_r():
    """a_y <= 0.85 mu g on R = 50 m: sunny 19.36, light rain 17.08, heavy rain 14.44, snow 10.21."""
    for mu, expected in [(0.9, 19.36), (0.7, 17.08), (0.5, 14.44), (0.25, 10.21)]:
        # slip bound 0.6 admits 1 - 0.4^3 = 94% of the grip: the 85% fraction binds
        v = cond.grip_speed_limit_mps(mu, 50.0, 0.6, 0.85)
        assert v == pytest.approx(np.sqrt(0.85 * mu * GRAVITY_MPS2 * 50.0))
        assert v == pytest.approx(expected, abs=0.05)
    # a small slip bound binds instead: z_b = 0.2 admits 1 - 0.8^3 = 48.8% of mu g
    assert cond.grip_speed_limit_mps(0.5, 50.0, 0.2, 0.85) == pytest.approx(
        np.sqrt(0.488 * 0.5 * GRAVITY_MPS2 * 50.0))


def test_single_label_speeds_follow_friction_not_stiffness(default_design_table):
    # asphalt and heavy rain share the stiffness interval 40k-60k; friction 0.8 vs 0.5
    asphalt = _design(default_design_table, "asphalt").speed_mps
    heavy_rain = _design(default_design_table, "heavy_rain").speed_mps
    assert asphalt > heavy_rain
    assert asphalt == pytest.approx(np.sqrt(0.85 * 0.8 * GRAVITY_MPS2 * 50.0), abs=0.05)


@pytest.mark.parametrize("utilisation", [0.1, 0.5, 0.85, 0.99])
def test_steady_tire_slip_matches_the_axle_balance_through_the_fiala_force(utilisation):
    from drake_cert.synthesis.verify import cornering_normalised_slip

    vehicle, mu, radius = load_vehicle(), 0.7, 50.0
    speed = np.sqrt(utilisation * mu * GRAVITY_MPS2 * radius)
    closed_form = cond.steady_state_normalised_slip(mu, speed, radius)
    assert closed_form == pytest.approx(cornering_normalised_slip(vehicle, mu, speed, radius),
                                        abs=1e-9)
    assert 3 * closed_form - 3 * closed_form**2 + closed_form**3 == pytest.approx(utilisation)


@pytest.mark.parametrize("stiffness,speed", [(20e3, 8.0), (80e3, 16.0), (45e3, 25.0)])
def test_slip_angle_formula_matches_the_steady_state_single_track(stiffness, speed):
    vehicle = load_vehicle()
    formula = cond.steady_state_slip_angles(vehicle, stiffness, speed, 50.0)
    solved = cornering_slip_angles(vehicle, stiffness, speed, 50.0)
    assert formula == pytest.approx(solved, rel=1e-12)


def test_no_safe_speed_names_grip_when_the_slip_limit_is_unreachable():
    settings = load_settings()
    settings = dataclasses.replace(
        settings, synthesis=dataclasses.replace(settings.synthesis, normalised_slip_max=1e-4))
    d = synthesize_design(load_vehicle(), (20e3, 40e3), 0.25, settings, ["snow"])
    assert d.speed_mps == 0.0 and d.failed_condition == cond.GRIP
    assert d.margins["grip_normalised_slip"] < 0.0


def test_no_safe_speed_names_the_l1_condition_when_the_filter_is_too_slow():
    settings = load_settings()
    settings = dataclasses.replace(
        settings, synthesis=dataclasses.replace(settings.synthesis, filter_gain_max=2.0),
        controller=dataclasses.replace(settings.controller, sample_period_s=0.1))
    # (T_s = 0.1 s: the sample-period limit on k, about 5, is no way out either)
    d = synthesize_design(load_vehicle(), (20e3, 120e3), 0.25, settings, ["wide"])
    assert d.speed_mps == 0.0 and d.failed_condition == cond.L1_CONDITION
    assert d.margins["l1_condition"] < 0.0


def _l1_bound_setting():
    """T_s = 1.6 ms: the widest interval's filter gain is held to about 360, and the L1
    condition, not grip, stops its speed (on a high-friction road)."""
    settings = load_settings()
    return dataclasses.replace(settings, controller=dataclasses.replace(
        settings.controller, sample_period_s=1.6e-3))


def test_an_l1_limited_speed_is_the_largest_to_a_64th_of_a_metre_per_second():
    settings, vehicle = _l1_bound_setting(), load_vehicle()
    syn = settings.synthesis
    d = synthesize_design(vehicle, (20e3, 120e3), 0.9, settings, ["wide"])
    assert d.speed_limited_by == cond.L1_CONDITION
    k_bar = sample_period_filter_gain_limit(settings, d.certified_interval)

    def margin(v):
        return cond.l1_condition_margin(vehicle, d.k_m, d.certified_interval, v, k_bar,
                                        syn.w_grid_points, syn.stiffness_grid_points)

    assert margin(d.speed_mps) >= L1_MARGIN_MIN > margin(d.speed_mps + SPEED_RESOLUTION_MPS)
    cell = syn.speed_grid_step_mps
    assert d.speed_mps % cell != 0.0  # resolved inside the grid cell, not at its floor


def test_the_filter_gain_rises_to_the_sample_period_limit_where_that_gives_more_speed():
    """The shipped envelope (sunny to snow, joint gains) at the shipped T_s: its speed at
    k_bar = 500 is L1-limited; at the sample-period limit it is faster, and the search keeps
    that design. With T_s set so that the limit is k_bar itself, the search stays at k_bar."""
    settings, vehicle, conditions = load_settings(), load_vehicle(), load_conditions()
    envelope = ("sunny", "rain", "snow")
    fast = synthesize_label_range(vehicle, conditions, envelope, settings)
    w_max = fast.certified_interval[1] / fast.nominal_stiffness_n_per_rad
    capped_settings = dataclasses.replace(settings, controller=dataclasses.replace(
        settings.controller, sample_period_s=1.0 / (settings.synthesis.filter_gain_max * w_max)))
    capped = synthesize_label_range(vehicle, conditions, envelope, capped_settings)
    assert capped.certified_interval == fast.certified_interval
    assert capped.filter_gain <= settings.synthesis.filter_gain_max * (1 + 1e-12)
    assert fast.filter_gain > settings.synthesis.filter_gain_max
    assert fast.speed_mps > capped.speed_mps + SPEED_RESOLUTION_MPS
    assert fast.filter_gain * w_max * settings.controller.sample_period_s <= 1.0 + 1e-12


def _lqr_gain(vehicle, c_hat, speed):
    a, b, _ = lateral_error_dynamics(vehicle, c_hat, speed)
    p = scipy.linalg.solve_continuous_are(a, b.reshape(4, 1), np.eye(4), np.eye(1))
    return b @ p


def test_adaptive_equilibrium_is_an_equilibrium_of_plant_predictor_and_gradient_law():
    vehicle = load_vehicle()
    k_m, c_hat, c, v, kappa = _lqr_gain(vehicle, 50e3, 20.0), 50e3, 22e3, 20.0, 1.0 / 50.0
    eq = adaptive_steady_state(vehicle, k_m, c_hat, c, SteadyCornering(v, kappa),
                               [10.0, 1.0, 10.0, 1.0])
    a, b, g = lateral_error_dynamics(vehicle, c, v)
    u = -k_m @ eq.state + eq.adaptive_input_rad + eq.feedforward_input_rad
    assert np.allclose(a @ eq.state + b * u + g * v * kappa, 0.0, atol=1e-10)
    a_hat, b_m, g_hat = lateral_error_dynamics(vehicle, c_hat, v)
    a_m = a_hat - np.outer(b_m, k_m)
    assert np.allclose(a_m @ eq.predictor_state + b_m * eq.feedforward_input_rad
                       + g_hat * v * kappa, 0.0, atol=1e-10)
    assert abs(eq.predictor_state[0]) < 1e-12  # curvature feedforward: nominal e1 = 0
    p_ad = scipy.linalg.solve_continuous_lyapunov(a_m.T, -np.diag([10.0, 1.0, 10.0, 1.0]))
    assert abs((eq.predictor_state - eq.state) @ p_ad @ b_m) < 1e-9


def test_weighting_position_errors_in_q_ad_shrinks_the_offset_as_design_reports():
    """DESIGN 4: LQR k_m, V = 20, C_hat = 50k, C = 22k: about -0.59 m (Q_ad = I) vs -0.15 m
    (diag(10, 1, 10, 1)); our LQR weights differ, so only sign and ordering are checked."""
    vehicle = load_vehicle()
    k_m = _lqr_gain(vehicle, 50e3, 20.0)
    offsets = [adaptive_steady_state(vehicle, k_m, 50e3, 22e3,
                                     SteadyCornering(20.0, 1.0 / 50.0), q)
               .lateral_offset_m for q in ([1.0] * 4, [10.0, 1.0, 10.0, 1.0])]
    assert offsets[0] < offsets[1] < 0.0
    assert offsets[1] > 0.5 * offsets[0] and offsets[0] > -vehicle.lane_margin_m


def test_regression_interval_takes_the_least_friction_of_every_label_it_meets():
    conditions = load_conditions()
    assert friction_lower_bound(conditions, "carla-like", (85e3, 110e3)) == 0.9
    assert friction_lower_bound(conditions, "carla-like", (70e3, 90e3)) == 0.7
    assert friction_lower_bound(conditions, "rtk-like", (46e3, 50e3)) == 0.6  # asphalt/cobble
    assert friction_lower_bound(conditions, "rtk-like", (45e3, 50e3)) == 0.45  # sand: closed
    assert friction_lower_bound(conditions, "weather", (5e3, 10e3)) == 0.25  # meets none
