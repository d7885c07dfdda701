"""``drake-cert simulate``: the closed loop (plant + L1 adaptive controller) on a road.

For each chosen design of a design table (``drake-cert synthesize --out FILE``; by default
every single-label design), simulate one episode at the design speed on a road (default: a
curve of the design radius placed in the episode) and print a short table (peak |e1|, when
the car left its lane, final offset); optionally write a plot of e1(t) and the steering
(``--plot``), the tapes (``--out tape.csv|tape.npz``) and the results as JSON on stdout.

An episode stops early once |e1| > ``drake_cert.systems.closed_loop.OFF_ROAD_M``; its peak |e1| is
then the peak up to the stop, and ``time_left_lane_s`` says when the car left its lane.
"""

import argparse
import io
import json
import math
import sys
import time

from drake_cert import metrics
from drake_cert.config import STIFFNESS_PLAUSIBLE, format_label_range, parse_label_range
from drake_cert.errors import ConfigError
from drake_cert.io import atomic_write_bytes, check_writable, provenance

STIFFNESS_CHOICES = ("lo", "mid", "hi", "ends")
# as drake_cert.systems.road.ROAD_KINDS
ROAD_CHOICES = ("curve", "s_curve", "curvature_step", "straight")
FRICTION_MAX = 2.0  # the conditions file accepts friction_mu in (0, 2]
RADIUS_MAX_M = 10_000.0  # m: a larger radius is a straight road for the lateral loop
DURATION_MAX_S = 3600.0  # longer episodes are a typo, not a study
OFF_ROAD_M = 5.0  # drake_cert.systems.closed_loop.OFF_ROAD_M (not imported: --help stays fast)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--designs", required=True, metavar="FILE",
                        help="design table or single design (YAML from `synthesize --out`)")
    pick = parser.add_mutually_exclusive_group()
    pick.add_argument("--labels", metavar="A+B",
                      help="simulate the design of exactly this label range, written as "
                           "`synthesize` prints it (e.g. light_rain+heavy_rain); "
                           "default: every single-label design")
    pick.add_argument("--design-index", type=int, metavar="N",
                      help="simulate the N-th design of the file (0-based)")
    parser.add_argument("--plant", choices=("nonlinear", "linear", "linear_sampled"),
                        default="nonlinear",
                        help="evaluation plant: Fiala single track, eq. 2.45, or "
                             "eq. 2.45 sampled exactly at T_s (piecewise-constant law only)")
    parser.add_argument("--law", choices=("piecewise_constant", "gradient"),
                        help="adaptation law (default: the settings stored with the designs)")
    parser.add_argument("--stiffness", default="lo", metavar="C",
                        help="true stiffness per tire: lo, mid, hi, ends (lo and hi) of the "
                             "design interval, or a number in N/rad")
    parser.add_argument("--friction", type=float, metavar="MU",
                        help=f"friction coefficient in (0, {FRICTION_MAX:g}] (default: the "
                             "design's least friction)")
    parser.add_argument("--speed", type=float, metavar="MPS",
                        help="forward speed in m/s, inside the design speed range "
                             "[speed_min_mps, speed_max_mps] of the stored settings "
                             "(default: each design's safe speed)")
    parser.add_argument("--road", choices=ROAD_CHOICES, default="curve",
                        help="road: a curve (straight, clothoid, arc, clothoid, straight), an "
                             "S-curve (left arc then right arc), a curvature step, or straight")
    parser.add_argument("--radius", type=float, metavar="M",
                        help=f"arc radius in m, > {OFF_ROAD_M:g} (default: the synthesis "
                             "design radius)")
    parser.add_argument("--initial-offset", type=float, default=0.0, metavar="M",
                        help=f"initial lateral offset e1(0) in m, |e1(0)| < {OFF_ROAD_M:g}")
    parser.add_argument("--duration", type=float, default=20.0, metavar="S",
                        help=f"episode length in s, at most {DURATION_MAX_S:g}")
    parser.add_argument("--plot", metavar="PNG", help="write e1(t) and steering(t) to this PNG")
    parser.add_argument("--out", metavar="TAPE",
                        help="write every episode's tape (t, state, steering, curvature) to "
                             "this .csv or .npz file")
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
        wanted = parse_label_range(args.labels)
        chosen = [(i, d) for i, d in designs if list(d.labels) == wanted]
        if not chosen:
            known = sorted({format_label_range(d.labels) for _, d in designs})
            raise ConfigError(f"--labels {args.labels!r}: no design for this label range; "
                              f"known: {', '.join(known)}")
        return chosen[:1]
    singles = [(i, d) for i, d in designs if len(d.labels) == 1]
    return singles or designs


