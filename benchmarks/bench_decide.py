"""Run-time decisions at a known budget: the fixed-n certificate vs sequential decisions.

Same frames (the preset's synthetic test split, every label alike), same model (the shipped
classifier at --sigma, in the precision and backend that `auto` picks here unless given), the
same run-time question: which label range is certified at radius --eps (the narrowest, as the
driving Diagram asks)? Side by side, alternating per frame so that load hits both alike:

- fixed: Cohen's CERTIFY with n0 = 100 selection and n = --n estimation samples, joint
  Clopper-Pearson bounds, then the narrowest range with R_T > eps;
- sequential (looks): SmoothedClassifier.decide with at most --n samples, every candidate
  range tested at once (no selection), Clopper-Pearson at geometric looks;
- sequential (mixture): the same with Robbins' beta-mixture confidence sequence;
- sequential (select 30): the ranges holding the top label of 30 selection samples.

Prints samples per decision, decisions per second, the share certified and the share where
the sequential range equals the fixed one; then one JSON line.

Usage: python benchmarks/bench_decide.py [--preset robotcar-like] [--sigma 1.0] [--eps 1.0]
       [--frames 60] [--n 1000] [--threads 1] [--precision auto] [--backend auto]
"""

import argparse
import json
import time

import numpy as np
import torch

from drake_cert.certification.backends import evaluated_model, resolve_backend
from drake_cert.certification.classifier import SmoothedClassifier
from drake_cert.certification.intervals import candidate_ranges, runtime_classification_interval
from drake_cert.certification.sampler import resolve_precision, with_precision
from drake_cert.certification.statistics import SequentialOptions
from drake_cert.config import load_conditions
from drake_cert.perception.datasets import load_split
from drake_cert.perception.models import load_model


def main() -> None:
    from drake_cert.certification.sampler import retain_freed_memory

    retain_freed_memory()  # as the long-running commands run (docs/results.md figures)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="robotcar-like")
    parser.add_argument("--sigma", type=float, default=1.0)
    parser.add_argument("--eps", type=float, default=1.0)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--n", type=int, default=1000)
    parser.add_argument("--alpha", type=float, default=0.001)
    parser.add_argument("--batch-size", type=int, default=500)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--precision", default="auto", choices=("auto", "fp32", "bf16"))
    parser.add_argument("--backend", default="auto", choices=("auto", "torch", "onnxruntime"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    precision = resolve_precision(args.precision)
    backend = resolve_backend(args.backend, precision)
    conditions = load_conditions()
    labels = list(conditions.preset(args.preset).labels)
    model = evaluated_model(with_precision(load_model(args.preset, "classify", args.sigma),
                                           precision), backend=backend, precision=precision)
    g = SmoothedClassifier(model, len(labels), args.sigma)
    per_class = max(1, args.frames // len(labels))
    test = load_split(args.preset, "test", conditions=conditions, frames_per_class=per_class)
    ranges = candidate_ranges(conditions, args.preset, labels)
    methods = ("fixed", "sequential (looks)", "sequential (mixture)", "sequential (select 30)")
    out = {m: {"samples": [], "seconds": 0.0, "certified": [], "range": []} for m in methods}
    for i, x in enumerate(test.images):
        for m in methods:
            start = time.perf_counter()
            if m == "fixed":
                cert = g.certify(x, 100, args.n, args.alpha, args.batch_size, seed=i)
                rt = runtime_classification_interval(cert, conditions, args.preset, args.eps,
                                                     labels)
                samples, certified, rng = 100 + args.n, rt.certified, rt.labels
            else:
                select = "select" in m
                d = g.decide(x, args.eps, args.alpha, args.n, args.batch_size,
                             (lambda a: [c for c in ranges if a in c]) if select else ranges,
                             seed=i, options=SequentialOptions(
                                 bound="mixture" if "mixture" in m else "looks",
                                 selection_n=30 if select else 0, selection_seed=10**6 + i))
                samples, certified = d.samples, d.certified
                rng = tuple(labels[k] for k in d.labels) if certified else tuple(labels)
            out[m]["seconds"] += time.perf_counter() - start
            out[m]["samples"].append(samples)
            out[m]["certified"].append(certified)
            out[m]["range"].append(rng)
    frames = len(test.images)
    print(f"{args.preset}, sigma {args.sigma:g}, eps {args.eps:g}, alpha {args.alpha:g}, "
          f"{frames} test frames, n = {args.n}, {precision} via {backend}, "
          f"{args.threads} thread(s)")
    print(f"{'method':<24}{'samples/decision':>18}{'decisions/s':>13}{'certified':>11}"
          f"{'same range as fixed':>21}")
    summary = {"preset": args.preset, "sigma": args.sigma, "eps": args.eps, "frames": frames,
               "n": args.n, "precision": precision, "backend": backend,
               "threads": args.threads}
    for m in methods:
        r = out[m]
        same = np.mean([a == b for a, b in zip(r["range"], out["fixed"]["range"], strict=True)])
        row = {"samples_per_decision": float(np.mean(r["samples"])),
               "decisions_per_s": frames / r["seconds"],
               "certified_share": float(np.mean(r["certified"])), "same_range_share": same}
        summary[m] = row
        print(f"{m:<24}{row['samples_per_decision']:>18.0f}{row['decisions_per_s']:>13.1f}"
              f"{row['certified_share']:>11.1%}{same:>21.1%}")
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
