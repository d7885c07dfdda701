"""How informative the median-smoothed regressor h is: per preset and model, its run-time
interval's width, coverage of the true stiffness and certified share, clean and attacked
(DESIGN 3.5).

For each preset and each model folder given: the conformal beta is calibrated on the
calibration split (``--calibration-per-class`` frames a label, ``calibrate_conformal``, n =
``--n`` samples a frame); then on the first ``--test-per-class`` test frames of each label,
clean and under each ``--attacks`` attack at budget ``--eps`` (L2 PGD against h's median
surrogate, ``--attack-steps`` steps, 8 noise draws a step), the run-time interval
``[lower - beta, upper + beta]`` at eps (``certify_interval``, n samples, alpha 0.001).
"Certified" counts the frames whose bounds satisfy a candidate of ``median_candidates``: the
run-time interval lies inside the stiffness hull of a contiguous label range narrower than the
envelope (the designs h selects between), as the drive's sequential decision asks. Coverage
carries its 95 % Clopper-Pearson interval. Models run in torch, fp32, ``--threads`` threads;
every noise stream is seeded, so the same command prints the same table.

Run: ``.venv/bin/python benchmarks/regressor_intervals.py [--presets carla-like ...]
[--models point=DIR band=DIR] [--alpha-c 0.01] [--calibration-per-class 400] [--jobs 2]
[--out FILE.md]`` (default: the shipped models; about 8 min a preset and model at 400
calibration frames a label, on one core of an Intel Xeon).
"""

import argparse
import sys
import time
from types import SimpleNamespace

import numpy as np
import torch

from drake_cert.certification.attacks import AttackSettings, attack
from drake_cert.certification.intervals import median_candidates, runtime_interval
from drake_cert.certification.regressor import MedianSmoothedRegressor, calibrate_conformal
from drake_cert.certification.sampler import CalibrationSampling
from drake_cert.config import load_conditions
from drake_cert.experiments.perception_eval import clopper_pearson_interval
from drake_cert.io import atomic_write_text
from drake_cert.perception.datasets import load_split
from drake_cert.perception.models import load_model, training_of


def label_range_designs(table, preset: str) -> list:
    """The stiffness hull of every contiguous label range (what the design table holds)."""
    return [SimpleNamespace(stiffness_lo_n_per_rad=lo, stiffness_hi_n_per_rad=hi, speed_mps=0.0)
            for lo, hi in (table.hull(r) for r in table.contiguous_ranges(preset))]


def first_per_label(labels: np.ndarray, count: int) -> np.ndarray:
    return np.concatenate([np.flatnonzero(labels == k)[:count] for k in np.unique(labels)])


def evaluate(preset: str, root: str | None, args, table) -> dict:
    """Beta and, per attack, per-frame (label, width, covered, certified) of one model."""
    model = load_model(preset, "regress", args.sigma, root)
    smooth = MedianSmoothedRegressor(model, args.sigma)
    cal = load_split(preset, "calibration", frames_per_class=args.calibration_per_class,
                     conditions=table)
    start = time.perf_counter()
    name = root or "shipped"
    print(f"regressor_intervals: {preset} {name}: calibrating on {len(cal)} frames",
          file=sys.stderr)
    calib = calibrate_conformal(
        smooth, cal.images, cal.stiffness_n_per_rad.tolist(), cal.labels.tolist(),
        sampling=CalibrationSampling(n=calibration_n(args), batch_size=calibration_n(args),
                                     seed=args.seed),
        alpha_c=args.alpha_c)
    envelope = table.hull(table.preset(preset).labels)
    candidates = median_candidates(label_range_designs(table, preset), calib.beta, envelope)
    test = load_split(preset, "test", conditions=table)
    idx = first_per_label(np.asarray(test.labels), args.test_per_class)
    frames, truth = test.images[idx], test.stiffness_n_per_rad[idx].double().numpy()
    out = {"beta": calib.beta, "betas": calib.betas, "labels": np.asarray(test.labels)[idx],
           "label_names": test.label_names, "method": training_of(model).get("method", "?"),
           "cells": {}}
    for kind in ("none", *args.attacks):
        print(f"regressor_intervals: {preset} {name}: {kind}, {len(idx)} test frames "
              f"({time.perf_counter() - start:.0f} s)", file=sys.stderr)
        x = frames if kind == "none" else attack(
            model, frames, kind, AttackSettings(eps=args.eps, steps=args.attack_steps,
                                                noise_draws=8, seed=args.seed),
            task="regress", sigma=args.sigma, frame_seeds=[int(i) for i in idx])
        rows = []
        for j, i in enumerate(idx):
            _, lower, upper = smooth.certify_interval(x[j], args.eps, args.n, 0.001, args.n,
                                                      seed=args.seed + int(i))
            lo, hi = runtime_interval(lower, upper, calib.beta, envelope)
            rows.append((hi - lo, lo <= truth[j] <= hi,
                         any(lower >= a and upper <= b for a, b in candidates)))
        out["cells"][kind] = np.array(rows, dtype=float)
    print(f"regressor_intervals: {preset} {name}: done in {time.perf_counter() - start:.0f} s",
          file=sys.stderr)
    return out