def _stiffness_values(design, choice: str) -> list[float]:
    lo, hi = design.interval
    named = {"lo": [lo], "mid": [0.5 * (lo + hi)], "hi": [hi], "ends": [lo, hi]}
    if choice in named:
        return named[choice]
    return [stiffness_number(choice)]


def stiffness_number(choice: str) -> float:
    """``--stiffness`` given as a number: N/rad per tire, positive and plausible (a number
    below 1000 N/rad is refused as kN/rad written by mistake)."""
    try:
        value = float(choice)
    except ValueError:
        raise ConfigError(f"--stiffness {choice!r}: expected one of {', '.join(STIFFNESS_CHOICES)} "
                          "or a number in N/rad") from None
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(f"--stiffness {choice!r} must be a positive number of N/rad")
    STIFFNESS_PLAUSIBLE.check(value, "--stiffness")
    return value


def check(args) -> None:
    """Every check that needs no design file (``cli.main`` runs it before importing pydrake):
    numbers in range (``--stiffness`` too), output paths writable."""
    if args.stiffness not in STIFFNESS_CHOICES:
        stiffness_number(args.stiffness)
    for name in ("friction", "speed", "radius", "duration"):
        value = getattr(args, name)
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ConfigError(f"--{name} {value!r} must be a positive number")
    if args.friction is not None and args.friction > FRICTION_MAX:
        raise ConfigError(f"--friction {args.friction:g} is outside (0, {FRICTION_MAX:g}], the "
                          "range the conditions file accepts")
    if args.radius is not None and args.radius > RADIUS_MAX_M:
        raise ConfigError(f"--radius {args.radius:g} m is implausibly large for a road curve, "
                          f"above {RADIUS_MAX_M:g} m (mm? write {args.radius / 1000:g}; a "
                          "straight road is --road straight)")
    if args.radius is not None and args.radius <= OFF_ROAD_M:
        raise ConfigError(f"--radius {args.radius:g} m must exceed {OFF_ROAD_M:g} m (the road "
                          "frame about the arc breaks down as |e1| approaches the radius)")
    if args.duration > DURATION_MAX_S:
        raise ConfigError(f"--duration {args.duration:g} s exceeds {DURATION_MAX_S:g} s")
    if not (math.isfinite(args.initial_offset) and abs(args.initial_offset) < OFF_ROAD_M):
        raise ConfigError(f"--initial-offset {args.initial_offset!r} m must be finite with "
                          f"|e1(0)| < {OFF_ROAD_M:g} m (beyond, the car is off the road)")
    if args.plot:
        check_writable(args.plot, "--plot")
    if args.out:
        from drake_cert.systems.tape_io import check_tape_path

        check_writable(check_tape_path(args.out), "--out")


def check_speed(speed: float, synthesis_settings) -> None:
    """A speed must lie in the design speed range the gains were synthesized for."""
    lo, hi = synthesis_settings.speed_min_mps, synthesis_settings.speed_max_mps
    if not lo <= speed <= hi:
        raise ConfigError(f"--speed {speed:g} m/s is outside the design speed range "
                          f"[{lo:g}, {hi:g}] m/s of the designs' settings")


def run(args) -> int:
    from drake_cert.cli.progress import progress_bar
    from drake_cert.synthesis.design_io import load_design_file
    from drake_cert.systems.closed_loop import EpisodeOptions, simulate
    from drake_cert.systems.road import Road

    table = load_design_file(args.designs)  # cli.main has run check(args)
    vehicle, settings = table.vehicle, table.settings
    if args.speed is not None:
        check_speed(args.speed, settings.synthesis)
    law = args.law or settings.controller.adaptation_law
    if args.plant == "linear_sampled" and law != "piecewise_constant":
        raise ConfigError("--plant linear_sampled needs --law piecewise_constant")
    radius = args.radius or settings.synthesis.design_radius_m
    cases, skipped = _cases(table, args)
    results, tapes = [], []
    for index, design, stiffness, mu, speed in progress_bar(cases, desc="simulate", unit="episode",
                                                             disable=len(cases) < 2):
        road = Road.for_episode(args.road, radius_m=radius, length_m=speed * args.duration)
        start = time.perf_counter()
        tape = simulate(vehicle=vehicle, design=design, settings=settings,
                        stiffness_n_per_rad=stiffness, friction_mu=mu, speed_mps=speed, road=road,
                        episode=EpisodeOptions(plant=args.plant, law=law, t_final_s=args.duration,
                                               initial_state=[args.initial_offset, 0.0, 0.0, 0.0]))
        wall = time.perf_counter() - start
        tapes.append((design, tape))
        results.append(case_record(index, design, tape, wall, road=args.road, radius_m=radius,
                                   duration_s=args.duration))
    _write_outputs(args, tapes, results, radius)
    if args.json:
        json.dump({"provenance": provenance(None), "designs_file": str(args.designs),
                   "cases": results, "skipped": skipped}, sys.stdout, indent=2)
        print()
    else:
        print(_table(results, skipped))
    return 0


