"""The L1 norm (DESIGN 5.2) against closed forms and an independent quadrature."""

import numpy as np
import pytest
import scipy.integrate
from hypothesis import given, settings
from hypothesis import strategies as st

from drake_cert.config import load_vehicle
from drake_cert.synthesis import l1_norm
from drake_cert.synthesis.conditions import filtered_plant_realisation
from drake_cert.synthesis.uncertainty import nominal_model
from drake_cert.synthesis.verify import l1_norm_by_quadrature


@pytest.mark.parametrize("a", [0.05, 1.0, 37.0, 2.0e3])
def test_first_order_lag_has_l1_norm_one_over_a(a):
    assert l1_norm([[-a]], [1.0], [1.0]) == pytest.approx(1.0 / a, rel=1e-10)


def _second_order(zeta, omega):
    a = np.array([[0.0, 1.0], [-omega**2, -2.0 * zeta * omega]])
    return a, np.array([0.0, 1.0]), np.array([1.0, 0.0])


@pytest.mark.parametrize("zeta,omega", [(0.05, 2.0), (0.3, 1.0), (0.7, 15.0)])
def test_underdamped_second_order_matches_closed_form_and_quadrature(zeta, omega):
    """g(t) = exp(-s t) sin(d t) / d with s = zeta omega, d = omega sqrt(1 - zeta^2).

    Closed form: the half-period lobes form a geometric series with ratio q = exp(-s pi / d),
    integral |g| = (1 + q) / ((1 - q) omega^2). Independently, scipy quad over each half period.
    """
    s, d = zeta * omega, omega * np.sqrt(1.0 - zeta**2)
    q = np.exp(-s * np.pi / d)
    closed_form = (1.0 + q) / ((1.0 - q) * omega**2)
    lobes, k = 0.0, 0
    while True:
        lobe, _ = scipy.integrate.quad(lambda t: abs(np.exp(-s * t) * np.sin(d * t)) / d,
                                       k * np.pi / d, (k + 1) * np.pi / d, epsabs=0, epsrel=1e-12)
        lobes += lobe
        k += 1
        if lobe < 1e-14 * lobes:
            break
    value = l1_norm(*_second_order(zeta, omega))
    assert lobes == pytest.approx(closed_form, rel=1e-9)
    assert value == pytest.approx(closed_form, rel=1e-4)
    # the L1 norm of an oscillating response exceeds its DC gain 1 / omega^2
    assert value > 1.0 / omega**2


def test_l1_norm_is_max_over_outputs_of_sum_over_inputs():
    a = np.diag([-1.0, -2.0])
    b = np.array([[1.0, -2.0], [3.0, 0.0]])
    # output 1: e^-t and -2 e^-t -> 1 + 2 = 3; output 2: 3 e^-2t -> 1.5
    assert l1_norm(a, b, np.eye(2)) == pytest.approx(3.0, rel=1e-10)
    assert l1_norm(a, b, np.array([[0.0, 1.0]])) == pytest.approx(1.5, rel=1e-10)


def test_defective_matrix_falls_back_and_stays_accurate():
    # Jordan block: g(t) = t exp(-t), integral 1
    a = np.array([[-1.0, 1.0], [0.0, -1.0]])
    assert l1_norm(a, [0.0, 1.0], [1.0, 0.0]) == pytest.approx(1.0, rel=1e-4)


def test_unstable_system_has_infinite_l1_norm():
    assert l1_norm([[0.1]], [1.0], [1.0]) == np.inf


def test_incompatible_shapes_are_rejected():
    with pytest.raises(ValueError, match="incompatible shapes"):
        l1_norm(np.eye(3) * -1.0, np.ones(2), np.ones(3))


@settings(max_examples=25, deadline=None)
@given(speed=st.floats(5.0, 30.0), w=st.floats(0.3, 1.7), k=st.floats(10.0, 600.0),
       stiffness=st.floats(25e3, 110e3))
def test_l1_norm_of_filtered_plant_agrees_with_independent_quadrature(speed, w, k, stiffness):
    """G = H (1 - C_w) for the lateral model (order 5, 4 outputs) vs trapezoid quadrature."""
    k_m = [0.0101, 0.0031, 0.215, 0.0172]  # a corner-LMI gain (snow interval)
    nom = nominal_model(load_vehicle(), stiffness, speed, k_m)
    a, b, c = filtered_plant_realisation(nom, w, k)
    if np.linalg.eigvals(nom.a_m).real.max() >= 0.0:
        assert l1_norm(a, b, c) == np.inf
        return
    assert l1_norm(a, b, c) == pytest.approx(l1_norm_by_quadrature(a, b.ravel(), c), rel=2e-4)


def test_random_stable_systems_agree_with_independent_quadrature():
    rng = np.random.default_rng(7)
    for _ in range(10):
        a = rng.normal(size=(5, 5))
        a -= (np.linalg.eigvals(a).real.max() + rng.uniform(0.1, 2.0)) * np.eye(5)
        b, c = rng.normal(size=5), rng.normal(size=(3, 5))
        assert l1_norm(a, b, c) == pytest.approx(l1_norm_by_quadrature(a, b, c), rel=2e-4)


def test_batched_filtered_plant_norms_equal_one_at_a_time_norms():
    """The speed search's shared-pole evaluation over w agrees with l1_norm per realisation."""
    from drake_cert.synthesis.conditions import high_passed_plant_l1_norms

    k_m = [0.0349, 0.0132, 0.528, 0.0599]  # corner-LMI gain of the 20k-120k envelope
    for speed, k in [(5.0, 500.0), (12.0, 50.0), (30.0, 200.0)]:
        nom = nominal_model(load_vehicle(), 70e3, speed, k_m)
        w = np.linspace(20e3, 120e3, 6) / 70e3
        one_at_a_time = [l1_norm(*filtered_plant_realisation(nom, wi, k)) for wi in w]
        assert high_passed_plant_l1_norms(nom, w, k) == pytest.approx(one_at_a_time, rel=1e-9)
