"""The f-vs-g traces of a reproduction: the same attacked frame, each pipeline's own design."""

from __future__ import annotations

from drake_cert.experiments import outputs
from drake_cert.experiments.reproduce_config import ReproduceConfig


def _row(pipeline, position, eps, left, speed, labels="sunny", sigma=0.0):
    return dict(preset="carla-like", pipeline=pipeline, attack="sa", eps=eps, sigma=sigma,
                position=position, frame=100 + position, true_label="light_rain",
                left_lane=left, velocity_mps=speed, design_labels=labels,
                stiffness_n_per_rad=65_000.0, friction_mu=0.7)


def test_the_pair_is_the_frame_where_f_left_its_lane_at_the_largest_budget():
    config = ReproduceConfig.quick()
    g_sigma = config.sweep_sigma
    rows = [_row("f", 0, 2.0, False, 19.0), _row("f", 1, 2.0, True, 17.0),
            _row("f", 2, 0.5, True, 19.0),
            _row("g", 1, 2.0, False, 0.0, "light_rain", g_sigma),
            _row("g", 0, 2.0, False, 14.0, "light_rain", g_sigma)]
    [(f, g)] = outputs.trace_episodes(rows, config)
    assert (f["position"], f["eps"], f["left_lane"]) == (1, 2.0, True)
    assert (g["pipeline"], g["position"]) == ("g", 1)


def test_traces_plot_draws_a_png_and_a_stopped_car_needs_no_episode():
    config = ReproduceConfig.quick()
    rows = [_row("f", 0, 1.0, False, 0.0), _row("g", 0, 1.0, False, 0.0, "light_rain",
                                                  config.sweep_sigma)]
    png = outputs.traces_plot(rows, config, designs=[])
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
