"""Backends for the base model under noise, side by side: samples/s and top-1 agreement.

One shipped classifier, one test frame per label, the same seeded noise for every backend,
each run through ``NoisySampler`` (noise drawn and added in torch, as in certification): torch
eager fp32, torch.compile fp32 (freezing, as the sampler compiles; compile time reported
apart), torch bf16 (only where the CPU has native bf16), ONNX Runtime fp32 and int8
(calibrated on noisy copies of the preset's calibration frames). Each at every thread count
(intra-op); the repetitions alternate over backends and thread counts so that load hits all
alike.
Agreement: the fraction of all samples whose top-1 label equals torch eager fp32's at the same
thread count. Ends with one JSON line.

Usage: python benchmarks/bench_backends.py [--preset carla-like] [--sigma 0.25] [--n 1000]
       [--batch-size 250] [--threads 1,2] [--reps 4]
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import time

import torch

from drake_cert.certification.backends import Int8Calibration, evaluated_model
from drake_cert.certification.sampler import NoisySampler, bf16_supported, with_precision
from drake_cert.perception.datasets import load_split
from drake_cert.perception.models import load_model


def build(name: str, model: torch.nn.Module, sigma: float, threads: int,
          calibration: torch.Tensor) -> tuple[NoisySampler, float]:
    """The sampler for one backend at ``threads``, and its build seconds (export, quantize).
    Each gets its own copy of the model: torch.compile generates code for the thread count at
    compile time (serial code at one thread), and a second compile of the same module could
    reuse the first one's."""
    torch.set_num_threads(threads)
    model = copy.deepcopy(model)
    start = time.perf_counter()
    if name == "ort-int8":
        base = evaluated_model(model, backend="onnxruntime", quantization="int8",
                               calibration=Int8Calibration(calibration, sigma),
                               threads=threads)
    elif name == "ort-fp32":
        base = evaluated_model(model, backend="onnxruntime", threads=threads)
    else:
        base = with_precision(model, "bf16" if name == "torch-bf16" else "fp32")
    seconds = time.perf_counter() - start
    return NoisySampler(base, sigma, "cpu", compile=name == "torch-compile"), seconds


def run(sampler: NoisySampler, frames: torch.Tensor, n: int, batch_size: int, seed: int,
        threads: int) -> tuple[torch.Tensor, float]:
    """Top-1 labels of n noisy copies of each frame (noise seeded by ``seed``), seconds taken."""
    torch.set_num_threads(threads)
    generator = torch.Generator().manual_seed(seed)
    start = time.perf_counter()
    with torch.inference_mode():
        labels = torch.cat([out.argmax(1) for x in frames
                            for out in sampler.outputs(x, n, batch_size, generator)])
    return labels, time.perf_counter() - start


def main() -> None:
    from drake_cert.certification.sampler import retain_freed_memory

    retain_freed_memory()  # as the long-running commands run (docs/results.md figures)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="carla-like")
    parser.add_argument("--sigma", type=float, default=0.25)
    parser.add_argument("--n", type=int, default=1000,
                        help="noisy samples per frame and repetition")
    parser.add_argument("--batch-size", type=int, default=250)
    parser.add_argument("--threads", default="1,2", help="comma-separated intra-op counts")
    parser.add_argument("--reps", type=int, default=4)
    args = parser.parse_args()
    thread_counts = [int(t) for t in args.threads.split(",")]

    model = load_model(args.preset, "classify", args.sigma)
    calibration = load_split(args.preset, "calibration", frames_per_class=8).images
    frames = load_split(args.preset, "test", frames_per_class=1).images  # one per label
    names = ["torch-eager", "torch-compile", "torch-bf16", "ort-fp32", "ort-int8"]
    if not bf16_supported():
        names.remove("torch-bf16")
        print("torch-bf16 skipped: this CPU has no native bf16 (AVX512-BF16/AMX), so bf16 is "
              "emulated and slower than fp32")
    print(f"{args.preset} classifier, sigma {args.sigma}, batch {args.batch_size}, "
          f"{len(frames)} frames x n = {args.n} x {args.reps} repetitions per backend and "
          f"thread count, "
          f"{torch.get_num_threads()} torch threads available")

    samplers, build_s, compile_s = {}, {}, {}
    for t in thread_counts:
        for name in names:
            samplers[name, t], build_s[name, t] = build(name, model, args.sigma, t, calibration)
            start = time.perf_counter()
            samplers[name, t].warmup(frames[0].shape, args.batch_size)  # compiles torch-compile
            compile_s[name, t] = time.perf_counter() - start

    speeds = {key: [] for key in samplers}
    agree = {key: [0, 0] for key in samplers}
    for rep in range(args.reps):
        for t in thread_counts:
            reference = None
            for name in names:
                labels, seconds = run(samplers[name, t], frames, args.n, args.batch_size, rep, t)
                reference = labels if reference is None else reference
                speeds[name, t].append(len(labels) / seconds)
                agree[name, t][0] += int((labels == reference).sum())
                agree[name, t][1] += len(labels)

    rows = []
    for t in thread_counts:
        for name in names:
            rows.append(dict(backend=name, threads=t,
                             samples_per_s=round(statistics.median(speeds[name, t]), 1),
                             agreement=agree[name, t][0] / agree[name, t][1],
                             build_s=round(build_s[name, t], 3),
                             warmup_s=round(compile_s[name, t], 3)))
    eager = {r["threads"]: r["samples_per_s"] for r in rows if r["backend"] == "torch-eager"}
    print(f"{'backend':<14} {'threads':>7} {'samples/s':>10} {'vs eager':>9} {'agreement':>10} "
          f"{'build s':>8} {'warm-up s':>10}")
    for r in rows:
        print(f"{r['backend']:<14} {r['threads']:>7} {r['samples_per_s']:>10.0f} "
              f"{r['samples_per_s'] / eager[r['threads']]:>8.2f}x {r['agreement']:>10.4f} "
              f"{r['build_s']:>8.2f} {r['warmup_s']:>10.2f}")
    print("warm-up s: the first batch (for torch-compile: the compile time); build s: export "
          "and quantization")
    print(json.dumps(dict(preset=args.preset, sigma=args.sigma, n=args.n, reps=args.reps,
                          batch_size=args.batch_size, bf16_supported=bf16_supported(),
                          results=rows)))


if __name__ == "__main__":
    main()
