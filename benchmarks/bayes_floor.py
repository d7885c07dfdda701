"""How much of a classifier's own-label tail the generator forces: the known-scene oracle
(``drake_cert.perception.bayes_floor``) beside the shipped model, on the same frames.

Per true label and severity quarter (q1 grippiest), for the oracle and for the model: the
tail (share of frames whose own label gets under half the noisy votes, the column the
training sweep ranks by) and the noisy error (one minus the mean own-label share). The
oracle is told each frame's scene, so its noisy error is a lower bound on any base
classifier's, up to its severity grid and draws (docs/design.md 3.2). Frames come from their
own seeds (not the training or test splits), torch fp32 for the model, ``--threads``.

Run: ``.venv/bin/python benchmarks/bayes_floor.py [--preset carla-like] [--sigma 1]
[--frames-per-class 100] [--grid 16] [--draws 400] [--n 1000] [--model FILE]``
(``--n 0``: the oracle alone; 157-190 s a preset at the defaults on one Intel Xeon thread;
progress on stderr, the table on stdout).
"""

import argparse
import sys
import time

import numpy as np
import torch

from drake_cert.certification.classifier import SmoothedClassifier
from drake_cert.certification.sampler import make_generator
from drake_cert.config import load_conditions
from drake_cert.perception.bayes_floor import known_scene_votes, oracle_frames
from drake_cert.perception.models import load_model, load_model_file
from drake_cert.rng import torch_generator

QUARTERS = 4
TAIL_SHARE = 0.5


def _cells(rows: list[tuple[int, int, float, float]], lab: int, quarter: int | None,
           column: int) -> str:
    shares = np.array([r[column] for r in rows
                       if r[0] == lab and (quarter is None or r[1] == quarter)])
    if len(shares) == 0:
        return "- | -"
    return f"{(shares < TAIL_SHARE).mean():.1%} | {1 - shares.mean():.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="carla-like")
    parser.add_argument("--sigma", type=float, default=1.0)
    parser.add_argument("--frames-per-class", type=int, default=100)
    parser.add_argument("--grid", type=int, default=16, help="oracle severity grid points")
    parser.add_argument("--draws", type=int, default=400, help="oracle noise draws a frame")
    parser.add_argument("--n", type=int, default=1000, help="model samples a frame (0: none)")
    parser.add_argument("--model", default=None, help="a candidate classifier file")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    conditions = load_conditions()
    names = [c.name for c in conditions.preset_conditions(args.preset)]
    classifier = None
    if args.n > 0:
        model = (load_model_file(args.model) if args.model
                 else load_model(args.preset, "classify", args.sigma))
        classifier = SmoothedClassifier(model, len(names), args.sigma)
    rows = []  # (label, quarter, oracle share, model share)
    start = time.perf_counter()
    total = args.frames_per_class * len(names)
    frames = oracle_frames(conditions, args.preset, frames_per_class=args.frames_per_class,
                           seed=args.seed, grid_points=args.grid)
    for i, frame in enumerate(frames):
        votes = known_scene_votes(frame, args.sigma, args.draws,
                                  torch_generator(args.seed * 1_000_003 + i))
        model_share = float("nan")
        if classifier is not None:
            counts = classifier.sample_counts(frame.image, args.n, 250,
                                              make_generator(args.seed + i, classifier.device))
            model_share = counts[frame.label] / args.n
        quarter = min(int(frame.severity * QUARTERS), QUARTERS - 1)
        rows.append((frame.label, quarter, votes[frame.label] / args.draws, model_share))
        if (i + 1) % 50 == 0 or i + 1 == total:
            print(f"bayes_floor: {i + 1}/{total} frames, {time.perf_counter() - start:.0f} s",
                  file=sys.stderr)
    what = (f"{args.model or 'shipped model'} at n = {args.n}" if classifier is not None
            else "no model")
    print(f"{args.preset}, sigma {args.sigma:g}: {args.frames_per_class} frames a label, "
          f"oracle grid {args.grid}, {args.draws} draws; {what}; fp32 torch, {args.threads} "
          f"thread(s), {time.perf_counter() - start:.0f} s\n")
    print("| label | severity | frames | oracle tail | oracle noisy error | model tail "
          "| model noisy error |")
    print("|---|---|---|---|---|---|---|")
    for lab, name in enumerate(names):
        for quarter in (*range(QUARTERS), None):
            count = sum(1 for r in rows if r[0] == lab and (quarter is None or r[1] == quarter))
            where = "all" if quarter is None else f"q{quarter + 1}"
            model_cells = (_cells(rows, lab, quarter, 3) if classifier is not None
                           else "- | -")
            print(f"| {name} | {where} | {count} | {_cells(rows, lab, quarter, 2)} | "
                  f"{model_cells} |")


if __name__ == "__main__":
    main()
