"""Plots and tape files of drives (:func:`drake_cert.systems.driving.drive`): lateral offset, speed
and the certified interval against the true stiffness, one column per drive."""

from __future__ import annotations

import io
import json

import numpy as np

TAPE_COLUMNS = ("time_s", "e1_m", "e1dot_mps", "e2_rad", "e2dot_radps", "steering_rad",
                "speed_mps", "speed_command_mps", "arc_length_m", "curvature_per_m",
                "interval_lo_n_per_rad", "interval_hi_n_per_rad", "true_stiffness_n_per_rad",
                "design_index", "certified_radius", "status", "design_lo_n_per_rad",
                "design_hi_n_per_rad", "design_speed_mps")


def tape_matrix(tape) -> np.ndarray:
    """The tape as an (N, len(TAPE_COLUMNS)) float array."""
    return np.column_stack([
        tape.times_s, tape.states, tape.steering_rad, tape.speed_mps, tape.speed_command_mps,
        tape.arc_length_m, tape.curvature_per_m, tape.interval_n_per_rad,
        tape.true_stiffness_n_per_rad, tape.design_index, tape.certified_radius, tape.status,
        tape.design_interval_n_per_rad, tape.design_speed_mps])


def tape_bytes(results, path: str) -> bytes:
    """CSV (one block per drive, a ``pipeline`` column first, then one ``# summary`` comment
    line per drive with its JSON summary: precision, seed, settings) or NPZ (one array per
    drive and ``summaries_json``)."""
    summaries = [json.dumps(r.summary, default=str) for r in results]
    if str(path).lower().endswith(".npz"):
        buf = io.BytesIO()
        np.savez_compressed(buf, columns=np.array(TAPE_COLUMNS),
                            summaries_json=np.array(summaries), **{
            f"{r.summary['pipeline']}_{i}": tape_matrix(r.tape) for i, r in enumerate(results)})
        return buf.getvalue()
    lines = ["pipeline," + ",".join(TAPE_COLUMNS)]
    for r in results:
        for row in tape_matrix(r.tape):
            lines.append(r.summary["pipeline"] + "," + ",".join(f"{v:.6g}" for v in row))
    lines += [f"# summary {s}" for s in summaries]
    return ("\n".join(lines) + "\n").encode()


def rear_ratio(summary: dict) -> float:
    """The rear tire's stiffness over the front's for the drive's vehicle (1 for one scale):
    every interval of a drive is the front tire's C; the rear tire's is this times it."""
    vehicle = summary.get("vehicle") or {}
    front = vehicle.get("tire_stiffness_scale")
    rear = vehicle.get("rear_tire_stiffness_scale")
    return float(rear) / float(front) if front and rear else 1.0


def drive_figure_png(results) -> bytes:
    """Lateral offset (with the lane margin), speed (with the command and the safe speed of the
    design in force) and the design in force against the true stiffness under the car (the
    latest look-ahead decision dotted), for each drive side by side."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.5 * len(results), 7.5))
    axes = fig.subplots(3, len(results), sharex="col", squeeze=False)
    for j, r in enumerate(results):
        t, tape, s = r.tape.times_s, r.tape, r.summary
        ax = axes[0, j]
        ax.plot(t, tape.lateral_offset_m, label="e1")
        for sign in (1, -1):
            ax.axhline(sign * tape.lane_margin_m, color="r", ls=":", lw=1)
        ax.set_ylabel("lateral offset e1 (m)")
        ax.set_title(f"{s['scenario']}: {s['pipeline']}, attack {s['attack']} "
                     f"(eps {s['attack_eps']:g})" + (" LEFT LANE" if s["left_lane"] else ""))
        ax = axes[1, j]
        ax.plot(t, tape.speed_mps, label="speed")
        ax.step(t, tape.speed_command_mps, where="post", ls="--", label="command (look-ahead)")
        ax.step(t, tape.design_speed_mps, where="post", color="g", lw=1,
                label="safe speed of the design in force")
        ax.set_ylabel("speed (m/s)")
        ax.legend(fontsize=7)
        ax = axes[2, j]
        ax.fill_between(t, tape.design_interval_n_per_rad[:, 0] / 1e3,
                        tape.design_interval_n_per_rad[:, 1] / 1e3, step="post", alpha=0.3,
                        label="design in force")
        for edge in (0, 1):
            ax.step(t, tape.interval_n_per_rad[:, edge] / 1e3, where="post", color="tab:orange",
                    lw=0.8, ls=":", label=None if edge else "latest decision (look-ahead)")
        front_label = " (front tire)" if rear_ratio(s) != 1.0 else ""
        ax.plot(t, tape.true_stiffness_n_per_rad / 1e3, "k", lw=1,
                label=f"true C{front_label} (at the car)")
        if rear_ratio(s) != 1.0:  # a per-axle vehicle: the rear tire's interval and truth too
            rho = rear_ratio(s)
            ax.fill_between(t, rho * tape.design_interval_n_per_rad[:, 0] / 1e3,
                            rho * tape.design_interval_n_per_rad[:, 1] / 1e3, step="post",
                            alpha=0.15, color="tab:purple",
                            label=f"design in force, rear tire ({rho:.3g} C)")
            ax.plot(t, rho * tape.true_stiffness_n_per_rad / 1e3, "k--", lw=0.8,
                    label="true rear tire stiffness")
        covers = 100 * (s["design_covers_true_fraction"] or 0.0)
        ax.set_title(f"design in force holds true C {covers:.1f}% of the time; unprotected "
                     f"{s['time_unprotected_s']:.2f} s", fontsize=8)
        ax.set_ylabel("stiffness (kN/rad)")
        ax.set_xlabel("time (s)")
        ax.legend(fontsize=7)
        for a in axes[:, j]:
            a.grid(alpha=0.3)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    return buf.getvalue()
