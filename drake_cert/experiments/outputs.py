"""Write a reproduction's results: CSVs, Markdown, plots and a metadata file (atomically).

``results.csv``   one row per cell (see :mod:`drake_cert.experiments.tables`)
``frames.csv``    one row per frame and cell, with the frame's seed (recomputable alone)
``tables.md``     the paper's tables, ours beside the paper's numbers
``meta.json``     command line, git revision, root seed, configuration, wall time
``sweep.png``     share certified, velocity and instability of f and g against eps
``radii.png``     certified-radius distributions of g per preset and sigma
"""

from __future__ import annotations

import dataclasses
import io
import json
from pathlib import Path

import numpy as np

from drake_cert.experiments import tables
from drake_cert.io import atomic_write_bytes, atomic_write_text

FRAME_COLUMNS = ("preset", "frame", "position", "seed", "true_label", "stiffness_n_per_rad",
                 "friction_mu", "task", "pipeline", "sigma", "attack", "eps", "predicted",
                 "interval_lo", "interval_hi", "interval_covers", "certified", "certificate",
                 "safe_set_radius",
                 "design_labels", "velocity_mps", "left_lane", "peak_abs_e1_m")


def write_results(out_dir: str | Path, rows: list[dict], summary: list[dict], config,
                  conditions, meta: dict, plots: bool = True) -> list[Path]:
    """Write every output file under ``out_dir``; returns their paths."""
    out = Path(out_dir)
    written = [
        atomic_write_text(out / "results.csv", tables.to_csv(summary)),
        atomic_write_text(out / "frames.csv", tables.to_csv(rows, FRAME_COLUMNS)),
        atomic_write_text(out / "tables.md", tables.markdown(summary, config, conditions)),
        atomic_write_text(out / "meta.json", json.dumps(
            dict(meta, config=dataclasses.asdict(config)), indent=2) + "\n"),
    ]
    if plots:
        written += [atomic_write_bytes(out / "sweep.png", sweep_plot(summary, config)),
                    atomic_write_bytes(out / "radii.png", radius_plot(rows, config))]
    return written


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    return buf.getvalue()


def sweep_plot(summary: list[dict], config) -> bytes:
    """Share certified (g), velocity under EA and instability under SA against the budget."""
    from matplotlib.figure import Figure

    presets = list(config.presets)
    fig = Figure(figsize=(4.2 * len(presets), 8.5))
    axes = fig.subplots(3, len(presets), squeeze=False)
    for j, p in enumerate(presets):
        for pipe, sigma, style in (("f", 0.0, "o--"), ("g", config.sweep_sigma, "s-")):
            def series(attack, metric, p=p, pipe=pipe, sigma=sigma):
                pts = sorted((s["eps"], s[metric]) for s in summary
                             if s["preset"] == p and s["pipeline"] == pipe
                             and s["sigma"] == sigma and s["attack"] == attack)
                return [e for e, _ in pts], [v for _, v in pts]

            label = "f" if pipe == "f" else f"g (sigma {sigma})"
            axes[0, j].plot(*series("sa", "instability_pct"), style, label=label)
            axes[1, j].plot(*series("ea", "velocity_mps"), style, label=label)
            if pipe == "g":
                axes[2, j].plot(*series("sa", "certified_pct"), style, label=f"{label}, SA")
                axes[2, j].plot(*series("ea", "certified_pct"), "^:", label=f"{label}, EA")
        axes[0, j].set_title(p)
        axes[0, j].set_ylabel("instability under SA (%)")
        axes[1, j].set_ylabel("velocity under EA (m/s)")
        axes[2, j].set_ylabel("certified (%)")
        axes[2, j].set_xlabel("L2 budget eps")
        for i in range(3):
            axes[i, j].grid(alpha=0.3)
            axes[i, j].legend(fontsize=7)
    return _png(fig)


def radius_plot(rows: list[dict], config) -> bytes:
    """Histogram of g's certified radius (run-time label range) at the observed frame."""
    from matplotlib.figure import Figure

    presets = list(config.presets)
    fig = Figure(figsize=(4.2 * len(presets), 3.2))
    axes = fig.subplots(1, len(presets), squeeze=False)
    for j, p in enumerate(presets):
        for s in config.sigmas:
            radii = [r["certificate"] for r in rows if r["preset"] == p and r["pipeline"] == "g"
                     and r["sigma"] == s and r["eps"] == config.eps]
            if radii:
                axes[0, j].hist(radii, bins=np.linspace(0, max(max(radii), 1e-3), 20),
                                alpha=0.5, label=f"sigma {s}")
        axes[0, j].axvline(config.eps, color="k", ls=":", label=f"eps {config.eps}")
        axes[0, j].set_title(p)
        axes[0, j].set_xlabel("certified radius of the run-time range")
        axes[0, j].legend(fontsize=7)
    axes[0, 0].set_ylabel("frame-cells")
    return _png(fig)
