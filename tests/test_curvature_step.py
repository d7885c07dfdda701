"""A curvature step (straight -> design radius) makes no steering spike (issue 9, item 4).

The measured e2dot = r - V kappa jumps by -V dkappa at a step; the predictor holds its state
as q = s + V kappa e4 (systems.l1_law.predicted_measurement), so the prediction error, and
with it the piecewise-constant estimate, does not jump. Before, the steering saturated at
0.5 rad after the step for every single-label design (steady about 0.07 rad).
"""

import numpy as np
import pytest

from drake_cert.config import load_settings, load_vehicle
from systems import l1_law
from systems.closed_loop import simulate
from systems.road import Road

CAR = load_vehicle()
SETTINGS = load_settings()


@pytest.fixture(scope="module")
def heavy_rain(default_design_table):
    (design,) = [d for d in default_design_table.designs if d.labels == ["heavy_rain"]]
    assert design.has_safe_speed
    return design


def test_a_curvature_step_does_not_move_the_estimate(heavy_rain):
    # Plant and predictor agree on the straight; the step moves the measured e2dot only.
    v = heavy_rain.speed_mps
    p = l1_law.l1_parameters(CAR, heavy_rain, SETTINGS, v)
    s = np.array([0.05, -0.02, 0.01, 0.03])
    q_hat = l1_law.predictor_memory(p, s, 0.0)
    kappa = 1.0 / SETTINGS.synthesis.design_radius_m
    s_after = s - np.array([0.0, 0.0, 0.0, v * kappa])
    u_ad = 0.004
    _, u_ad_next = l1_law.piecewise_constant_update(p, q_hat, u_ad, s_after, kappa)
    decay = np.exp(-p.filter_gain * p.sample_period_s)
    assert u_ad_next == pytest.approx(decay * u_ad, abs=1e-12)  # no estimate from the step


def _step_episode(design, friction_mu):
    v = design.speed_mps
    road = Road.curvature_step(radius_m=SETTINGS.synthesis.design_radius_m, straight_m=2.0 * v)
    tape = simulate(vehicle=CAR, design=design, settings=SETTINGS,
                    stiffness_n_per_rad=design.interval[0], friction_mu=friction_mu,
                    speed_mps=v, road=road, t_final_s=8.0, tape_period_s=0.002)
    u = np.abs(tape.steering_rad)
    steady = float(np.mean(u[tape.times_s > 7.0]))
    peak = float(np.max(u[tape.times_s > 1.9]))
    return tape, peak, steady


def test_peak_steering_at_a_step_is_within_1p5_times_steady_when_the_tire_has_grip(heavy_rain):
    # Fiala plant at the certified speed and C_lo, friction 2.0: the step's transient stays
    # in the tire's near-linear range (measured ratio 1.20; 7.2 without the jump model).
    tape, peak, steady = _step_episode(heavy_rain, friction_mu=2.0)
    assert steady > 0.03
    assert peak <= 1.5 * steady
    assert not tape.stopped_early


def test_at_the_design_friction_the_step_leaves_the_steering_unsaturated(heavy_rain):
    # At mu_lo the car runs at 85% of its grip on the arc, so the step needs more yaw moment
    # than the front tire has: the loop compensates the saturating tire (measured peak
    # 0.19 rad, 2.4x steady), but no longer at the 0.5 rad limit, and stays in its lane.
    tape, peak, steady = _step_episode(heavy_rain, friction_mu=heavy_rain.friction_mu_lo)
    assert peak < 0.8 * CAR.steering_limit_rad
    assert np.max(np.abs(tape.states[:, 0])) < CAR.lane_margin_m
