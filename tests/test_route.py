"""The route: truth drawn within each condition, clothoid curvature, centre line, RouteSource."""

import math

import numpy as np
import pytest
from pydrake.systems.framework import DiagramBuilder

from drake_cert.config import load_conditions
from drake_cert.errors import ConfigError
from drake_cert.systems.route import Route, RouteSource, SegmentSpec

PRESET = "robotcar-like"
SPECS = [SegmentSpec(60.0, 0.0, "sunny"), SegmentSpec(80.0, 0.01, "sunny"),
         SegmentSpec(50.0, 0.01, "rain"), SegmentSpec(40.0, -0.02, "snow")]


@pytest.fixture(scope="module")
def conditions():
    return load_conditions()


def test_truth_draws_lie_in_their_condition_and_carry_its_friction(conditions):
    labels = conditions.preset(PRESET).labels
    for seed in range(20):
        route = Route.build(SPECS, conditions, PRESET, seed)
        for seg, spec in zip(route.segments, SPECS, strict=True):
            cond = conditions.condition(spec.condition)
            assert cond.stiffness_lo_n_per_rad <= seg.stiffness_n_per_rad
            assert seg.stiffness_n_per_rad <= cond.stiffness_hi_n_per_rad
            assert seg.friction_mu == cond.friction_mu
            assert labels[seg.label_index] == spec.condition


def test_truth_draws_are_deterministic_by_seed(conditions):
    a = Route.build(SPECS, conditions, PRESET, 7)
    b = Route.build(SPECS, conditions, PRESET, 7)
    c = Route.build(SPECS, conditions, PRESET, 8)
    assert [s.stiffness_n_per_rad for s in a.segments] == [s.stiffness_n_per_rad
                                                           for s in b.segments]
    assert [s.stiffness_n_per_rad for s in a.segments] != [s.stiffness_n_per_rad
                                                           for s in c.segments]
    # two segments of the same condition draw independently
    assert a.segments[0].stiffness_n_per_rad != a.segments[1].stiffness_n_per_rad


def test_segments_are_laid_end_to_end_and_looked_up_by_arc_length(conditions):
    route = Route.build(SPECS, conditions, PRESET, 0)
    assert route.total_length_m == pytest.approx(230.0)
    assert [s.start_m for s in route.segments] == [0.0, 60.0, 140.0, 190.0]
    s = np.array([-5.0, 0.0, 59.9, 60.0, 139.0, 140.0, 229.0, 230.0, 500.0])
    np.testing.assert_array_equal(route.segment_index_at(s), [0, 0, 0, 1, 1, 2, 3, 3, 3])
    assert route.stiffness_at(500.0) == route.segments[-1].stiffness_n_per_rad
    assert route.friction_at(145.0) == conditions.condition("rain").friction_mu


def test_curvature_is_constant_on_segments_and_ramps_across_boundaries(conditions):
    route = Route.build(SPECS, conditions, PRESET, 0, transition_m=10.0)
    k = route.curvature_at
    assert k(30.0) == 0.0 and k(100.0) == 0.01 and k(210.0) == -0.02
    assert k(60.0) == pytest.approx(0.005)  # the middle of the ramp at a boundary
    assert k(55.0) == 0.0 and k(65.0) == pytest.approx(0.01)  # the ramp spans 10 m
    assert k(140.0) == pytest.approx(0.01)  # no ramp where only the condition changes
    assert k(190.0) == pytest.approx(-0.005)
    assert k(1000.0) == -0.02  # beyond the end: the last segment
    grid = np.linspace(0.0, 230.0, 4601)
    assert np.max(np.abs(np.diff(k(grid)))) <= 0.03 / 10.0 * 0.05 + 1e-12  # continuous


def test_centre_line_of_a_quarter_circle_ends_where_geometry_says(conditions):
    radius = 100.0
    route = Route.build([SegmentSpec(0.5 * math.pi * radius, 1.0 / radius, "sunny")],
                        conditions, PRESET, 0)
    x, y, heading = route.pose_at(np.array([0.0, 0.5 * math.pi * radius]))
    assert (x[0], y[0], heading[0]) == (0.0, 0.0, 0.0)
    assert x[1] == pytest.approx(radius, abs=0.05)
    assert y[1] == pytest.approx(radius, abs=0.05)
    assert heading[1] == pytest.approx(0.5 * math.pi, abs=1e-6)


def test_bad_routes_raise_config_errors_naming_the_problem(conditions):
    with pytest.raises(ConfigError, match="asphalt"):
        Route.build([SegmentSpec(10.0, 0.0, "asphalt")], conditions, PRESET, 0)
    with pytest.raises(ConfigError, match="50 m"):
        Route.build([SegmentSpec(10.0, 0.05, "sunny")], conditions, PRESET, 0)
    with pytest.raises(ConfigError, match="length_m"):
        Route.build([SegmentSpec(0.0, 0.0, "sunny")], conditions, PRESET, 0)
    with pytest.raises(ConfigError, match="at least one"):
        Route.build([], conditions, PRESET, 0)


