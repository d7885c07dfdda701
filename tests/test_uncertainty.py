"""DESIGN 4: the matched/unmatched split reconstructs the true closed loop exactly."""

import numpy as np
import pytest

from drake_cert.config import VehicleParams
from drake_cert.dynamics import lateral_error_dynamics
from drake_cert.synthesis.uncertainty import (
    curvature_feedforward_gain,
    matched_disturbance,
    matched_uncertainty,
    nominal_model,
    pseudo_inverse,
)

K_M = np.array([0.3, 0.05, 1.2, 0.1])
CASES = [(22_000.0, 50_000.0, 20.0), (120_000.0, 100_000.0, 8.0), (40_000.0, 50_000.0, 5.0),
         (50_000.0, 50_000.0, 30.0)]


@pytest.mark.parametrize("c, c_hat, v", CASES)
def test_split_reconstructs_true_state_matrix(c, c_hat, v):
    car = VehicleParams()
    w, theta, unmatched = matched_uncertainty(car, c, c_hat, v, K_M)
    a, b, _ = lateral_error_dynamics(car, c, v)
    nom = nominal_model(car, c_hat, v, K_M)
    true_closed_loop = a - np.outer(b, K_M)
    rebuilt = nom.a_m + np.outer(nom.b_m, theta) + unmatched
    np.testing.assert_allclose(rebuilt, true_closed_loop, rtol=1e-12, atol=1e-9)
    assert w == pytest.approx(c / c_hat)
    np.testing.assert_allclose(w * nom.b_m, b, rtol=1e-14)  # b(C) = w b_m


@pytest.mark.parametrize("c, c_hat, v", CASES)
def test_unmatched_part_is_orthogonal_to_the_input_direction(c, c_hat, v):
    car = VehicleParams()
    _, _, unmatched = matched_uncertainty(car, c, c_hat, v, K_M)
    b_m = nominal_model(car, c_hat, v, K_M).b_m
    np.testing.assert_allclose(b_m @ unmatched, 0.0, atol=1e-9 * np.abs(unmatched).max() + 1e-12)


@pytest.mark.parametrize("c, c_hat, v", CASES)
def test_curvature_terms_split_into_sigma_and_an_unmatched_rest(c, c_hat, v):
    car = VehicleParams()
    psidot = v / 50.0
    nom = nominal_model(car, c_hat, v, K_M)
    _, b, g = lateral_error_dynamics(car, c, v)
    u_ff = curvature_feedforward_gain(nom) * psidot
    sigma = matched_disturbance(car, c, c_hat, v, K_M, psidot)
    b_pinv = pseudo_inverse(nom.b_m)
    rest = (np.eye(4) - np.outer(nom.b_m, b_pinv)) @ (g - nom.g_hat) * psidot
    true_input = b * u_ff + g * psidot
    rebuilt = nom.b_m * (u_ff + sigma) + nom.g_hat * psidot + rest
    np.testing.assert_allclose(rebuilt, true_input, rtol=1e-12, atol=1e-12)


def test_feedforward_gives_zero_nominal_offset_on_a_curve():
    car = VehicleParams()
    nom = nominal_model(car, 50_000.0, 20.0, K_M)
    psidot = 20.0 / 50.0
    u_ff = curvature_feedforward_gain(nom) * psidot
    s_ss = -np.linalg.solve(nom.a_m, nom.b_m * u_ff + nom.g_hat * psidot)
    assert abs(s_ss[0]) < 1e-12