def _cases(table, args):
    """(design index, design, stiffness, friction, speed) per episode, and skipped designs."""
    cases, skipped = [], []
    for index, design in _select_designs(table, args):
        speed = args.speed or design.speed_mps
        if not speed > 0:
            skipped.append({"design_index": index, "labels": list(design.labels),
                            "reason": f"no safe speed ({design.failed_condition}): the car stops"})
            continue
        for stiffness in _stiffness_values(design, args.stiffness):
            cases.append((index, design, stiffness, args.friction or design.friction_mu_lo, speed))
    return cases, skipped


def case_record(index: int, design, tape, wall_s: float, **extra) -> dict:
    """The JSON record of one episode. ``peak_abs_e1_m`` is the peak up to the end of the
    tape: for an episode stopped off the road (``stopped_early``) that is about the stop
    threshold, so read ``time_left_lane_s`` there. ``real_time_factor`` = simulated_s / wall_s."""
    return {
        "design_index": index, "labels": list(design.labels),
        "stiffness_n_per_rad": tape.stiffness_n_per_rad, "friction_mu": tape.friction_mu,
        "speed_mps": tape.speed_mps, **extra, "plant": tape.plant, "law": tape.law,
        "initial_offset_m": float(tape.states[0, 0]),
        "peak_abs_e1_m": metrics.peak_lateral_offset(tape),
        "left_lane": metrics.left_lane(tape),
        "time_left_lane_s": tape.time_left_lane_s,
        "stopped_early": tape.stopped_early,
        "final_offset_m": metrics.final_offset(tape),
        "peak_steering_rad": metrics.peak_steering(tape),
        "lane_margin_m": tape.lane_margin_m,
        "simulated_s": tape.simulated_s, "wall_s": wall_s,
        "real_time_factor": tape.simulated_s / wall_s if wall_s > 0 else None,
    }


def _write_outputs(args, tapes, results, radius_m: float) -> None:
    if args.plot:
        atomic_write_bytes(args.plot, _plot_png(tapes, radius_m))
        print(f"wrote {args.plot}", file=sys.stderr)
    if args.out:
        from drake_cert.systems.tape_io import tape_header, write_tapes

        headers = [tape_header(t, design_index=r["design_index"], labels=r["labels"],
                               road=r["road"], radius_m=r["radius_m"])
                   for (_, t), r in zip(tapes, results, strict=True)]
        write_tapes(args.out, [t for _, t in tapes], headers)
        print(f"wrote {args.out}", file=sys.stderr)


def _table(results, skipped) -> str:
    head = (f"{'labels':<32} {'C_true':>8} {'mu':>5} {'V m/s':>6} {'peak|e1| m':>10} "
            f"{'left lane':>11} {'final e1 m':>10}")
    lines = [head, "-" * len(head)]
    for r in results:
        left = f"at {r['time_left_lane_s']:.2f} s" if r["left_lane"] else "no"
        peak = f"{r['peak_abs_e1_m']:.3f}" + ("*" if r["stopped_early"] else "")
        lines.append(f"{format_label_range(r['labels']) or '-':<32} "
                     f"{r['stiffness_n_per_rad']:>8.0f} {r['friction_mu']:>5.2f} "
                     f"{r['speed_mps']:>6.2f} {peak:>10} {left:>11} "
                     f"{r['final_offset_m']:>10.3f}")
    for s in skipped:
        lines.append(f"{format_label_range(s['labels']) or '-':<32} {s['reason']}")
    if any(r["stopped_early"] for r in results):
        lines.append(f"* stopped off the road (|e1| > {OFF_ROAD_M:g} m): peak and final e1 "
                     "are at the stop")
    return "\n".join(lines)


def _plot_png(tapes, radius_m: float) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_e1, ax_u) = plt.subplots(2, 1, figsize=(9, 6.5), sharex=True)
    for design, tape in tapes:
        name = (f"{format_label_range(design.labels) or 'design'} "
                f"C={tape.stiffness_n_per_rad / 1e3:.0f}k")
        ax_e1.plot(tape.times_s, tape.lateral_offset_m, label=name)
        ax_u.plot(tape.times_s, tape.steering_rad, label=name)
    if tapes:
        margin = tapes[0][1].lane_margin_m
        for sign in (1, -1):
            ax_e1.axhline(sign * margin, color="k", ls="--", lw=0.8)
    ax_e1.set_ylabel("lateral offset e1 (m)")
    ax_e1.set_title(f"closed loop, arc radius {radius_m:g} m (dashed: lane margin)")
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
