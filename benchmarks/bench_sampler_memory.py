"""Noisy sampling with glibc keeping freed memory vs glibc's defaults, side by side.

Each policy runs in its own fresh process (the allocator setting is process-wide and cannot be
undone): the shipped classifier (carla-like, sigma 0.5) in the reproduction's precision and
batch size, one thread, a warm-up, then timed repetitions of n noisy samples. Reports samples/s,
minor page faults and kernel time per 1000 samples. ``retain_freed_memory`` changes where
memory comes from, never a number: the script checks that both policies give the same outputs.

Usage: python benchmarks/bench_sampler_memory.py [--n 4000] [--reps 5] [--precision bf16]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

WORKER = """
import hashlib, json, resource, statistics, sys, time, torch
import drake_cert.certification.sampler as sampler
if sys.argv[1] == "retain":  # as the long-running commands do; "defaults" leaves glibc as it is
    if not sampler.retain_freed_memory():
        sys.exit("glibc refused the settings (or this is not glibc): nothing to compare")
torch.set_num_threads(1)
from drake_cert.perception.models import load_model
n, reps, batch, precision = int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
s = sampler.NoisySampler(sampler.with_precision(load_model("carla-like", "classify", 0.5),
                                                precision), 0.5, "cpu", False)
x = torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(1))
with torch.inference_mode():  # warm-up
    list(s.outputs(x, 2 * n, batch, generator=torch.Generator().manual_seed(0)))
times, faults, kernel, digest = [], [], [], hashlib.sha256()
for rep in range(reps):
    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    with torch.inference_mode():  # as the callers do
        out = list(s.outputs(x, n, batch, generator=torch.Generator().manual_seed(rep)))
    t1, r1 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
    times.append(t1 - t0)
    faults.append((r1.ru_minflt - r0.ru_minflt) * 1000 / n)
    kernel.append((r1.ru_stime - r0.ru_stime) * 1000 / n)
    digest.update(torch.cat(out).float().numpy().tobytes())
print(json.dumps(dict(samples_per_s=n / statistics.median(times),
                      faults_per_1000=statistics.median(faults),
                      kernel_s_per_1000=statistics.median(kernel),
                      outputs_sha256=digest.hexdigest())))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=4000, help="noisy samples per repetition")
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--batch-size", type=int, default=250)
    parser.add_argument("--precision", choices=("bf16", "fp32"), default="bf16")
    args = parser.parse_args()
    print(f"carla-like sigma 0.5 classifier, {args.precision}, batch {args.batch_size}, one "
          f"thread, n = {args.n}, median of {args.reps} (fresh process per policy)")
    results = {}
    for policy in ("defaults", "retain"):
        out = subprocess.run([sys.executable, "-c", WORKER, policy, str(args.n), str(args.reps),
                              str(args.batch_size), args.precision],
                             capture_output=True, text=True)
        if out.returncode != 0:
            sys.exit(f"the {policy} worker failed:\n{out.stderr}")
        results[policy] = json.loads(out.stdout.splitlines()[-1])
    print(f"{'glibc policy':<28} {'samples/s':>10} {'faults/1000':>12} {'kernel s/1000':>14}")
    for policy, label in (("defaults", "defaults (baseline)"),
                          ("retain", "retain_freed_memory (ours)")):
        r = results[policy]
        print(f"{label:<28} {r['samples_per_s']:>10.0f} {r['faults_per_1000']:>12.0f} "
              f"{r['kernel_s_per_1000']:>14.3f}")
    speedup = results["retain"]["samples_per_s"] / results["defaults"]["samples_per_s"]
    same = results["retain"]["outputs_sha256"] == results["defaults"]["outputs_sha256"]
    print(f"speed-up {speedup:.2f}x; identical outputs: {same}")
    if not same:
        sys.exit("the allocator policy changed the model's outputs")


if __name__ == "__main__":
    main()