def calibration_n(args) -> int:
    """Samples a calibration frame: ``--calibration-n``, else the certificate's n."""
    return args.calibration_n or args.n


def _evaluate_one(job) -> dict:
    preset, root, args = job
    torch.set_num_threads(args.threads)
    return evaluate(preset, root, args, load_conditions())


def cell_text(rows: np.ndarray) -> str:
    k, n = int(rows[:, 1].sum()), len(rows)
    lo, hi = clopper_pearson_interval(k, n)
    return (f"{rows[:, 0].mean() / 1e3:.1f}; {k}/{n} [{lo:.2f}, {hi:.2f}]; "
            f"{rows[:, 2].mean():.2f}")


def markdown(results: dict, args) -> str:
    lines = [
        "# The median-smoothed regressor's run-time interval, per preset and model",
        "",
        f"Made by `python benchmarks/regressor_intervals.py {' '.join(sys.argv[1:])}` "
        f"(torch fp32, one thread a process). Settings: sigma = {args.sigma:g}, eps = "
        f"{args.eps:g}, n = {args.n} samples a frame (certificate), {calibration_n(args)} "
        "(calibration), alpha = "
        f"0.001, alpha_c = {args.alpha_c:g}, alpha_m = 0.001 (guarantee "
        f"{1 - 0.002 - args.alpha_c:.3f}); {args.calibration_per_class} calibration frames a "
        f"label; the first {args.test_per_class} test frames of each label; attacks: L2 PGD, "
        f"{args.attack_steps} steps, 8 noise draws a step. Cells: mean width (kN/rad); "
        "coverage of the true stiffness [95% Clopper-Pearson]; share certified (the interval "
        "inside a label range's stiffness hull narrower than the envelope).",
        "",
    ]
    for preset, models in results.items():
        lines += [f"## {preset}", "",
                  "| model (method) | beta per label (kN/rad) | run-time beta | attack | all "
                  "labels | " + " | ".join(next(iter(models.values()))["label_names"]) + " |",
                  "|---|---|---|---|---|" + "---|" * len(
                      next(iter(models.values()))["label_names"])]
        for name, r in models.items():
            betas = ", ".join(f"{v / 1e3:.1f}" for _, v in sorted(r["betas"].items()))
            for kind, rows in r["cells"].items():
                per = [cell_text(rows[r["labels"] == k])
                       for k in range(len(r["label_names"]))]
                lines.append(f"| {name} ({r['method']}) | {betas} | {r['beta'] / 1e3:.1f} | "
                             f"{kind} | {cell_text(rows)} | " + " | ".join(per) + " |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["carla-like", "rtk-like",
                                                         "robotcar-like"])
    parser.add_argument("--models", nargs="+", default=["shipped"],
                        help="NAME=DIR model folders to compare ('shipped': the shipped ones)")
    parser.add_argument("--calibration-per-class", type=int, default=100)
    parser.add_argument("--test-per-class", type=int, default=40)
    parser.add_argument("--alpha-c", type=float, default=0.01)
    parser.add_argument("--sigma", type=float, default=0.25, help="the models' noise level")
    parser.add_argument("--eps", type=float, default=0.25)
    parser.add_argument("--n", type=int, default=500)
    parser.add_argument("--calibration-n", type=int, default=None,
                        help="samples a calibration frame (default: --n)")
    parser.add_argument("--attacks", nargs="*", default=["sa", "ea"])
    parser.add_argument("--attack-steps", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads a process")
    parser.add_argument("--jobs", type=int, default=1,
                        help="processes, one (preset, model) pair each (default 1)")
    parser.add_argument("--out", default=None, help="write the table here (Markdown)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    table = load_conditions()
    roots = {}
    for spec in args.models:
        name, _, root = spec.partition("=")
        roots[name] = root or (None if name == "shipped" else name)
    pairs = [(p, name) for p in args.presets for name in roots]
    if args.jobs > 1:  # one process a (preset, model); every stream is seeded: same numbers
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(args.jobs) as pool:
            done = list(pool.map(_evaluate_one, [(p, roots[name], args) for p, name in pairs]))
    else:
        done = [evaluate(p, roots[name], args, table) for p, name in pairs]
    results: dict = {}
    for (p, name), r in zip(pairs, done, strict=True):
        results.setdefault(p, {})[name] = r
    text = markdown(results, args)
    print(text)
    if args.out:
        atomic_write_text(args.out, text + "\n")


if __name__ == "__main__":
    main()
