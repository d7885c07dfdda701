"""Cost of one frame of `drake-cert reproduce`, and how much of it is certificate sampling.

Runs the reproduction's own worker (``FrameWorker``: the Diagram's attacker, perception and
interval blocks, then the episodes) on one frame, on one thread as one Ray worker does, at the
default n = 10,000 and again at n = 1,000. A frame's time is fixed work (attacks, episodes,
loading) plus sampling that grows with n, so the two timings give both parts: the sampling
rate ``certificates x 9,000 / (t(10,000) - t(1,000))`` and the sampling share of the frame.
Classification cells only (``regression=False``): h's cells need the beta calibration first
(minutes), and the README's per-frame figures count them besides. bfloat16 (the default) and
float32 side by side in the same run.

Usage: python benchmarks/bench_reproduce_frame.py [--preset robotcar-like] [--position 0]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.experiments.reproduce import FrameWorker
from drake_cert.experiments.reproduce_config import FrameTask, ReproduceConfig
from drake_cert.synthesis.table import synthesize_table
from drake_cert.threads import torch_threads


def time_frame(config: ReproduceConfig, task: FrameTask, designs) -> tuple[float, int]:
    """Seconds for one frame on a fresh worker (models loaded on first use), and its
    number of certificates (rows whose interval came from a smoothed model)."""
    with torch_threads(1):  # as the executors run a worker
        worker = FrameWorker(config, designs=designs)
        start = time.perf_counter()
        rows = worker(task)
    return time.perf_counter() - start, sum(r["pipeline"] == "g" for r in rows)


def main() -> None:
    from drake_cert.certification.sampler import retain_freed_memory

    retain_freed_memory()  # as the long-running commands run (README figures)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="robotcar-like")
    parser.add_argument("--position", type=int, default=0, help="which of the preset's frames")
    args = parser.parse_args()

    designs = synthesize_table(load_vehicle(), load_conditions(), load_settings())
    task = FrameTask(args.preset, args.position)
    print(f"one frame of {args.preset} (position {args.position}), one thread, "
          "classification cells only")
    print(f"{'precision':>9s} {'t(n=10,000)':>12s} {'t(n=1,000)':>11s} {'certificates':>12s} "
          f"{'samples/s':>10s} {'sampling share':>15s}")
    for precision in ("bf16", "fp32"):
        base = ReproduceConfig(presets=(args.preset,), regression=False, conformal=False,
                               precision=precision)
        full, certificates = time_frame(base, task, designs)
        small, _ = time_frame(dataclasses.replace(base, n=1000), task, designs)
        extra = base.n - 1000  # samples each certificate draws beyond the small run's
        rate = certificates * extra / (full - small)
        sampling = (full - small) * (base.n0 + base.n) / extra  # all of the n0 + n samples
        print(f"{precision:>9s} {full:10.1f} s {small:9.1f} s {certificates:12d} "
              f"{rate:10.0f} {100 * sampling / full:14.0f}%")


if __name__ == "__main__":
    main()
