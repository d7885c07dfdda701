"""The route: truth drawn within each condition, clothoid curvature, centre line, RouteSource."""

import math

import numpy as np
import pytest
from pydrake.systems.framework import DiagramBuilder

from drake_cert.config import load_conditions
from drake_cert.errors import ConfigError
from systems.route import Route, RouteSource, SegmentSpec

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
