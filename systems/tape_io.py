"""Tapes to files: one row per tape sample, as CSV or NumPy ``.npz`` (written atomically).

Columns (SI units): ``case`` (index of the episode in the file), ``t_s``, ``e1_m``,
``e1dot_mps``, ``e2_rad``, ``e2dot_radps``, ``steering_rad``, ``curvature_per_m``. Per-episode
constants (speed, stiffness, friction, plant, law, stopped_early, simulated_s) are in a
``cases`` block: CSV comment lines ``# case <i>: key=value ...`` after the data (the first
line is the column header, so ``numpy.genfromtxt(f, delimiter=",", names=True)`` and
``pandas.read_csv(f, comment="#")`` read the file as is), or the npz array ``cases_json``
(a JSON string).
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from drake_cert.errors import ConfigError
from drake_cert.io import atomic_write_bytes

COLUMNS = ("case", "t_s", "e1_m", "e1dot_mps", "e2_rad", "e2dot_radps", "steering_rad",
           "curvature_per_m")
FORMATS = (".csv", ".npz")


def check_tape_path(path: str | Path, option: str = "--out") -> Path:
    """The tape file's format from its suffix; ConfigError for any other suffix."""
    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise ConfigError(f"{option} {path}: the tape is written as .csv or .npz, "
                          f"not {path.suffix or 'a file without suffix'!r}")
    return path


def tape_rows(tapes) -> np.ndarray:
    """All samples of all tapes as one float array [rows, len(COLUMNS)]."""
    blocks = [np.column_stack([np.full(len(t.times_s), i, float), t.times_s, t.states,
                               t.steering_rad, t.curvature_per_m])
              for i, t in enumerate(tapes)]
    return np.vstack(blocks) if blocks else np.zeros((0, len(COLUMNS)))


def tape_header(tape, **extra) -> dict:
    """The per-episode constants of one tape (JSON-serialisable)."""
    return {"speed_mps": tape.speed_mps, "stiffness_n_per_rad": tape.stiffness_n_per_rad,
            "friction_mu": tape.friction_mu, "plant": tape.plant, "law": tape.law,
            "lane_margin_m": tape.lane_margin_m, "stopped_early": bool(tape.stopped_early),
            "simulated_s": float(tape.simulated_s), **extra}


def write_tapes(path: str | Path, tapes, headers: list[dict] | None = None) -> Path:
    """Write ``tapes`` to ``path`` (.csv or .npz by suffix) atomically; returns the path."""
    path = check_tape_path(path)
    tapes = list(tapes)
    headers = headers or [tape_header(t) for t in tapes]
    rows = tape_rows(tapes)
    if path.suffix.lower() == ".csv":
        lines = [f"# case {i}: " + " ".join(f"{k}={json.dumps(v)}" for k, v in h.items())
                 for i, h in enumerate(headers)]
        buf = io.StringIO()
        np.savetxt(buf, rows, delimiter=",", fmt="%.9g", header=",".join(COLUMNS),
                   comments="")
        data = buf.getvalue() + ("\n".join(lines) + "\n" if lines else "")
        return atomic_write_bytes(path, data.encode("utf-8"))
    buf = io.BytesIO()
    np.savez(buf, **{c: rows[:, j] for j, c in enumerate(COLUMNS)},
             cases_json=np.array(json.dumps(headers)))
    return atomic_write_bytes(path, buf.getvalue())
