"""Cost of `drake-cert reproduce` per frame and per stage: fixed-n certificates in torch (the
run before sequential decisions) against the default (sequential decisions where a cell is read
only as a decision, ONNX Runtime where installed), side by side on the same frames.

Runs the reproduction's own worker (``FrameWorker``: the Diagram's attacker, perception and
interval blocks, then the episodes) on one thread, as one Ray worker does, at the default size
(n = 10,000, every pipeline, fp32). The calibrations (h's betas, g's robust conformal
calibrations) are computed first, once, with the default backend, timed, and given to both
variants. Each stage's CPU time is summed over the frames: attacks (``Attacker.perturb``),
certificates (``PerceptionSmoothing.perceive``) and episodes (``EpisodeRunner.outcome``).

With ``--cells K`` it also prints the K costliest cells of the default variant (CPU seconds a
frame per stage, and how the cell is decided); ``--default-only`` skips the fixed-n variant.

Usage: python benchmarks/bench_reproduce_frame.py [--preset robotcar-like] [--positions 0 1]
       [--cells 12] [--default-only]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections import defaultdict

from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.experiments.calibrations import calibration_beta, conformal_calibration
from drake_cert.experiments.episodes import EpisodeRunner
from drake_cert.experiments.reproduce import FrameWorker
from drake_cert.experiments.reproduce_config import FrameTask, ReproduceConfig, run_model
from drake_cert.synthesis.table import synthesize_table
from drake_cert.systems.attacker import Attacker
from drake_cert.systems.perception_smoothing import PerceptionSmoothing
from drake_cert.threads import torch_threads

STAGES = {"attacks": (Attacker, "perturb"), "certificates": (PerceptionSmoothing, "perceive"),
          "episodes": (EpisodeRunner, "outcome")}


def timed(spent: dict, per_cell: dict):
    """Wrap each stage's method so that its time adds to ``spent[stage]`` and to
    ``per_cell[(stage, cell)]`` (the cell whose blocks the worker fetched last); returns an
    undo."""
    originals = {name: getattr(cls, name) for cls, name in STAGES.values()}
    originals["blocks"] = FrameWorker.blocks
    current = [None]

    def blocks(self, preset, cell):
        current[0] = cell
        return originals["blocks"](self, preset, cell)
    FrameWorker.blocks = blocks
    for stage, (cls, name) in STAGES.items():
        def wrapper(self, *a, _original=originals[name], _stage=stage, **k):
            start = time.process_time()
            try:
                return _original(self, *a, **k)
            finally:
                used = time.process_time() - start
                spent[_stage] += used
                per_cell[(_stage, current[0])] += used
        setattr(cls, name, wrapper)

    def undo():
        FrameWorker.blocks = originals["blocks"]
        for cls, name in STAGES.values():
            setattr(cls, name, originals[name])
    return undo


def calibrate(config: ReproduceConfig, preset: str) -> tuple[dict, dict, float]:
    """h's betas and g's conformal calibrations of ``preset`` at every sigma, and the CPU
    seconds they took."""
    conditions = load_conditions()
    start = time.process_time()
    betas = {(preset, s): calibration_beta(config, preset, s,
                                           run_model(config, preset, "regress", s), conditions)
             for s in config.sigmas}
    conformal = {(preset, s): conformal_calibration(config, preset, s, conditions)
                 for s in config.sigmas}
    return betas, conformal, time.process_time() - start


def run_frames(config, positions, preset, designs, betas, conformal):
    """CPU seconds per stage over the frames and the total; CPU seconds per (stage, cell); the
    worker (its decision rule names how each cell is decided)."""
    spent: dict = defaultdict(float)
    per_cell: dict = defaultdict(float)
    undo = timed(spent, per_cell)
    try:
        worker = FrameWorker(config, betas=betas, designs=designs, conformal=conformal)
        start = time.process_time()
        for position in positions:
            worker(FrameTask(preset, position))
        spent["total"] = time.process_time() - start
    finally:
        undo()
    return dict(spent), dict(per_cell), worker


def main() -> None:
    from drake_cert.certification.sampler import retain_freed_memory

    retain_freed_memory()  # as the long-running commands run
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="robotcar-like")
    parser.add_argument("--positions", type=int, nargs="+", default=[0, 1],
                        help="which of the preset's frames")
    parser.add_argument("--cells", type=int, default=0,
                        help="print the default variant's K costliest cells")
    parser.add_argument("--default-only", action="store_true",
                        help="skip the fixed-n torch variant")
    args = parser.parse_args()

    designs = synthesize_table(load_vehicle(), load_conditions(), load_settings())
    after = ReproduceConfig(presets=(args.preset,), precision="fp32")
    before = dataclasses.replace(after, backend="torch", decisions="fixed")
    with torch_threads(1):  # as the executors run a worker
        betas, conformal, cal_s = calibrate(after, args.preset)
        print(f"{args.preset}, frames {args.positions}, one thread, fp32, default size "
              f"(n = {after.n}); calibrations ({after.backend}): {cal_s:.0f} CPU-s for "
              f"{len(after.sigmas)} sigmas")
        print(f"{'variant':<34s} {'attacks':>9s} {'certificates':>13s} {'episodes':>9s} "
              f"{'frame total':>12s} {'per frame':>10s}")
        variants = [("fixed n, torch (before)", before)] * (not args.default_only)
        for name, config in (*variants, (f"sequential, {after.backend} (default)", after)):
            s, per_cell, worker = run_frames(config, args.positions, args.preset, designs,
                                             betas, conformal)
            print(f"{name:<34s} {s['attacks']:8.1f}s {s['certificates']:12.1f}s "
                  f"{s['episodes']:8.1f}s {s['total']:11.1f}s "
                  f"{s['total'] / len(args.positions):9.1f}s")
        if args.cells:
            print(f"\nthe {args.cells} costliest cells of the default variant, CPU-s a frame:")
            top = sorted(per_cell.items(), key=lambda kv: -kv[1])[:args.cells]
            for (stage, cell), used in top:
                rule = worker.decision_rule(args.preset, cell)
                print(f"{used / len(args.positions):7.2f}  {stage:<12s} {cell}  {rule}")


if __name__ == "__main__":
    main()
