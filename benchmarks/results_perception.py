"""Perception results table: run-time stiffness intervals of f, g and h, clean and
attacked, on the same frames at the same budgets (drake_cert.experiments.perception_table).

Cells are stored as JSON under --store as soon as each is done (an interrupted run resumes);
writes --out (Markdown) and the same rows as JSON beside it (.json), with provenance.

Usage: python benchmarks/results_perception.py [--presets carla-like ...] [--frames 300]
       [--tasks classify regress] [--n 1000] [--sigma 0.25] [--budgets 0.25 0.5]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from tqdm import tqdm

from drake_cert.config import load_conditions
from drake_cert.experiments.perception_table import (
    PRESETS,
    CellReport,
    CellStore,
    TableSettings,
    render,
    rows,
    run_preset,
)
from drake_cert.io import atomic_write_text, provenance


def main() -> None:
    from drake_cert.certification.sampler import retain_freed_memory

    retain_freed_memory()  # as the long-running commands run (docs/results.md figures)
    d = TableSettings()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=list(PRESETS))
    parser.add_argument("--tasks", nargs="+", default=list(d.tasks))
    parser.add_argument("--frames", type=int, default=d.frames)
    parser.add_argument("--sigma", type=float, default=d.sigma)
    parser.add_argument("--budgets", nargs="+", type=float, default=list(d.budgets))
    parser.add_argument("--n0", type=int, default=d.n0)
    parser.add_argument("--n", type=int, default=d.n)
    parser.add_argument("--calibration-n", type=int, default=d.calibration_n)
    parser.add_argument("--conformal-per-class", type=int, default=d.conformal_per_class)
    parser.add_argument("--regression-per-class", type=int, default=d.regression_per_class)
    parser.add_argument("--attack-steps", type=int, default=d.attack_steps)
    parser.add_argument("--precision", default="auto", choices=("auto", "fp32", "bf16"))
    parser.add_argument("--seed", type=int, default=d.seed)
    parser.add_argument("--store", default="results/perception_table")
    parser.add_argument("--out", default="docs/perception_table.md")
    parser.add_argument("--models", default=None, help="model folder (default: shipped)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    ts = dataclasses.replace(
        d, frames=args.frames, sigma=args.sigma, budgets=tuple(args.budgets), n0=args.n0,
        n=args.n, calibration_n=args.calibration_n, conformal_per_class=args.conformal_per_class,
        regression_per_class=args.regression_per_class, attack_steps=args.attack_steps,
        precision=args.precision, seed=args.seed, tasks=tuple(args.tasks))
    table = load_conditions()
    store = CellStore(args.store)
    start = time.perf_counter()
    all_rows = {}
    for preset in args.presets:
        report = CellReport(
            progress=lambda desc: lambda it: tqdm(it, desc=desc, file=sys.stderr, leave=False),
            log=lambda msg: print(msg, file=sys.stderr, flush=True))
        cells = run_preset(preset, ts, table, store, models=args.models, report=report)
        all_rows[preset] = rows(cells, ts)
    seconds = sum(c["seconds"] for p in args.presets for c in _cells(store, p))
    command = " ".join(["python", *sys.argv])
    header = [f"Made by `{command}` (compute {seconds / 60:.0f} min on one CPU thread, summed "
              f"over cells; this call {(time.perf_counter() - start) / 60:.0f} min).", ""]
    out = Path(args.out)
    atomic_write_text(out, render(all_rows, ts, header))
    atomic_write_text(out.with_suffix(".json"), json.dumps(
        {"settings": dataclasses.asdict(ts), "rows": all_rows, "compute_seconds": seconds,
         "provenance": provenance(args.seed)}, indent=1))
    print(out.read_text())


def _cells(store: CellStore, preset: str) -> list[dict]:
    folder = store.root / preset
    return [json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))] \
        if folder.exists() else []


if __name__ == "__main__":
    main()
