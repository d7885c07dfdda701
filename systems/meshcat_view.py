"""Meshcat view of a drive: the road and the car, coloured by certification state (DESIGN 6).

Runs headless: the drive is recorded as a Meshcat animation after the simulation (from the
logged tape, so the view adds no cost to the simulation), and ``StaticHtml()`` turns the
recording into one standalone page that any browser opens without a server.

Colours: the car is green while its interval is certified, amber while it runs on the
family envelope (abstain, bad frame, nothing certified), red while stopped (no safe speed
or below the stop speed), blue for the non-robust baseline. Road segments are tinted by
their true condition (grippy grey, wet blue, snow white).
"""

from __future__ import annotations

import numpy as np
from pydrake.geometry import Box, Meshcat, Rgba
from pydrake.math import RigidTransform, RotationMatrix

STATUS_COLOURS = {  # status code (drake_cert.systems.certified_interval) -> RGBA
    0: (0.1, 0.75, 0.2, 1.0),  # certified
    1: (1.0, 0.65, 0.0, 1.0),  # envelope
    2: (0.85, 0.1, 0.1, 1.0),  # stop
    3: (0.2, 0.4, 0.95, 1.0),  # base (non-robust)
}
STOPPED_COLOUR = STATUS_COLOURS[2]


def condition_colour(name: str) -> Rgba:
    """A tint per road condition for the lane edges."""
    name = name.lower()
    if "snow" in name:
        return Rgba(0.95, 0.95, 1.0, 1.0)
    if "rain" in name:
        return Rgba(0.3, 0.5, 0.9, 1.0)
    if "sand" in name or "cobble" in name:
        return Rgba(0.8, 0.65, 0.4, 1.0)
    return Rgba(0.6, 0.6, 0.6, 1.0)


def car_poses(route, arc_length_m: np.ndarray, lateral_offset_m: np.ndarray,
              heading_error_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World (x, y, yaw) of the car from its route coordinates: the centre-line pose at arc
    length s, moved by e1 along the left normal, yawed by e2."""
    x, y, heading = route.pose_at(np.asarray(arc_length_m, float))
    e1 = np.asarray(lateral_offset_m, float)
    return x - e1 * np.sin(heading), y + e1 * np.cos(heading), heading + heading_error_rad


def draw_route(meshcat: Meshcat, route, lane_width_m: float, step_m: float = 2.0) -> None:
    """Lane edges of every segment as lines, tinted by the segment's condition."""
    for i, seg in enumerate(route.segments):
        s = np.arange(seg.start_m, seg.start_m + seg.length_m + step_m, step_m)
        x, y, h = route.pose_at(s)
        for side, sign in (("left", 1.0), ("right", -1.0)):
            off = sign * 0.5 * lane_width_m
            pts = np.vstack([x - off * np.sin(h), y + off * np.cos(h), np.zeros_like(x)])
            meshcat.SetLine(f"road/{i:02d}_{seg.condition}/{side}", pts, 3.0,
                            condition_colour(seg.condition))


def record_drives(tapes: dict, route, *, lane_width_m: float, meshcat: Meshcat | None = None,
                  frames_per_second: float = 10.0) -> Meshcat:
    """Record drives on the same route (``{name: DriveTape}``, e.g. certified and base) as one
    animation: one car per drive, under ``cars/<name>``, coloured by its certification state."""
    meshcat = meshcat or Meshcat()
    meshcat.Delete()
    draw_route(meshcat, route, lane_width_m)
    ends = [float(t.times_s[-1]) for t in tapes.values() if len(t.times_s)]
    if not ends:
        return meshcat
    frame_times = np.arange(0.0, max(ends) + 1e-9, 1.0 / frames_per_second)
    for name in tapes:
        meshcat.SetObject(f"cars/{name}", Box(4.5, 1.8, 1.4), Rgba(*STATUS_COLOURS[1]))
    meshcat.StartRecording(frames_per_second=frames_per_second,
                           set_visualizations_while_recording=False)
    for name, tape in tapes.items():
        times = np.asarray(tape.times_s)
        if len(times) == 0:
            continue
        idx = np.clip(np.searchsorted(times, frame_times), 0, len(times) - 1)
        x, y, yaw = car_poses(route, tape.arc_length_m[idx], tape.states[idx, 0],
                              tape.states[idx, 2])
        for k, t in enumerate(frame_times):
            pose = RigidTransform(RotationMatrix.MakeZRotation(float(yaw[k])),
                                  [float(x[k]), float(y[k]), 0.7])
            meshcat.SetTransform(f"cars/{name}", pose, float(t))
            colour = STATUS_COLOURS.get(int(tape.status[idx[k]]), STATUS_COLOURS[1])
            if tape.speed_mps[idx[k]] < 0.1:
                colour = STOPPED_COLOUR
            meshcat.SetProperty(f"cars/{name}", "color", list(colour), float(t))
    meshcat.StopRecording()
    meshcat.PublishRecording()
    return meshcat
