"""``drake-cert simulate``: the closed loop (plant + L1 adaptive controller) on a curved road.

For each chosen design of a design table (``drake-cert synthesize --out FILE``; by default
every single-label design), simulate one episode at the design speed on a road that runs
straight, turns along an arc of the design radius, and runs straight again; print a short
table (peak |e1|, lane departure, final offset) and optionally write a plot of e1(t) and the
steering, and the results as JSON on stdout.
"""

import argparse
import io
import json
import sys
import time

import numpy as np

from drake_cert import metrics
from drake_cert.errors import ConfigError
from drake_cert.io import atomic_write_bytes, provenance

STIFFNESS_CHOICES = ("lo", "mid", "hi", "ends")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--designs", required=True, metavar="FILE",
                        help="design table or single design (YAML from `synthesize --out`)")
    pick = parser.add_mutually_exclusive_group()
    pick.add_argument("--labels", metavar="A,B,...",
                      help="simulate the design of exactly this label range (comma separated); "
                           "default: every single-label design")
    pick.add_argument("--design-index", type=int, metavar="N",
                      help="simulate the N-th design of the file (0-based)")
    parser.add_argument("--plant", choices=("nonlinear", "linear", "linear_sampled"),
                        default="nonlinear",
                        help="evaluation plant: Fiala single track (default), eq. 2.45, or "
                             "eq. 2.45 sampled exactly at T_s (piecewise-constant law only)")
    parser.add_argument("--law", choices=("piecewise_constant", "gradient"),
                        help="adaptation law (default: the settings stored with the designs)")
    parser.add_argument("--stiffness", default="lo", metavar="C",
                        help="true stiffness per tire: lo, mid, hi, ends (lo and hi) of the "
                             "design interval, or a number in N/rad (default: lo)")
    parser.add_argument("--friction", type=float, metavar="MU",
                        help="friction coefficient (default: the design's least friction)")
    parser.add_argument("--speed", type=float, metavar="MPS",
                        help="forward speed in m/s (default: each design's safe speed)")
    parser.add_argument("--radius", type=float, metavar="M",
                        help="curve radius in m (default: the synthesis design radius)")
    parser.add_argument("--duration", type=float, default=20.0, metavar="S",
                        help="episode length in s (default: 20)")
    parser.add_argument("--plot", metavar="PNG", help="write e1(t) and steering(t) to this PNG")
    parser.add_argument("--json", action="store_true",
                        help="print the results as JSON on stdout instead of the table")


def _select_designs(table, args):
    designs = list(enumerate(table.designs))
    if args.design_index is not None:
        if not 0 <= args.design_index < len(designs):
            raise ConfigError(f"--design-index {args.design_index} is out of range; the file "
                              f"holds {len(designs)} designs")
        return [designs[args.design_index]]
    if args.labels is not None:
        wanted = [s.strip() for s in args.labels.split(",") if s.strip()]
        chosen = [(i, d) for i, d in designs if list(d.labels) == wanted]
        if not chosen:
            known = sorted({",".join(d.labels) for _, d in designs})
            raise ConfigError(f"--labels {args.labels!r}: no design for this label range; "
                              f"known: {'; '.join(known)}")
        return chosen[:1]
    singles = [(i, d) for i, d in designs if len(d.labels) == 1]
    return singles or designs


def _stiffness_values(design, choice: str) -> list[float]:
    lo, hi = design.interval
    named = {"lo": [lo], "mid": [0.5 * (lo + hi)], "hi": [hi], "ends": [lo, hi]}
    if choice in named:
        return named[choice]
    try:
        value = float(choice)
    except ValueError:
        raise ConfigError(f"--stiffness {choice!r}: expected one of {', '.join(STIFFNESS_CHOICES)} "
                          "or a number in N/rad") from None
    if not (np.isfinite(value) and value > 0):
        raise ConfigError(f"--stiffness {choice!r} must be a positive number of N/rad")
    return [value]


def _check_positive(name: str, value) -> None:
    if value is not None and not (np.isfinite(value) and value > 0):
        raise ConfigError(f"{name} = {value!r} must be a positive number")


