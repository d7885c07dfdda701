"""Meshcat view: the road and each car are recorded headless into one standalone page."""

import numpy as np

from drake_cert.config import load_conditions
from drake_cert.systems.driving import DriveTape
from drake_cert.systems.meshcat_view import car_poses, record_drives
from drake_cert.systems.route import Route, SegmentSpec


def tape_along(route, status: int, seconds: float = 3.0) -> DriveTape:
    t = np.arange(0.0, seconds, 0.05)
    n = len(t)
    states = np.zeros((n, 4))
    states[:, 0] = 0.2 * np.sin(t)
    return DriveTape(times_s=t, states=states, steering_rad=np.zeros(n), speed_mps=np.full(n, 10.0),
                     speed_command_mps=np.full(n, 10.0), arc_length_m=10.0 * t,
                     curvature_per_m=np.zeros(n), interval_n_per_rad=np.zeros((n, 2)),
                     true_stiffness_n_per_rad=np.zeros(n), design_index=np.zeros(n, int),
                     certified_radius=np.zeros(n), status=np.full(n, status), lane_margin_m=0.85,
                     design_interval_n_per_rad=np.zeros((n, 2)),
                     design_speed_mps=np.full(n, 10.0))


def test_both_cars_and_the_road_are_in_the_recorded_page():
    route = Route.build([SegmentSpec(30.0, 0.0, "sunny"), SegmentSpec(40.0, 0.02, "snow")],
                        load_conditions(), "robotcar-like", seed=0)
    meshcat = record_drives({"certified": tape_along(route, 0), "base": tape_along(route, 3)},
                            route, lane_width_m=3.5)
    for path in ("cars/certified", "cars/base", "road/00_sunny/left", "road/01_snow/right"):
        assert meshcat.HasPath(path), path
    html = meshcat.StaticHtml()  # one standalone page, the recording embedded (msgpack)
    assert html.startswith("<!DOCTYPE html>") and len(html) > 100_000


def test_the_car_sits_left_of_the_centre_line_when_e1_is_positive():
    route = Route.build([SegmentSpec(50.0, 0.0, "sunny")], load_conditions(), "robotcar-like",
                        seed=0)
    x, y, yaw = car_poses(route, np.array([10.0]), np.array([0.5]), np.array([0.0]))
    x0, y0, heading = route.pose_at(np.array([10.0]))
    left = np.array([-np.sin(heading[0]), np.cos(heading[0])])
    assert abs(np.dot([x[0] - x0[0], y[0] - y0[0]], left) - 0.5) < 1e-9
