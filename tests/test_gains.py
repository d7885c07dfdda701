"""The corner LMI of DESIGN 5.1: gains with the decay rate on the whole (C, V) box."""

import dataclasses

import numpy as np
import pytest

from drake_cert.config import load_settings, load_vehicle
from drake_cert.dynamics import lateral_error_dynamics
from drake_cert.errors import InfeasibleDesign
from drake_cert.synthesis.gains import corner_points, state_feedback_lmi, synthesize_state_feedback


def _abscissa(vehicle, k_m, c, v):
    a, b, _ = lateral_error_dynamics(vehicle, c, v)
    return np.linalg.eigvals(a - np.outer(b, k_m)).real.max()


@pytest.mark.parametrize("interval", [(20e3, 40e3), (80e3, 120e3), (20e3, 120e3)])
def test_lmi_gain_makes_every_corner_and_grid_point_hurwitz_with_the_decay_rate(interval):
    vehicle, syn = load_vehicle(), load_settings().synthesis
    k_m, v_hi = synthesize_state_feedback(vehicle, interval, syn)
    assert v_hi == syn.speed_max_mps
    for c, v in corner_points(interval, syn.speed_min_mps, v_hi):
        assert _abscissa(vehicle, k_m, c, v) <= -syn.decay_rate
    # a grid denser than the synthesis check, off its points
    worst = max(_abscissa(vehicle, k_m, c, v) for c in np.linspace(*interval, 33)
                for v in np.linspace(syn.speed_min_mps, v_hi, 77))
    assert worst <= -syn.decay_rate + 1e-9


def test_without_feedback_the_open_loop_misses_the_decay_rate():
    """The LMI is doing work: the open loop (a double integrator in e1) is not alpha-stable."""
    vehicle = load_vehicle()
    assert _abscissa(vehicle, np.zeros(4), 50e3, 20.0) > -0.2


def test_gain_speed_range_is_bisected_when_the_top_speed_is_infeasible():
    vehicle = load_vehicle()
    syn = dataclasses.replace(load_settings().synthesis, decay_rate=2.0)
    interval = (20e3, 120e3)
    assert state_feedback_lmi(vehicle, interval, 5.0, 30.0, 2.0, syn.lmi_margin) is None
    k_m, v_hi = synthesize_state_feedback(vehicle, interval, syn)
    assert syn.speed_min_mps < v_hi < syn.speed_max_mps
    worst = max(_abscissa(vehicle, k_m, c, v) for c in np.linspace(*interval, 21)
                for v in np.linspace(syn.speed_min_mps, v_hi, 41))
    assert worst <= -2.0 + 1e-9


def test_unreachable_decay_rate_raises_infeasible_design():
    vehicle = load_vehicle()
    syn = dataclasses.replace(load_settings().synthesis, decay_rate=10.0)
    with pytest.raises(InfeasibleDesign, match="gain LMI infeasible"):
        synthesize_state_feedback(vehicle, (20e3, 120e3), syn)
