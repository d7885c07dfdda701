"""DESIGN 7 metrics as pure functions of a tape."""

import numpy as np
import pytest

from drake_cert import metrics
from drake_cert.systems.closed_loop import Tape


def _tape(e1, steering=None, margin=0.85):
    e1 = np.asarray(e1, float)
    states = np.zeros((len(e1), 4))
    states[:, 0] = e1
    return Tape(times_s=np.arange(len(e1)) * 0.1, states=states,
                steering_rad=np.zeros(len(e1)) if steering is None else np.asarray(steering),
                curvature_per_m=np.zeros(len(e1)), lane_margin_m=margin, speed_mps=10.0,
                stiffness_n_per_rad=5e4, friction_mu=0.5, plant="linear", law="gradient")


def test_peak_offset_final_offset_and_steering():
    tape = _tape([0.0, 0.3, -0.6, 0.2], steering=[0.0, -0.4, 0.1, 0.0])
    assert metrics.peak_lateral_offset(tape) == pytest.approx(0.6)
    assert metrics.final_offset(tape) == pytest.approx(0.2)
    assert metrics.peak_steering(tape) == pytest.approx(0.4)


def test_leaving_the_lane_is_exceeding_the_margin_on_either_side():
    assert not metrics.left_lane(_tape([0.0, 0.85, -0.85]))
    assert metrics.left_lane(_tape([0.0, -0.8501]))
    assert metrics.left_lane(_tape([0.9]))


def test_instability_rate_is_the_percentage_of_episodes_that_left():
    tapes = [_tape([0.1]), _tape([1.0]), _tape([-2.0]), _tape([0.5])]
    assert metrics.instability_rate(tapes) == pytest.approx(50.0)
    assert metrics.instability_rate([]) == 0.0


def test_time_left_lane_interpolates_the_first_crossing_of_the_margin():
    from drake_cert.metrics import time_left_lane

    tape = _tape([0.0, 0.5, 0.8, 1.2, 6.0])  # samples every 0.1 s, margin 0.85 m
    assert time_left_lane(tape) == pytest.approx(0.2 + 0.1 * (0.85 - 0.8) / (1.2 - 0.8))
    assert time_left_lane(_tape([0.0, -0.3, 0.2])) is None
