"""The tail that sets the robust conformal thresholds: per true label, the calibration frames'
smoothed vote share for their own label, and the thresholds q_l and t_l(eps) it gives at several
alpha_c (DESIGN 3.6).

With alpha_c = 0.008 and 150 frames a label, q_l is the smallest of the 150 scores, so one frame
that g mostly misreads sets it; this prints how far the next frames are from it. Samples the
shipped classifier on the drive's calibration split (torch, fp32, ``--threads``), one noise
stream per frame from ``--seed``; nothing is cached or written.

Run: ``.venv/bin/python benchmarks/conformal_tail.py [--preset robotcar-like] [--sigma 1]
[--n 1000] [--frames-per-class 150] [--eps 1] [--model FILE] [--split test]`` (``--model``: a
candidate classifier file instead of the shipped one; ``--split test``: held-out frames)
(about 3 min for robotcar-like at n = 1000 on 2 cores).
"""

import argparse
import time

import numpy as np
import torch

from drake_cert.certification.classifier import SmoothedClassifier
from drake_cert.certification.conformal import (
    RobustConformalCalibration,
    calibration_scores,
    thresholds_from_scores,
)
from drake_cert.certification.sampler import make_generator
from drake_cert.config import load_conditions
from drake_cert.perception.datasets import load_split
from drake_cert.perception.models import load_model, load_model_file

ALPHA_CS = (0.008, 0.02, 0.05)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="robotcar-like")
    parser.add_argument("--sigma", type=float, default=1.0)
    parser.add_argument("--n", type=int, default=1000, help="samples per calibration frame")
    parser.add_argument("--frames-per-class", type=int, default=150)
    parser.add_argument("--eps", type=float, default=1.0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--model", default=None,
                        help="a candidate classifier file (default: the shipped model)")
    parser.add_argument("--split", choices=("calibration", "test"), default="calibration",
                        help="whose frames: the drive's calibration split or held-out test")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    conditions = load_conditions()
    names = [c.name for c in conditions.preset_conditions(args.preset)]
    cal = load_split(args.preset, args.split, conditions=conditions,
                     frames_per_class=args.frames_per_class)
    model = (load_model_file(args.model) if args.model
             else load_model(args.preset, "classify", args.sigma))
    classifier = SmoothedClassifier(model, len(names), args.sigma)
    start = time.perf_counter()
    own = np.array([classifier.sample_counts(cal.images[i], args.n, 250,
                                             make_generator(args.seed + i, classifier.device))
                    [int(cal.labels[i])] for i in range(len(cal.labels))])
    width = getattr(getattr(model, "backbone", model), "width", "?")
    print(f"{args.preset}, sigma {args.sigma:g}, {args.model or 'shipped model'} "
          f"(training {model.meta.get('training')}, width {width}), "
          f"{len(cal.labels)} {args.split} frames, n = {args.n}, fp32 torch, {args.threads} "
          f"thread(s): {time.perf_counter() - start:.0f} s")
    scores = calibration_scores(own, args.n)
    calibrations = {}
    for alpha_c in ALPHA_CS:
        thresholds, sizes = thresholds_from_scores(scores, cal.labels, len(names), alpha_c)
        calibrations[alpha_c] = RobustConformalCalibration(thresholds, sizes, len(names),
                                                           args.sigma, args.n, alpha_c)
    for lab, name in enumerate(names):
        shares = np.sort(own[cal.labels == lab] / args.n)
        print(f"{name}: lowest own-label shares {np.round(shares[:6], 3).tolist()}; "
              f"{int((shares < 0.5).sum())} of {len(shares)} under 0.5")
        for alpha_c, calibration in calibrations.items():
            print(f"    alpha_c {alpha_c:<6g} q {calibration.thresholds[lab]:.3f}  "
                  f"t(eps = {args.eps:g}) {calibration.threshold(lab, args.eps):.4f}")

if __name__ == "__main__":
    main()
