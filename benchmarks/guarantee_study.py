"""The drive-level guarantee over seeds: every shipped scenario (or the ones named), each seed,
unattacked and under SA at its certified budget, with the shipped defaults (docs/design.md 6.2).

Each drive is ``drake-cert drive --scenario S --seed K --attack A --json`` through the library
(the design table synthesized once from the shipped vehicle, settings and conditions); one row
per drive: speed, envelope share, abstentions, samples a tick, time unprotected, lane, and what
the guarantee rests on (planned ticks, per-tick miss bound, m, j, guarantee_failure_bound).
Writes the rows to a CSV atomically and prints a Markdown table per scenario and attack
(ranges over the seeds). fp32 (``DRAKE_CERT_PRECISION=fp32``); two drives at once, one per core.

Run: ``.venv/bin/python benchmarks/guarantee_study.py [--scenarios dry_to_snow,...]
[--seeds 1-5] [--base dry_to_snow] [--out docs/seed_study/guarantee_seeds_1-5.csv]`` (about
40 min for all seven scenarios on 2 cores). The CSV is rewritten after every drive.
"""

from __future__ import annotations

import argparse
import csv
import io
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("DRAKE_CERT_PRECISION", "fp32")

FIELDS = ("scenario", "seed", "attack", "pipeline", "mean_speed_mps", "envelope_time_fraction",
          "abstention_fraction", "certified_wrong_fraction", "mean_samples_per_tick",
          "time_unprotected_s", "design_covers_true_fraction", "left_lane", "peak_abs_e1_m",
          "camera_ticks", "planned_ticks", "frame_miscoverage", "looks_per_side",
          "tolerated_wrong_frames", "guarantee_failure_bound", "wall_s")


def seed_range(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def drive_one(name: str, seed: int, attack: str, pipeline: str, designs) -> dict:
    from drake_cert.config import load_conditions, load_settings, load_vehicle
    from drake_cert.systems.driving import drive_scenario, with_overrides
    from drake_cert.systems.scenario import load_scenario

    os.environ["OMP_NUM_THREADS"] = "1"
    sc = with_overrides(load_scenario(name), seed=seed, attack=attack, pipeline=pipeline)
    start = time.perf_counter()
    s = drive_scenario(sc, vehicle=load_vehicle(), settings=load_settings(),
                       conditions=load_conditions(), designs=designs).summary
    row = {k: s.get(k) for k in FIELDS if k in s}
    row.update(scenario=name, seed=seed, attack=attack, pipeline=pipeline,
               wall_s=round(time.perf_counter() - start, 1))
    return row


def fmt_range(values, spec="{:.2f}", scale=1.0, suffix="") -> str:
    lo, hi = min(values) * scale, max(values) * scale
    a, b = spec.format(lo), spec.format(hi)
    return f"{a}{suffix}" if a == b else f"{a}-{b}{suffix}"


def summary(rows: list[dict]) -> str:
    out = ["| scenario | attack | pipeline | mean speed (m/s) | envelope in force (time) | "
           "abstaining ticks | samples a tick | time unprotected | left lane | "
           "guarantee_failure_bound |", "|---|---|---|---|---|---|---|---|---|---|"]
    keys = sorted({(r["scenario"], r["attack"], r["pipeline"]) for r in rows})
    for name, attack, pipeline in keys:
        group = [r for r in rows if (r["scenario"], r["attack"], r["pipeline"]) ==
                 (name, attack, pipeline)]
        cert = pipeline == "certified"
        out.append(
            f"| {name} | {attack} | {pipeline} | "
            f"{fmt_range([r['mean_speed_mps'] for r in group])} | "
            + (f"{fmt_range([r['envelope_time_fraction'] for r in group], '{:.1f}', 100, '%')} | "
               f"{fmt_range([r['abstention_fraction'] for r in group], '{:.1f}', 100, '%')} | "
               f"{sum(r['mean_samples_per_tick'] for r in group) / len(group):.0f} | "
               f"{max(r['time_unprotected_s'] for r in group):.2f} s | " if cert else
               "- | - | - | - | ")
            + f"{sum(bool(r['left_lane']) for r in group)} of {len(group)} | "
            + (f"{max(r['guarantee_failure_bound'] for r in group):.4f} |" if cert else "- |"))
    return "\n".join(out)


def write_rows(path: Path, rows: list[dict]) -> None:
    """The rows as CSV, written atomically."""
    from drake_cert.io import atomic_write_text

    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=FIELDS)
    writer.writeheader()
    for r in rows:
        writer.writerow({k: (round(v, 6) if isinstance(v, float) else v)
                         for k, v in r.items() if k in FIELDS})
    atomic_write_text(path, buf.getvalue())


def main() -> None:
    from drake_cert.config import load_conditions, load_settings, load_vehicle
    from drake_cert.synthesis.table import synthesize_table
    from drake_cert.systems.scenario import SHIPPED_SCENARIOS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", default=",".join(SHIPPED_SCENARIOS))
    parser.add_argument("--seeds", default="1-5")
    parser.add_argument("--attacks", default="none,sa")
    parser.add_argument("--base", default="",
                        help="comma-separated scenarios whose base pipeline also drives "
                             "unattacked (the speed reference); 'all' for every one")
    parser.add_argument("--out", default="docs/seed_study/guarantee_seeds_1-5.csv")
    args = parser.parse_args()
    names = [n for n in args.scenarios.split(",") if n]
    unknown = [n for n in names if n not in SHIPPED_SCENARIOS]
    if unknown:
        sys.exit(f"unknown scenario(s) {unknown}; shipped: {', '.join(SHIPPED_SCENARIOS)}")
    designs = synthesize_table(load_vehicle(), load_conditions(), load_settings())
    jobs = [(n, s, a, "certified") for n in names for a in args.attacks.split(",")
            for s in seed_range(args.seeds)]
    base = names if args.base == "all" else [n for n in args.base.split(",") if n]
    jobs = [(n, s, "none", "base") for n in base for s in seed_range(args.seeds)] + jobs
    rows = []
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = [pool.submit(drive_one, *job, designs) for job in jobs]
        for job, fut in zip(jobs, futures, strict=True):
            row = fut.result()
            rows.append(row)
            write_rows(out, rows)  # after every drive: an interrupted study keeps its rows
            print(f"{time.perf_counter() - start:7.0f} s  {job}: {row['mean_speed_mps']:.2f} m/s,"
                  f" unprotected {row.get('time_unprotected_s')}, bound "
                  f"{row.get('guarantee_failure_bound')}", file=sys.stderr, flush=True)
    print(summary(rows))
    print(f"\n{len(rows)} drives in {time.perf_counter() - start:.0f} s; rows in {out}")


if __name__ == "__main__":
    main()
