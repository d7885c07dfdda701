"""Simulated seconds per wall second of the certified driving Diagram at camera 10 Hz.

Drives the shipped dry_to_snow route for ``--seconds`` of simulated time with the camera at
10 Hz and no attack, side by side in one run (same machine, same load):

- certified, the robust conformal set decided sequentially (the shipped default, DESIGN 3.6;
  its calibration comes with the model and is not in the real-time factor);
- the same as it ran before 2026-12-06, the baseline of the default's speed-ups: every set
  sampled until decided or n (no futility stop) and no noise drawn ahead (DESIGN 3.6, 3.8);
- certified, sequential decisions with the safe-set interval (the paper's): at most n samples
  per frame, the range decided as soon as it is known;
- the same in the torch backend (the model in torch instead of ONNX Runtime);
- the safe-set interval with fixed-n certificates: n0 = 100 selection and n estimation samples
  per frame;
- perception off in effect (the base pipeline: one forward pass of f per frame).

``--threads`` is torch's thread count for the Diagram (the drive's own default is 1); the ONNX
Runtime session runs one intra-op thread per available core either way (DESIGN 3.8).

Precision and backend are what ``auto`` picks here unless ``DRAKE_CERT_PRECISION`` says
otherwise (both printed). For each: the real-time factor, the wall time, the time inside
perception (perf_counter around the perception block's work) and samples per frame.

``--repeat K`` drives every configuration K times, interleaved (one of each, then again), and
reports each one's median wall and perception time: a shared machine's speed drifts over
minutes, and the ratio "default / perception off" is then read from drives made side by side.

``--profile K`` also drives the conformal default once more under cProfile and prints its K
most expensive functions (cumulative time per frame), the profile of a frame.

Usage: python benchmarks/bench_driving.py [--seconds 10] [--n 1000] [--threads 1] [--repeat 1]
       [--profile 25]
"""

import argparse
import dataclasses
import json
import time

import numpy as np

from drake_cert.certification.backends import resolve_backend
from drake_cert.certification.conformal import LabelSetStopping
from drake_cert.certification.sampler import resolve_precision
from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.synthesis.table import synthesize_table
from drake_cert.systems.driving import build_certified_driving_diagram, drive, with_overrides
from drake_cert.systems.scenario import load_scenario
from drake_cert.threads import torch_threads


def timed_drive(scenario, setup, seconds, before=False):
    """One drive; ``before``: as the conformal default ran until 2026-12-05 (every set sampled
    until decided or n, no futility stop, and no noise drawn ahead), the baseline."""
    built = build_certified_driving_diagram(scenario, **setup)
    perception = built.systems["perception"]
    if before:  # measurement only: the same Diagram with the two speed-ups turned off
        perception.label_set_stopping = LabelSetStopping(futility_z=None)
        perception.draw_ahead_samples = 0
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
    spent["samples_per_frame"] = float(np.mean(result.ticks.samples))
    return result.summary, spent


