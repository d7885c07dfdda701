"""Perception results table: accuracy, attacks, certified radius, run-time interval.

For each preset and sigma in {0, 0.25, 0.5, 1.0}, with the shipped models
(drake_cert/data/models):
- sigma = 0 (the paper's f): clean accuracy, and accuracy under L2 PGD at --attack-eps
  (stability attack SA, efficiency attack EA, and "either": a frame counts as right only if
  both attacks fail), against f.
- sigma > 0 (smoothed g, n0 = 100, n = 10,000, alpha = 0.001 by default): clean accuracy,
  mean certified radius R_S(a) and R_{a} at the clean frame (abstain = 0), clean abstain rate;
  then a SmoothAdv stability attack at --interval-eps against g and, at the attacked frame,
  the smoothed accuracy and the run-time stiffness interval at budget --interval-eps: mean
  width, coverage of the true stiffness, envelope rate.

Each cell is stored as JSON under results/perception/ (with provenance) as soon as it is done,
so an interrupted run resumes; cells whose model is missing are listed as such. Writes
results/perception_table.md and prints it.

Usage: python benchmarks/results_perception.py [--frames 20] [--presets carla-like ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from drake_cert.config import load_conditions
from drake_cert.errors import ModelNotFoundError
from drake_cert.experiments.perception_eval import (
    CertifySettings,
    certify_classifier,
    select_frames,
    summarize_classification,
)
from drake_cert.io import atomic_write_text, provenance
from drake_cert.perception.datasets import load_split
from drake_cert.perception.models import file_sha256, load_model, model_path, sigma_tag

PRESETS = ("carla-like", "rtk-like", "robotcar-like")
SIGMAS = (0.0, 0.25, 0.5, 1.0)


def run_cell(preset: str, sigma: float, args: argparse.Namespace, table) -> dict:
    """One (preset, sigma) cell: the summaries of perception_eval.certify_classifier."""
    model = load_model(preset, "classify", sigma, args.models)
    frames = args.base_frames if sigma == 0 else args.frames
    k = len(table.preset(preset).labels)
    test = load_split(preset, "test", seed=0, size=int(model.meta.get("image_size", 64)),
                      frames_per_class=-(-frames // k))
    idx = select_frames(test.labels, frames, args.seed)
    data = (test.images[idx], test.labels[idx], test.stiffness_n_per_rad[idx])
    base = CertifySettings(preset=preset, sigma=sigma, n0=args.n0, n=args.n, alpha=args.alpha,
                           frames=frames, batch_size=args.batch_size, seed=args.seed,
                           compile=args.compile, attack_steps=args.attack_steps)
    cell = {"preset": preset, "sigma": sigma, "frames": frames,
            "model_sha256": file_sha256(model_path(preset, "classify", sigma, args.models))}
    start = time.perf_counter()
    if sigma == 0:
        for kind in ("sa", "ea"):
            s = dataclasses.replace(base, attack=kind, eps=args.attack_eps)
            records, summary = certify_classifier(model, *data, list(test.label_names), table, s)
            cell[kind] = summary
            cell[f"{kind}_records"] = records
        either = [a["prediction"] == a["label"] and b["prediction"] == b["label"]
                  for a, b in zip(cell["sa_records"], cell["ea_records"], strict=True)]
        cell["either_accuracy"] = sum(either) / len(either)
    else:
        s = dataclasses.replace(base, attack="sa", eps=args.interval_eps)
        records, summary = certify_classifier(model, *data, list(test.label_names), table, s,
                                              progress=_progress(f"{preset} sigma={sigma:g}"))
        cell["sa"] = summary
        cell["sa_records"] = records
    cell["seconds"] = time.perf_counter() - start
    return cell


def _progress(desc):
    from tqdm import tqdm

    return lambda it: tqdm(it, desc=desc, file=sys.stderr, leave=False)


def _fmt(value, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _settings(summary: dict) -> CertifySettings:
    """The settings a stored summary was made with (for recomputing its metrics)."""
    keys = ("preset", "sigma", "task", "attack", "eps", "n0", "n", "alpha", "frames")
    return CertifySettings(**{k: summary[k] for k in keys})


def render(cells: dict, args: argparse.Namespace) -> str:
    lines = [
        "# Perception: accuracy, attacks, certificates",
        "",
        f"Shipped classifiers, test frames chosen round-robin over labels (seed {args.seed}). "
        f"sigma = 0 is the base model f ({args.base_frames} frames, PGD: L2, eps = "
        f"{args.attack_eps}, {args.attack_steps} steps, against f). sigma > 0 is the smoothed "
        f"g ({args.frames} frames per cell; n0 = {args.n0}, n = {args.n}, alpha = "
        f"{args.alpha}): radii at the clean frame (abstain = 0), in L2 pixel units ([0, 1] "
        f"pixels); the run-time interval is taken at the frame attacked by a SmoothAdv "
        f"stability attack at eps = {args.interval_eps} (8 noise draws per step, "
        f"{args.attack_steps} steps), with budget eps = {args.interval_eps}.",
        "",
        "| preset | sigma | frames | clean acc. | acc. under PGD (SA / EA / either) | "
        "mean R_S(a) (share S(a) = all) | mean R_{a} | abstain | interval width (kN/rad) | "
        "coverage (all / clean g right) | envelope rate |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for preset in args.presets:
        for sigma in SIGMAS:
            cell = cells.get((preset, sigma))
            if cell is None:
                lines.append(f"| {preset} | {sigma:g} | - | not run (no model yet) "
                             "| | | | | | | |")
                continue
            if sigma == 0:
                sa, ea = cell["sa"], cell["ea"]
                lines.append(
                    f"| {preset} | 0 | {cell['frames']} | {sa['clean_accuracy']:.2f} | "
                    f"{sa['accuracy']:.2f} / {ea['accuracy']:.2f} / "
                    f"{cell['either_accuracy']:.2f} (eps {args.attack_eps}) | - | - | - | - | - "
                    "| - |")
            else:
                s = summarize_classification(cell["sa_records"], _settings(cell["sa"]))
                lines.append(
                    f"| {preset} | {sigma:g} | {cell['frames']} | {s['clean_accuracy']:.2f} | "
                    f"{s['accuracy']:.2f} (SA on g, eps {args.interval_eps}) | "
                    f"{_fmt(s['mean_radius'], 3)} ({s['unbounded_radius_rate']:.2f}) | "
                    f"{s['mean_radius_label']:.3f} | "
                    f"{s['clean_abstain_rate']:.2f} | {s['interval_width_mean'] / 1e3:.1f} | "
                    f"{s['interval_coverage']:.2f} / {_fmt(s['coverage_given_clean_right'])} | "
                    f"{s['envelope_rate']:.2f} |")
    lines += ["", "R_S(a): certified radius of the safe set of the predicted label a (paper "
              "Prop. 1, made sound); when S(a) holds every label (a is the grippiest label) it "
              "is infinite, so the mean is over the other frames and the share of infinite ones "
              "is given in brackets. R_{a}: Cohen's radius of the label alone (joint bounds).",
              "", "Interval: the narrowest contiguous label range with certified radius "
              "> eps at the observed frame (DESIGN 3); envelope when none qualifies. Coverage: "
              "share of frames whose true stiffness lies in it."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=list(PRESETS))
    parser.add_argument("--sigmas", nargs="+", type=float, default=list(SIGMAS))
    parser.add_argument("--frames", type=int, default=20, help="frames per smoothed cell")
    parser.add_argument("--base-frames", type=int, default=100, help="frames for sigma = 0")
    parser.add_argument("--n0", type=int, default=100)
    parser.add_argument("--n", type=int, default=10_000)
    parser.add_argument("--alpha", type=float, default=0.001)
    parser.add_argument("--batch-size", type=int, default=1000)
    parser.add_argument("--attack-eps", type=float, default=0.5)
    parser.add_argument("--interval-eps", type=float, default=0.25)
    parser.add_argument("--attack-steps", type=int, default=20)
    parser.add_argument("--compile", default="on", choices=("auto", "on", "off"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="results")
    parser.add_argument("--models", default=None, help="model folder (default: shipped)")
    args = parser.parse_args()

    table = load_conditions()
    out = Path(args.out)
    cells = {}
    for preset in args.presets:
        for sigma in SIGMAS:
            path = out / "perception" / f"{preset}_sigma{sigma_tag(sigma)}.json"
            if path.exists():
                cells[(preset, sigma)] = json.loads(path.read_text())["cell"]
                continue
            if sigma not in args.sigmas:
                continue
            try:
                cell = run_cell(preset, sigma, args, table)
            except ModelNotFoundError as e:
                print(f"skipped: {e}", file=sys.stderr)
                continue
            atomic_write_text(path, json.dumps({"cell": cell, "provenance": provenance(
                args.seed)}, indent=1))
            cells[(preset, sigma)] = cell
            print(f"done {preset} sigma={sigma:g} in {cell['seconds']:.0f} s", file=sys.stderr)
    text = render(cells, args)
    atomic_write_text(out / "perception_table.md", text)
    print(text)


if __name__ == "__main__":
    main()