def run(args) -> int:
    from tqdm import tqdm

    from synthesis.design_io import load_design_file
    from systems.closed_loop import simulate
    from systems.road import Road

    for name in ("--friction", "--speed", "--radius", "--duration"):
        _check_positive(name, getattr(args, name[2:]))
    table = load_design_file(args.designs)
    vehicle, settings = table.vehicle, table.settings
    law = args.law or settings.controller.adaptation_law
    if args.plant == "linear_sampled" and law != "piecewise_constant":
        raise ConfigError("--plant linear_sampled needs --law piecewise_constant")
    radius = args.radius or settings.synthesis.design_radius_m
    cases, skipped = [], []
    for index, design in _select_designs(table, args):
        speed = args.speed or design.speed_mps
        if not speed > 0:
            skipped.append({"design_index": index, "labels": list(design.labels),
                            "reason": f"no safe speed ({design.failed_condition}): the car stops"})
            continue
        for stiffness in _stiffness_values(design, args.stiffness):
            cases.append((index, design, stiffness, args.friction or design.friction_mu_lo, speed))

    results, tapes = [], []
    for index, design, stiffness, mu, speed in tqdm(cases, desc="simulate", unit="episode",
                                                     file=sys.stderr, disable=len(cases) < 2):
        road = Road.episode_curve(radius_m=radius, length_m=speed * args.duration)
        start = time.perf_counter()
        tape = simulate(vehicle=vehicle, design=design, settings=settings,
                        stiffness_n_per_rad=stiffness, friction_mu=mu, speed_mps=speed,
                        road=road, plant=args.plant, law=law, t_final_s=args.duration)
        wall = time.perf_counter() - start
        tapes.append((design, tape))
        results.append({
            "design_index": index, "labels": list(design.labels),
            "stiffness_n_per_rad": stiffness, "friction_mu": mu, "speed_mps": speed,
            "radius_m": radius, "plant": args.plant, "law": law,
            "peak_abs_e1_m": metrics.peak_lateral_offset(tape),
            "left_lane": metrics.left_lane(tape),
            "final_offset_m": metrics.final_offset(tape),
            "peak_steering_rad": metrics.peak_steering(tape),
            "lane_margin_m": tape.lane_margin_m, "duration_s": args.duration,
            "wall_s": wall, "realtime_factor": args.duration / wall,
        })

    if args.plot:
        atomic_write_bytes(args.plot, _plot_png(tapes, radius))
        print(f"wrote {args.plot}", file=sys.stderr)
    if args.json:
        json.dump({"provenance": provenance(None), "designs_file": str(args.designs),
                   "cases": results, "skipped": skipped}, sys.stdout, indent=2)
        print()
    else:
        print(_table(results, skipped))
    return 0


def _table(results, skipped) -> str:
    head = (f"{'labels':<32} {'C_true':>8} {'mu':>5} {'V m/s':>6} {'peak|e1| m':>10} "
            f"{'left lane':>9} {'final e1 m':>10}")
    lines = [head, "-" * len(head)]
    for r in results:
        lines.append(f"{','.join(r['labels']) or '-':<32} {r['stiffness_n_per_rad']:>8.0f} "
                     f"{r['friction_mu']:>5.2f} {r['speed_mps']:>6.2f} {r['peak_abs_e1_m']:>10.3f} "
                     f"{'YES' if r['left_lane'] else 'no':>9} {r['final_offset_m']:>10.3f}")
    for s in skipped:
        lines.append(f"{','.join(s['labels']) or '-':<32} {s['reason']}")
    return "\n".join(lines)


def _plot_png(tapes, radius_m: float) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_e1, ax_u) = plt.subplots(2, 1, figsize=(9, 6.5), sharex=True)
    for design, tape in tapes:
        name = f"{','.join(design.labels) or 'design'} C={tape.stiffness_n_per_rad / 1e3:.0f}k"
        ax_e1.plot(tape.times_s, tape.lateral_offset_m, label=name)
        ax_u.plot(tape.times_s, tape.steering_rad, label=name)
    if tapes:
        margin = tapes[0][1].lane_margin_m
        for sign in (1, -1):
            ax_e1.axhline(sign * margin, color="k", ls="--", lw=0.8)
    ax_e1.set_ylabel("lateral offset e1 (m)")
    ax_e1.set_title(f"closed loop on a curve of radius {radius_m:g} m (dashed: lane margin)")
    ax_u.set_ylabel("steering (rad)")
    ax_u.set_xlabel("time (s)")
    ax_e1.legend(fontsize=7, ncol=2)
    ax_e1.grid(alpha=0.3)
    ax_u.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()
