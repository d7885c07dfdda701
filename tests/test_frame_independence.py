"""The model's assumption behind the drive's guarantee (docs/design.md 6.2, assumption A3):
frames of one stretch are independent given the stiffness under them. In the generator each
camera tick renders its frame from its own stream, and the smoothing and attack draw from their
own per-tick streams, so two frames of one stretch share only the stiffness (and condition) and
their look point."""

import dataclasses

import numpy as np
import torch

from drake_cert.certification.classifier import SmoothedClassifier
from drake_cert.certification.sampler import make_generator
from drake_cert.certification.seeds import Purpose, child_seed
from drake_cert.config import load_conditions
from drake_cert.perception.models import load_model
from drake_cert.systems.camera import CameraSource
from drake_cert.systems.route import Route, SegmentSpec
from drake_cert.systems.scenario import CameraSettings


def _camera(stiffness_n_per_rad=None):
    conditions = load_conditions()
    route = Route.build([SegmentSpec(200.0, 0.0, "sunny"), SegmentSpec(200.0, 0.0, "rain")],
                        conditions, "robotcar-like", seed=3)
    if stiffness_n_per_rad is not None:  # pin the first segment's stiffness (a bin's edge)
        segs = list(route.segments)
        segs[0] = dataclasses.replace(segs[0], stiffness_n_per_rad=float(stiffness_n_per_rad))
        route = Route(segs, route.transition_m)
    return CameraSource(route, conditions, "robotcar-like",
                        CameraSettings(rate_hz=10.0, look_ahead_m=0.0), seed=5)


def test_a_ticks_frame_depends_on_its_tick_and_the_stretch_under_its_look_point_only():
    cam = _camera()
    a = cam.capture(0.0, 10.0, 7)
    assert torch.equal(a.image, cam.capture(9.9, 150.0, 7).image)  # same stretch, same tick
    assert a.stiffness_n_per_rad == cam.capture(0.0, 150.0, 8).stiffness_n_per_rad
    assert not torch.equal(a.image, cam.capture(0.0, 10.0, 8).image)  # next tick: fresh draw
    assert cam.capture(0.0, 250.0, 7).label_index != a.label_index  # another stretch
    # the smoothing and attack noise of a tick are streams of their own, distinct per tick
    seeds = {child_seed(5, p, k) for p in (Purpose.CAMERA, Purpose.ESTIMATION, Purpose.ATTACK)
             for k in range(50)}
    assert len(seeds) == 150


def test_the_own_label_share_of_frames_at_one_stiffness_is_uncorrelated_from_tick_to_tick():
    # Frames of one stretch at sunny's least-grip edge (80 kN/rad, where g's misses gather):
    # the smoothed vote share for sunny (what a miss is decided on) varies from tick to tick
    # with no serial correlation beyond sampling error (|r| < 3 / sqrt(N) at lags 1-3).
    torch.set_num_threads(1)
    cam = _camera(stiffness_n_per_rad=80_000.0)
    classifier = SmoothedClassifier(load_model("robotcar-like", "classify", 1.0), 3, 1.0)
    ticks = 150
    share = np.empty(ticks)
    for k in range(ticks):
        frame = cam.capture(0.0, 10.0, k)
        assert frame.stiffness_n_per_rad == 80_000.0
        counts = classifier.sample_counts(frame.image, 100, 100,
                                          make_generator(child_seed(5, Purpose.ESTIMATION, k),
                                                         classifier.device))
        share[k] = counts[0] / 100
    assert share.std() > 0.05  # the share varies from frame to frame at this stiffness
    z = (share - share.mean()) / share.std()
    for lag in (1, 2, 3):
        r = float(np.mean(z[:-lag] * z[lag:]))
        assert abs(r) < 3 / np.sqrt(ticks - lag), (lag, r)