def main() -> None:
    from drake_cert.certification.sampler import retain_freed_memory

    retain_freed_memory()  # as the long-running commands run (docs/results.md figures)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--n", type=int, default=1000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=1,
                        help="drive each configuration K times, interleaved; report medians")
    parser.add_argument("--profile", type=int, default=0,
                        help="print the conformal drive's K most expensive functions")
    args = parser.parse_args()
    vehicle, conditions, settings = load_vehicle(), load_conditions(), load_settings()
    setup = dict(vehicle=vehicle, conditions=conditions, settings=settings,
                 designs=synthesize_table(vehicle, conditions, settings))
    shipped = load_scenario("dry_to_snow")
    precision = resolve_precision(shipped.perception.precision)
    backend = resolve_backend(shipped.perception.backend, precision)

    def variant(pipeline, **perception):
        p = dataclasses.replace(shipped.perception, n=args.n, **perception)
        sc = dataclasses.replace(shipped, perception=p,
                                 camera=dataclasses.replace(shipped.camera, rate_hz=10.0))
        return with_overrides(sc, pipeline=pipeline, attack="none")

    conformal = variant("certified", decision="sequential", interval="conformal")
    configs = [
        (f"conformal (default), n <= {args.n}", conformal),
        ("conformal, before 2026-12-06", conformal),
        (f"safe-set, sequential, n <= {args.n}", variant("certified", decision="sequential",
                                                        interval="safe_set")),
        ("safe-set, sequential, torch", variant("certified", decision="sequential",
                                                 interval="safe_set", backend="torch")),
        (f"safe-set, fixed, n0 100 + n {args.n}", variant("certified", decision="fixed",
                                                          interval="safe_set", n0=100)),
        ("perception off (base f)", variant("base")),
    ]
    if args.repeat < 1:
        parser.error(f"--repeat {args.repeat}: must be at least 1")
    drives = {name: [] for name, _ in configs}
    with torch_threads(args.threads):
        for _ in range(args.repeat):
            for name, scenario in configs:
                drives[name].append(timed_drive(scenario, setup, args.seconds,
                                                before=name.endswith("before 2026-12-06")))
    rows = [(name, *median_drive(drives[name])) for name, _ in configs]
    print(f"dry_to_snow, camera 10 Hz, no attack, {args.seconds:g} s simulated, {precision} "
          f"(backend auto: {backend}), {args.threads} thread(s), time.perf_counter, median of "
          f"{args.repeat} interleaved drive(s) each")
    print(f"{'configuration':<36}{'sim s / wall s':>15}{'wall s':>8}{'perception s':>14}"
          f"{'ms / frame':>11}{'samples / frame':>17}{'abstained':>10}{'envelope':>10}")
    out = {"precision": precision, "backend_auto": backend, "seconds": args.seconds,
           "n": args.n, "threads": args.threads, "repeat": args.repeat}
    for name, s, spent in rows:
        per_frame = 1e3 * spent["perceive_s"] / max(spent["frames"], 1)
        print(f"{name:<36}{s['real_time_factor']:>15.3f}{s['wall_s']:>8.1f}"
              f"{spent['perceive_s']:>14.1f}{per_frame:>11.1f}{spent['samples_per_frame']:>17.0f}"
              f"{s['abstention_fraction']:>10.1%}{s['envelope_fraction']:>10.1%}")
        out[name] = {"real_time_factor": s["real_time_factor"], "wall_s": s["wall_s"],
                     "perception_s": spent["perceive_s"], "ms_per_frame": per_frame,
                     "samples_per_frame": spent["samples_per_frame"],
                     "abstention_fraction": s["abstention_fraction"],
                     "envelope_fraction": s["envelope_fraction"]}
    default, off = rows[0][1]["wall_s"], rows[-1][1]["wall_s"]
    print(f"wall time, conformal default / perception off: {default / off:.2f}x (before "
          f"2026-12-06: {rows[1][1]['wall_s'] / off:.2f}x)")
    out["default_over_perception_off"] = default / off
    print(json.dumps(out))
    if args.profile:
        with torch_threads(args.threads):
            print_profile(configs[0][1], setup, args.seconds, args.profile)


def median_drive(drives):
    """The summary and perception time of the drive with the median wall time (the upper
    median of an even count), its perception time the median of all."""
    ranked = sorted(drives, key=lambda d: d[0]["wall_s"])
    summary, spent = ranked[len(ranked) // 2]
    spent = dict(spent, perceive_s=float(np.median([d[1]["perceive_s"] for d in drives])))
    return summary, spent


def print_profile(scenario, setup, seconds, top):
    """cProfile of one more drive of ``scenario``: the ``top`` functions by cumulative time,
    in ms per camera frame (the profiler's own overhead included)."""
    import cProfile
    import pstats

    profiler = cProfile.Profile()
    built = build_certified_driving_diagram(scenario, **setup)
    profiler.enable()
    result = drive(built, t_final_s=seconds)
    profiler.disable()
    frames = max(len(result.ticks.samples), 1)
    stats = pstats.Stats(profiler)
    rows = sorted(stats.stats.items(), key=lambda kv: kv[1][3], reverse=True)[:top]
    print(f"profile of the conformal drive: {frames} frames; cumulative ms per frame "
          "(calls per frame)")
    for (path, line, name), (_, calls, _, cumulative, _) in rows:
        where = f"{path.rsplit('/', 2)[-1] if '/' in path else path}:{line}({name})"
        print(f"{1e3 * cumulative / frames:9.2f} ms {calls / frames:9.1f}  {where}")


if __name__ == "__main__":
    main()
