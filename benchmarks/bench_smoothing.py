"""Certification throughput: drake_cert's SmoothedClassifier vs a plain Cohen-style loop.

Both certify the same frame with the same model (drake_cert's SmallResNet, 64x64 frames), the
same batch size and the same n0 / n, side by side in one run, alternating repetitions so that
load from other processes hits both alike. The plain loop is the shape of Cohen et al.'s
reference code: repeat the frame, ``randn_like`` noise, forward under ``torch.no_grad``, argmax,
count, then the Clopper-Pearson bound. Ours: preallocated in-place noise, inference mode,
``bincount`` on the device, padded last batch, and (optionally) the compiled model. The
one-time compilation is reported separately and excluded from the throughput.

Usage: python benchmarks/bench_smoothing.py [--n 10000] [--batch-size 1000] [--reps 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch
from scipy.stats import beta as beta_dist

from drake_cert.certification.classifier import SmoothedClassifier
from drake_cert.certification.sampler import Bfloat16Model, bf16_supported
from drake_cert.perception.models import SmallResNet


def plain_counts(model, x, num, batch_size, sigma, num_classes):
    """Cohen et al.'s sampling loop (core.py _sample_noise), counting with numpy."""
    counts = np.zeros(num_classes, dtype=np.int64)
    remaining = num
    with torch.no_grad():
        while remaining > 0:
            this_batch = min(batch_size, remaining)
            remaining -= this_batch
            batch = x.repeat((this_batch, 1, 1, 1))
            noise = torch.randn_like(batch) * sigma
            predictions = model(batch + noise).argmax(1)
            counts += np.bincount(predictions.numpy(), minlength=num_classes)
    return counts


def plain_certify(model, x, n0, n, alpha, batch_size, sigma, num_classes):
    """Cohen's CERTIFY: select with n0, estimate with n, one-sided Clopper-Pearson bound."""
    top = int(np.argmax(plain_counts(model, x, n0, batch_size, sigma, num_classes)))
    count = int(plain_counts(model, x, n, batch_size, sigma, num_classes)[top])
    p_low = beta_dist.ppf(alpha, count, n - count + 1) if count > 0 else 0.0
    return top, p_low


def main() -> None:
    from drake_cert.certification.sampler import retain_freed_memory

    retain_freed_memory()  # as the long-running commands run (docs/results.md figures)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=10_000)
    parser.add_argument("--n0", type=int, default=100)
    parser.add_argument("--batch-size", type=int, default=1000)
    parser.add_argument("--reps", type=int, default=3, help="certifications per method")
    parser.add_argument("--sigma", type=float, default=0.25)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: all)")
    parser.add_argument("--bf16", action="store_true",
                        help="also certify the bfloat16 model (compiled) and its plain loop")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    torch.manual_seed(0)
    num_classes = 3
    model = SmallResNet(num_classes).eval()
    x = torch.rand(3, args.size, args.size, generator=torch.Generator().manual_seed(1))
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; SmallResNet(3), "
          f"{args.size}x{args.size} frames, batch {args.batch_size}, n0 = {args.n0}, "
          f"n = {args.n}, sigma = {args.sigma}")

    eager = SmoothedClassifier(model, num_classes, args.sigma, compile=False)
    compiled = SmoothedClassifier(model, num_classes, args.sigma, compile=True)
    shape = tuple(x.shape)
    eager.warmup(shape, args.batch_size)
    compile_s = compiled.warmup(shape, args.batch_size)
    print(f"one-time compilation (first compiled batch): {compile_s:.1f} s "
          f"(compiled: {compiled.compile_seconds > 0}; a warm inductor cache shortens it, "
          "TORCHINDUCTOR_CACHE_DIR=<new folder> gives the cold figure)")
    plain_certify(model, x, 10, args.batch_size, 0.001, args.batch_size, args.sigma, num_classes)

    methods = {
        "plain Cohen-style loop": lambda: plain_certify(model, x, args.n0, args.n, 0.001,
                                                        args.batch_size, args.sigma,
                                                        num_classes),
        "ours, eager": lambda: eager.certify(x, args.n0, args.n, 0.001, args.batch_size),
        "ours, compiled": lambda: compiled.certify(x, args.n0, args.n, 0.001, args.batch_size),
    }
    if args.bf16:
        # bfloat16 (DESIGN 3.8): the certificate is of the bf16 model as evaluated; the
        # plain loop through the same bf16 model is shown too (the same dtype path).
        bf16_model = Bfloat16Model(model).eval()
        bf16 = SmoothedClassifier(model, num_classes, args.sigma, compile=True, precision="bf16")
        print(f"bf16 compilation: {bf16.warmup(shape, args.batch_size):.1f} s "
              f"(native bf16 on this CPU: {bf16_supported()})")
        methods["plain loop, bf16 model"] = lambda: plain_certify(
            bf16_model, x, args.n0, args.n, 0.001, args.batch_size, args.sigma, num_classes)
        methods["ours, compiled bf16"] = lambda: bf16.certify(x, args.n0, args.n, 0.001,
                                                              args.batch_size)
    times: dict[str, list[float]] = {k: [] for k in methods}
    for _ in range(args.reps):
        for name, fn in methods.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)

    base = statistics.median(times["plain Cohen-style loop"])
    print(f"{'method':<24} {'s/frame (median)':>16} {'samples/s':>10} {'vs plain':>9}")
    for name, ts in times.items():
        t = statistics.median(ts)
        rate = (args.n0 + args.n) / t
        print(f"{name:<24} {t:>16.3f} {rate:>10.0f} {base / t:>8.2f}x")
    t_eager = statistics.median(times["ours, eager"])
    t_comp = statistics.median(times["ours, compiled"])
    if t_comp < t_eager:
        per_sample_gain = (t_eager - t_comp) / (args.n0 + args.n)
        print(f"compilation pays off after about {compile_s / per_sample_gain:,.0f} samples "
              f"({compile_s / (t_eager - t_comp):.0f} certifications at this n)")


if __name__ == "__main__":
    main()
