"""Write a reproduction's results: CSVs, Markdown, plots and a metadata file (atomically).

``results.csv``   one row per cell (see :mod:`drake_cert.experiments.tables`)
``frames.csv``    one row per frame and cell, with the frame's seed (recomputable alone)
``tables.md``     the paper's tables, ours beside the paper's numbers
``claims.md``     the headline (departures not conditioned on the truth, :mod:`.headline`), then
                  the paper's claims checked on the frames (:mod:`.claims`; also ``claims.json``)
``meta.json``     command line, git revision, root seed, configuration, wall time
``sweep.png``     share certified, velocity and instability of f and g against eps
``radii.png``     certified-radius distributions of g per preset and sigma
``traces.png``    lateral offset of f and g on the same attacked frame (largest SA budget)
"""

from __future__ import annotations

import dataclasses
import io
import json
from pathlib import Path

import numpy as np

from drake_cert.experiments import tables
from drake_cert.experiments.perception_eval import json_safe
from drake_cert.io import atomic_write_bytes, atomic_write_text

FRAME_COLUMNS = ("preset", "frame", "position", "seed", "true_label", "stiffness_n_per_rad",
                 "friction_mu", "task", "pipeline", "sigma", "attack", "eps", "predicted",
                 "interval_lo", "interval_hi", "interval_covers", "certified", "certificate",
                 "safe_set_radius",
                 "design_labels", "velocity_mps", "left_lane", "peak_abs_e1_m")


@dataclasses.dataclass(frozen=True)
class RunResults:
    """What a reproduction writes: the frame rows, the per-cell summary and the run's meta."""

    rows: list[dict]
    summary: list[dict]
    meta: dict
    # per preset the bound p g_conformal's claim 3 is judged against
    # (claims.conformal_miss_bounds of the run's calibrations; None: no such verdict)
    conformal_miss_bounds: dict[str, float] | None = None


def write_results(out_dir: str | Path, results: RunResults, config, conditions,
                  plots: bool = True, designs: list | None = None) -> list[Path]:
    """Write every output file under ``out_dir``; returns their paths. ``designs``: the run's
    design table, which ``traces.png`` drives (synthesized again when not given)."""
    from drake_cert.experiments import claims

    rows, summary, meta = results.rows, results.summary, results.meta

    out = Path(out_dir)
    checked = claims.claims_document(rows, config.eps,
                                     conformal_miss_bounds=results.conformal_miss_bounds)
    written = [
        atomic_write_text(out / "results.csv", tables.to_csv(summary)),
        atomic_write_text(out / "frames.csv", tables.to_csv(rows, FRAME_COLUMNS)),
        atomic_write_text(out / "tables.md", tables.markdown(summary, config, conditions)),
        atomic_write_text(out / "claims.md", claims.document_markdown(checked, config.eps)),
        atomic_write_text(out / "claims.json", json.dumps(json_safe(checked), indent=1) + "\n"),
        atomic_write_text(out / "meta.json", json.dumps(
            dict(meta, config=dataclasses.asdict(config)), indent=2) + "\n"),
    ]
    if plots:
        written += [atomic_write_bytes(out / "sweep.png", sweep_plot(summary, config)),
                    atomic_write_bytes(out / "radii.png", radius_plot(rows, config)),
                    atomic_write_bytes(out / "traces.png", traces_plot(rows, config, designs))]
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
    """Histogram of g's certified radius (run-time label range) at the attacked frame, under
    SA and EA at the main budget (the cells that keep Cohen's fixed n)."""
    from matplotlib.figure import Figure

    presets = list(config.presets)
    fig = Figure(figsize=(4.2 * len(presets), 3.2))
    axes = fig.subplots(1, len(presets), squeeze=False)
    for j, p in enumerate(presets):
        for s in config.sigmas:
            radii = [r["certificate"] for r in rows if r["preset"] == p and r["pipeline"] == "g"
                     and r["sigma"] == s and r["eps"] == config.eps and r["attack"] != "none"]
            if radii:
                axes[0, j].hist(radii, bins=np.linspace(0, max(max(radii), 1e-3), 20),
                                alpha=0.5, label=f"sigma {s}")
        axes[0, j].axvline(config.eps, color="k", ls=":", label=f"eps {config.eps}")
        axes[0, j].set_title(p)
        axes[0, j].set_xlabel("certified radius of the run-time range")
        axes[0, j].legend(fontsize=7)
    axes[0, 0].set_ylabel("frame-cells")
    return _png(fig)


def trace_episodes(rows: list[dict], config) -> list[tuple[dict, dict]]:
    """Per preset, the (f row, g row) pair to draw: the same frame under SA at the largest
    budget where f left its lane (else where f drove fastest), g at the sweep's sigma."""
    pairs = []
    eps = max((r["eps"] for r in rows if r["attack"] == "sa"), default=None)
    for p in config.presets:
        f_rows = [r for r in rows if r["preset"] == p and r["pipeline"] == "f"
                  and r["attack"] == "sa" and r["eps"] == eps]
        if not f_rows:
            continue
        f = max(f_rows, key=lambda r: (bool(r["left_lane"]), r["velocity_mps"], -r["position"]))
        g = [r for r in rows if r["preset"] == p and r["pipeline"] == "g"
             and r["sigma"] == config.sweep_sigma and r["attack"] == "sa" and r["eps"] == eps
             and r["position"] == f["position"]]
        if g:
            pairs.append((f, g[0]))
    return pairs


def traces_plot(rows: list[dict], config, designs: list | None = None) -> bytes:
    """Lateral offset against time of f's and g's episodes on the same attacked frame: each
    drives the design its perception chose, at that design's safe speed (constant, in the
    legend), on the Fiala plant with the frame's true stiffness and friction."""
    from matplotlib.figure import Figure

    from drake_cert.config import load_conditions, load_settings, load_vehicle
    from drake_cert.experiments.episodes import EpisodeRunner
    from drake_cert.synthesis.table import synthesize_table

    vehicle, settings = load_vehicle(), load_settings()
    designs = designs if designs is not None else synthesize_table(vehicle, load_conditions(),
                                                                   settings)
    by_labels = {"+".join(d.labels): d for d in designs}
    runner = EpisodeRunner(vehicle, settings)
    pairs = trace_episodes(rows, config)
    fig = Figure(figsize=(4.2 * max(1, len(pairs)), 3.4))
    axes = fig.subplots(1, max(1, len(pairs)), squeeze=False)
    for j, pair in enumerate(pairs):
        ax = axes[0, j]
        margin = None
        for r, style in zip(pair, ("--", "-"), strict=True):
            name = "f" if r["pipeline"] == "f" else f"g (sigma {r['sigma']})"
            if r["velocity_mps"] <= 0:
                ax.plot([], [], style, label=f"{name}: stops")
                continue
            tape = runner.tape(by_labels[r["design_labels"]], r["stiffness_n_per_rad"],
                               r["friction_mu"])
            margin = tape.lane_margin_m
            ax.plot(tape.times_s, tape.states[:, 0], style,
                    label=f"{name}: {r['design_labels']} at {r['velocity_mps']:.1f} m/s"
                          + (", leaves lane" if r["left_lane"] else ""))
        if margin is not None:
            for sign in (1, -1):
                ax.axhline(sign * margin, color="k", lw=0.8, ls=":")
        f = pair[0]
        ax.set_title(f"{f['preset']}: frame {f['frame']} ({f['true_label']}), SA eps {f['eps']:g}",
                     fontsize=9)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("lateral offset e1 (m)")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    return _png(fig)
