"""Closed-loop metrics (DESIGN section 7): pure functions of a logged tape.

A tape is :class:`drake_cert.systems.closed_loop.Tape` (times, states s = [e1, e1dot, e2, e2dot],
steering, lane margin). Nothing here simulates.
"""

import numpy as np


def peak_lateral_offset(tape) -> float:
    """Largest |e1| over the episode (m)."""
    return float(np.max(np.abs(tape.states[:, 0])))


def left_lane(tape) -> bool:
    """True when |e1| exceeded the lane margin (lane - car width)/2 at some sample."""
    return not peak_lateral_offset(tape) <= tape.lane_margin_m  # a NaN state (diverged) too


def time_left_lane(tape) -> float | None:
    """First time (s) |e1| exceeded the lane margin, linearly interpolated between the last
    sample inside and the first sample outside the lane; None if it never did."""
    e1 = np.abs(tape.states[:, 0])
    outside = np.flatnonzero(~(e1 <= tape.lane_margin_m))  # NaN (a diverged run) counts
    if outside.size == 0:
        return None
    i = int(outside[0])
    if i == 0 or not np.isfinite(e1[i]):
        return float(tape.times_s[i])
    t0, t1, a, b = tape.times_s[i - 1], tape.times_s[i], e1[i - 1], e1[i]
    return float(t0 + (t1 - t0) * (tape.lane_margin_m - a) / (b - a))


def final_offset(tape) -> float:
    """e1 at the last sample (m), signed (> 0 left of the lane centre)."""
    return float(tape.states[-1, 0])


def peak_steering(tape) -> float:
    """Largest applied |steering| over the episode (rad)."""
    return float(np.max(np.abs(tape.steering_rad)))


def instability_rate(tapes) -> float:
    """Share of episodes (%) that left the lane."""
    tapes = list(tapes)
    if not tapes:
        return 0.0
    return 100.0 * sum(left_lane(t) for t in tapes) / len(tapes)
