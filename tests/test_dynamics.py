"""Eq. 2.45 (Rajamani; paper eq. dynamic): entries checked by hand for a numeric case."""

import numpy as np
import pydrake.symbolic as sym
import pytest

from drake_cert.config import VehicleParams
from drake_cert.dynamics import affine_parts, lateral_error_dynamics, yaw_rate_command


@pytest.fixture
def car():
    return VehicleParams()  # m = 1573 kg, I_z = 2873 kg m^2, l_f = 1.1 m, l_r = 1.58 m


def test_matrices_match_eq_2_45_by_hand(car):
    # C_f = C_r = 50 kN/rad per tire, V = 20 m/s; each entry written out from eq. 2.45.
    a, b, g = lateral_error_dynamics(car, 50_000.0, 20.0)
    cf = cr = 50_000.0
    expected_a = np.array([
        [0, 1, 0, 0],
        [0, -2 * (cf + cr) / (1573 * 20), 2 * (cf + cr) / 1573,
         2 * (-cf * 1.1 + cr * 1.58) / (1573 * 20)],
        [0, 0, 0, 1],
        [0, -2 * (cf * 1.1 - cr * 1.58) / (2873 * 20), 2 * (cf * 1.1 - cr * 1.58) / 2873,
         -2 * (cf * 1.1**2 + cr * 1.58**2) / (2873 * 20)],
    ])
    np.testing.assert_allclose(a, expected_a, rtol=1e-14)
    np.testing.assert_allclose(b, [0, 2 * cf / 1573, 0, 2 * cf * 1.1 / 2873], rtol=1e-14)
    np.testing.assert_allclose(
        g, [0, -2 * (cf * 1.1 - cr * 1.58) / (1573 * 20) - 20, 0,
            -2 * (cf * 1.1**2 + cr * 1.58**2) / (2873 * 20)], rtol=1e-14)
    # A few values typed in from a calculator, so that a shared slip in both sides shows.
    assert a[1, 1] == pytest.approx(-6.3573, abs=1e-4)
    assert a[1, 2] == pytest.approx(127.1456, abs=1e-4)
    assert a[3, 3] == pytest.approx(-6.4504, abs=1e-4)
    assert b[3] == pytest.approx(38.2875, abs=1e-4)


def test_affine_parts_reconstruct_a_and_b(car):
    a0, a1, a2, b1 = affine_parts(car)
    for c, v in ((20_000.0, 5.0), (120_000.0, 30.0), (55_000.0, 13.0)):
        a, b, _ = lateral_error_dynamics(car, c, v)
        np.testing.assert_allclose(a, c * a1 + (c / v) * a2 + a0, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(b, c * b1, rtol=1e-12)


def test_symbolic_dynamics_evaluate_to_the_numeric_ones(car):
    c, v = sym.Variable("C"), sym.Variable("V")
    a_sym, b_sym, g_sym = lateral_error_dynamics(car, c, v)
    env = {c: 42_000.0, v: 17.0}

    def evaluate(entries):
        return np.array([e.Evaluate(env) if isinstance(e, sym.Expression) else float(e)
                         for e in np.ravel(entries)]).reshape(np.shape(entries))

    a, b, g = lateral_error_dynamics(car, 42_000.0, 17.0)
    np.testing.assert_allclose(evaluate(a_sym), a, rtol=1e-14)
    np.testing.assert_allclose(evaluate(b_sym), b, rtol=1e-14)
    np.testing.assert_allclose(evaluate(g_sym), g, rtol=1e-14)


def test_yaw_rate_command_is_speed_times_curvature():
    assert yaw_rate_command(20.0, 1 / 50) == pytest.approx(0.4)
