"""Frame generation throughput: batched rendering (perception.frames) vs one frame at a time.

Both render the same number of carla-like frames with the same code; the only difference is
the batch (``frames.CHUNK``): 250 frames per call vs 1 (the shape of a per-image generator
loop). Repetitions alternate so that load from other processes hits both alike. Prints frames
per second and the projected time for the 12,000 carla-like training frames.

Usage: python benchmarks/bench_frames.py [--frames 500] [--reps 3] [--threads 1]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from drake_cert.config import load_conditions
from drake_cert.perception import frames


def time_generation(table, count_per_class: int, chunk: int) -> float:
    frames.CHUNK = chunk
    t0 = time.perf_counter()
    frames.generate_frames(table, "carla-like", seed=0, frames_per_class=count_per_class)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=500, help="frames per repetition")
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    table = load_conditions()
    per_class = max(1, args.frames // 3)
    n = 3 * per_class
    default_chunk = frames.CHUNK
    batched, single = [], []
    for _ in range(args.reps):
        batched.append(time_generation(table, per_class, default_chunk))
        single.append(time_generation(table, per_class, 1))
    frames.CHUNK = default_chunk
    tb, ts = statistics.median(batched), statistics.median(single)
    print(f"frames per repetition: {n}, threads: {args.threads}, reps: {args.reps} (median)")
    print(f"batched ({default_chunk}/call): {n / tb:8.1f} frames/s  "
          f"-> 12,000 carla-like train frames in {12000 / (n / tb):6.1f} s")
    print(f"one frame per call:   {n / ts:8.1f} frames/s  "
          f"-> 12,000 carla-like train frames in {12000 / (n / ts):6.1f} s")
    print(f"speed-up of batching: {ts / tb:.1f}x")


if __name__ == "__main__":
    main()
