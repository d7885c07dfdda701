"""Hovakimyan & Cao Def. B.3: integrating thetadot = Gamma Proj(theta, y) keeps |theta| <= thmax."""

import numpy as np
import pydrake.symbolic as sym
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drake_cert.systems.l1_law import projection_operator

EPS = 0.1


def _flow(theta0, theta_max, gamma, y_of_t, t_final, steps=2000):
    """Classical RK4 with a fixed step; returns the estimate at every step, shape (dim, N)."""
    def rhs(t, th):
        return gamma * projection_operator(th, y_of_t(t, th), theta_max, EPS).astype(float)

    h = t_final / steps
    th = np.asarray(theta0, float)
    out = [th]
    for i in range(steps):
        t = i * h
        k1 = rhs(t, th)
        k2 = rhs(t + h / 2, th + h / 2 * k1)
        k3 = rhs(t + h / 2, th + h / 2 * k2)
        k4 = rhs(t + h, th + h * k3)
        th = th + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(th)
    return np.array(out).T


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), dim=st.sampled_from([1, 2, 4]),
       theta_max=st.floats(0.05, 20.0))
def test_adversarial_updates_never_push_the_estimate_out_of_its_ball(seed, dim, theta_max):
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=dim)
    direction /= np.linalg.norm(direction)
    freqs = rng.uniform(0.5, 5.0, size=dim)

    def y_of_t(t, th):
        # Pushes outward along the current estimate (the worst case for the set) plus a
        # rotating component, with magnitude far above the set size.
        outward = th / max(np.linalg.norm(th), 1e-12)
        return 5.0 * theta_max * (outward + direction * np.sin(freqs * t))

    theta0 = direction * theta_max * rng.uniform(0.0, 0.99)
    path = _flow(theta0, theta_max, gamma=1.0, y_of_t=y_of_t, t_final=2.0)
    norms = np.linalg.norm(path, axis=0)
    assert norms.max() <= theta_max * (1.0 + 1e-6)
    # The push is strong enough that without projection the estimate would have left.
    assert norms.max() > theta_max / np.sqrt(1.0 + EPS)


def test_inside_the_inner_ball_the_update_is_untouched():
    th = np.array([0.1, -0.2])
    y = np.array([3.0, 4.0])
    np.testing.assert_array_equal(projection_operator(th, y, 1.0, EPS), y)


def test_on_the_boundary_the_outward_component_is_removed():
    th = np.array([1.0, 0.0])  # |th| = thmax: f = 1
    y = np.array([2.0, 1.0])
    out = projection_operator(th, y, 1.0, EPS)
    np.testing.assert_allclose(out, [0.0, 1.0], atol=1e-12)


def test_pointing_inward_is_never_projected():
    th = np.array([1.0, 0.0])
    y = np.array([-2.0, 1.0])
    np.testing.assert_array_equal(projection_operator(th, y, 1.0, EPS), y)


@pytest.mark.parametrize("th, y", [([0.99, 0.05], [1.0, -2.0]), ([0.2, 0.1], [1.0, 1.0]),
                                   ([-1.0, 0.3], [-0.5, 0.2])])
def test_symbolic_projection_evaluates_like_the_numeric_one(th, y):
    tv = sym.MakeVectorVariable(2, "th")
    yv = sym.MakeVectorVariable(2, "y")
    expr = projection_operator(tv, yv, 1.0, EPS)
    env = dict(zip(list(tv) + list(yv), th + y, strict=True))
    got = [e.Evaluate(env) for e in expr]
    np.testing.assert_allclose(got, projection_operator(np.array(th), np.array(y), 1.0, EPS),
                               rtol=1e-14)
