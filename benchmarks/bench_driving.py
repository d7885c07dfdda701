"""Simulated seconds per wall second of the certified driving Diagram (issue 7, item 13).

Drives the shipped dry_to_snow route for ``--seconds`` of simulated time with the camera at
10 Hz: (a) certified pipeline, n = 1000 estimation samples per frame (n0 = 100), no attack;
(b) the same Diagram with perception off in effect (the base pipeline: one forward pass of f
per frame). Prints both rates side by side, and where the time of (a) goes (certificates vs
the rest), measured with perf_counter around the drive and inside the perception block.

Usage: python benchmarks/bench_driving.py [--seconds 10] [--n 1000] [--threads 1]
"""

import argparse
import dataclasses
import time

import torch

from drake_cert.config import load_conditions, load_settings, load_vehicle
from synthesis.table import synthesize_table
from systems.driving import build_certified_driving_diagram, drive, with_overrides
from systems.scenario import load_scenario


def timed_drive(scenario, setup, seconds):
    built = build_certified_driving_diagram(scenario, **setup)
    perception = built.systems["perception"]
    spent = {"perceive_s": 0.0, "frames": 0}
    original = perception.perceive

    def perceive(frame, time_s):
        start = time.perf_counter()
        try:
            return original(frame, time_s)
        finally:
            spent["perceive_s"] += time.perf_counter() - start
            spent["frames"] += 1

    perception.perceive = perceive  # measurement only: same computation
    result = drive(built, t_final_s=seconds)
    return result.summary, spent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--n", type=int, default=1000)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    vehicle, conditions, settings = load_vehicle(), load_conditions(), load_settings()
    setup = dict(vehicle=vehicle, conditions=conditions, settings=settings,
                 designs=synthesize_table(vehicle, conditions, settings))
    base = load_scenario("dry_to_snow")
    base = dataclasses.replace(base, perception=dataclasses.replace(
        base.perception, n=args.n, n0=100), camera=dataclasses.replace(base.camera, rate_hz=10.0))
    rows = []
    for name, pipeline in ((f"certified, n = {args.n}", "certified"),
                           ("perception off (base f)", "base")):
        scenario = with_overrides(base, pipeline=pipeline, attack="none")
        summary, spent = timed_drive(scenario, setup, args.seconds)
        rows.append((name, summary, spent))
    print(f"dry_to_snow, camera 10 Hz, {args.seconds:g} s simulated, torch threads "
          f"{args.threads}, resolution: time.perf_counter")
    print(f"{'configuration':<28}{'sim s / wall s':>16}{'wall s':>9}{'perception s':>14}"
          f"{'per frame ms':>14}")
    for name, s, spent in rows:
        per_frame = 1e3 * spent["perceive_s"] / max(spent["frames"], 1)
        print(f"{name:<28}{s['real_time_factor']:>16.3f}{s['wall_s']:>9.1f}"
              f"{spent['perceive_s']:>14.1f}{per_frame:>14.1f}")
    (_, cert, spent), (_, off, _) = rows
    rest = cert["wall_s"] - spent["perceive_s"]
    print(f"certified: {100 * spent['perceive_s'] / cert['wall_s']:.0f}% of the wall time in "
          f"certificates ({spent['frames']} frames), {rest:.1f} s in the rest of the Diagram "
          f"(perception off: {off['wall_s']:.1f} s)")


if __name__ == "__main__":
    main()