def test_route_source_outputs_the_segment_under_the_car(conditions):
    route = Route.build(SPECS, conditions, PRESET, 3)
    builder = DiagramBuilder()
    source = builder.AddSystem(RouteSource(route))
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    sub = source.GetMyContextFromRoot(context)
    for s, index in [(10.0, 0), (60.0, 1), (150.0, 2), (400.0, 3)]:
        source.GetInputPort("arc_length_m").FixValue(sub, [s])
        seg = route.segments[index]
        assert source.GetOutputPort("segment_index").Eval(sub)[0] == index
        assert source.GetOutputPort("stiffness_n_per_rad").Eval(sub)[0] == \
            seg.stiffness_n_per_rad
        assert source.GetOutputPort("friction_mu").Eval(sub)[0] == seg.friction_mu
        assert source.GetOutputPort("curvature_per_m").Eval(sub)[0] == \
            pytest.approx(float(route.curvature_at(s)))


def _preview_source(route, speed_mps, ahead_s=0.4, window_s=0.4):
    source = RouteSource(route, preview_ahead_s=ahead_s, preview_window_s=window_s)
    context = source.CreateDefaultContext()
    source.GetInputPort("speed_mps").FixValue(context, [speed_mps])

    def preview_at(s):
        source.GetInputPort("arc_length_m").FixValue(context, [s])
        return source.GetOutputPort("curvature_preview_per_m").Eval(context)[0]
    return preview_at


def _mean_curvature(route, lo, hi):
    """The mean of kappa over [lo, hi] by quadrature (independent of curvature_integral)."""
    from scipy.integrate import quad
    kinks = [k for k in route._knots if lo < k < hi]
    return quad(lambda x: float(route.curvature_at(x)), lo, hi, points=kinks or None,
                epsabs=1e-13, epsrel=1e-12)[0] / (hi - lo)


@pytest.mark.parametrize("speed", [5.0, 12.0, 20.0])
def test_route_preview_is_the_mean_curvature_over_the_window_at_the_current_speed(
        conditions, speed):
    route = Route.build(SPECS, conditions, PRESET, 3)  # straight, then 0.01/m from 55-65 m
    preview = _preview_source(route, speed)
    for s in (40.0, 50.0, 53.0, 57.0, 60.0, 63.0, 70.0):
        expected = _mean_curvature(route, s, s + 0.4 * speed)  # window [s, s + 0.4 V]
        assert preview(s) == pytest.approx(expected, rel=1e-9, abs=1e-12)
    # the preview sees the arc before the car reaches the ramp: a feedforward lead
    s = 55.0 - 0.2 * speed
    assert float(route.curvature_at(s)) == 0.0 and preview(s) > 0.0
    # a window ending 1 s ahead, 0.4 s long: [s + 0.6 V, s + V]
    ahead = _preview_source(route, speed, ahead_s=1.0, window_s=0.4)
    assert ahead(50.0) == pytest.approx(
        _mean_curvature(route, 50.0 + 0.6 * speed, 50.0 + speed), rel=1e-9, abs=1e-12)


def test_route_preview_on_an_arc_is_its_curvature_and_at_rest_the_curvature_under_the_car(
        conditions):
    route = Route.build(SPECS, conditions, PRESET, 3)
    assert _preview_source(route, 12.0)(80.0) == pytest.approx(0.01, abs=1e-15)  # [80, 84.8]
    assert _preview_source(route, 12.0)(200.0) == pytest.approx(-0.02, abs=1e-15)  # last arc
    at_rest = _preview_source(route, 0.0)
    for s in (10.0, 58.0, 61.5, 80.0):
        assert at_rest(s) == pytest.approx(float(route.curvature_at(s)), abs=1e-15)


def test_the_route_source_has_a_preview_port_only_with_a_preview_window(conditions):
    route = Route.build(SPECS, conditions, PRESET, 3)
    plain = RouteSource(route)
    assert not plain.HasOutputPort("curvature_preview_per_m")
    assert not plain.HasInputPort("speed_mps")
    with pytest.raises(ConfigError, match="preview_window_s"):
        RouteSource(route, preview_window_s=-0.1)
    with pytest.raises(ConfigError, match="preview_ahead_s"):
        RouteSource(route, preview_ahead_s=math.nan, preview_window_s=0.4)


def test_route_preview_of_one_point_equals_the_array_evaluation(conditions):
    route = Route.build(SPECS, conditions, PRESET, 3)  # includes a ramp at 185-195 m
    s = np.linspace(-5.0, 240.0, 491)
    for ahead, window in ((4.8, 4.8), (12.0, 4.8), (0.0, 0.0), (3.0, 0.0)):
        one_by_one = [route.preview_curvature_at(float(x), ahead, window) for x in s]
        np.testing.assert_allclose(one_by_one, route.preview_curvature_at(s, ahead, window),
                                   rtol=0, atol=1e-15)
