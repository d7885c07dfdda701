"""``drake-cert drive``: drive a route in the certified closed-loop Diagram (DESIGN 6).

Loads a scenario (a shipped name or a YAML file), synthesizes the design table (or reads
``--designs``), builds the Diagram camera -> attacker -> perception smoothing -> certified
interval -> longitudinal motion -> switching L1 controller -> Fiala plant, drives the route
and prints a summary (``--json``: one object). ``--compare`` drives the certified and the base
pipeline under the same attack and prints both. ``--plot`` writes lateral offset, speed and
interval against the truth; ``--meshcat`` records the drive to a standalone HTML page;
``--out`` writes the tape (.csv or .npz). A progress bar on stderr.
"""

from __future__ import annotations

import argparse
import json

PIPELINES = ("certified", "base")
ATTACKS = ("none", "sa", "ea", "nan", "misshaped")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", default="dry_to_snow", metavar="NAME|FILE",
                        help="shipped scenario name (dry_to_snow, rain_route, road_surface, "
                             "sunny_into_snow, weather_change_in_curve, sunny_straight_to_snow,"
                             " curve_entry_changes) or a scenario YAML "
                             "file")
    parser.add_argument("--pipeline", choices=PIPELINES, default=None,
                        help="certified (smoothed g, certificate) or base (raw f); default: "
                             "the scenario's")
    parser.add_argument("--compare", action="store_true",
                        help="drive the certified and the base pipeline and print both")
    parser.add_argument("--attack", choices=ATTACKS, default=None,
                        help="attack on each frame (default: the scenario's)")
    parser.add_argument("--eps", type=float, default=None, metavar="E",
                        help="L2 budget of the attack, [0, 1] pixel units (default: scenario's)")
    parser.add_argument("--seed", type=_seed, default=None,
                        help="seed of every random stream, or 'none' for fresh noise from the "
                             "OS (deployment; the drawn seed is printed and stored so the drive "
                             "can be replayed) (default: the scenario's)")
    parser.add_argument("--n", type=int, default=None,
                        help="estimation samples per certificate (default: the scenario's)")
    parser.add_argument("--interval", choices=("safe_set", "conformal"), default=None,
                        help="classification interval: safe_set (the paper's; assumes g right on "
                             "the clean frame) or conformal (robust conformal, no such "
                             "assumption; calibrates before the drive); default: the scenario's")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop after S simulated seconds (default: the scenario's t_final_s;"
                             " 0 there means: until the route's end)")
    parser.add_argument("--designs", metavar="FILE", default=None,
                        help="design table from `synthesize --out`; the drive uses the vehicle, "
                             "settings and conditions it was synthesized for (default: "
                             "synthesize now)")
    parser.add_argument("--vehicle", metavar="FILE", default=None,
                        help="vehicle YAML; with --designs it must equal the design file's "
                             "vehicle (default: the design file's, else the shipped vehicle)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--plot", metavar="PNG", default=None,
                        help="write lateral offset, speed and interval vs truth to this PNG")
    parser.add_argument("--meshcat", metavar="HTML", default=None,
                        help="record the drive in Meshcat to this standalone HTML page")
    parser.add_argument("--out", metavar="TAPE", default=None,
                        help="write the tape(s) to this .csv or .npz file")


def check(args) -> None:
    """Options, output paths, ``--vehicle`` and the scenario file, before torch and cvxpy are
    imported (``cli.main`` runs this first; the scenario's schema imports pydrake)."""
    from drake_cert.config import load_vehicle
    from drake_cert.errors import ConfigError

    _check_outputs(args)
    if args.compare and args.pipeline is not None:
        raise ConfigError(f"--compare drives both pipelines; leave out --pipeline "
                          f"{args.pipeline} (or leave out --compare)")
    if args.vehicle:
        load_vehicle(args.vehicle)
    from drake_cert.config import load_conditions
    from drake_cert.systems.scenario import load_scenario, scenario_path

    scenario = load_scenario(args.scenario)
    if args.designs is None:  # a design file may carry conditions of its own: checked later
        try:
            load_conditions().preset(scenario.perception.preset)
        except ConfigError as e:  # name the file the preset came from
            raise ConfigError(f"{scenario_path(args.scenario)}: perception.preset: {e}"
                              ) from None


def _check_outputs(args) -> None:
    from drake_cert.errors import ConfigError
    from drake_cert.io import check_writable

    for option, path, suffixes in (("--plot", args.plot, (".png",)),
                                   ("--meshcat", args.meshcat, (".html", ".htm")),
                                   ("--out", args.out, (".csv", ".npz"))):
        if path is None:
            continue
        if not path.lower().endswith(suffixes):
            raise ConfigError(f"{option} {path}: expected a {' or '.join(suffixes)} file")
        check_writable(path, option)
    if args.eps is not None and not (args.eps >= 0 and args.eps < float("inf")):
        raise ConfigError(f"--eps {args.eps!r} must be a finite number >= 0")
    if args.duration is not None and not (0 < args.duration < float("inf")):
        raise ConfigError(f"--duration {args.duration!r} must be a positive number of seconds")
    if args.n is not None and args.n <= 0:
        raise ConfigError(f"--n {args.n} must be a positive integer")
    if isinstance(args.seed, int) and args.seed < 0:
        raise ConfigError(f"--seed {args.seed} must be >= 0")


def _seed(text: str) -> int | str:
    """An integer seed, or "none" (fresh noise from the operating system)."""
    import argparse

    if text.strip().lower() in ("none", "null"):
        return "none"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer or 'none'") from None


def _setup(args) -> dict:
    """Vehicle, settings, conditions and designs of the drive: a design file's own (a
    ``--vehicle`` that differs from it is refused), or the shipped files and a fresh table."""
    import dataclasses

    from drake_cert.config import load_conditions, load_settings, load_vehicle
    from drake_cert.errors import ConfigError

    vehicle = load_vehicle(args.vehicle) if args.vehicle else None
    if not args.designs:
        from drake_cert.synthesis.table import synthesize_table

        vehicle, conditions, settings = vehicle or load_vehicle(), load_conditions(), \
            load_settings()
        return dict(vehicle=vehicle, settings=settings, conditions=conditions,
                    designs=synthesize_table(vehicle, conditions, settings))
    from drake_cert.synthesis.design_io import load_design_file

    table = load_design_file(args.designs)
    if vehicle is not None and vehicle != table.vehicle:
        mine, theirs = dataclasses.asdict(vehicle), dataclasses.asdict(table.vehicle)
        field = next(k for k in mine if mine[k] != theirs[k])
        raise ConfigError(f"--vehicle {args.vehicle}: {field} = {mine[field]!r}, but "
                          f"{args.designs} was synthesized for {field} = {theirs[field]!r}; "
                          "synthesize designs for this vehicle (drake-cert synthesize "
                          "--vehicle FILE)")
    return dict(vehicle=table.vehicle, settings=table.settings,
                conditions=table.conditions or load_conditions(), designs=list(table.designs))


def run(args) -> int:
    _check_outputs(args)
    pipelines = PIPELINES if args.compare else (args.pipeline,)
    # Scenarios are rebuilt from these choices in each worker (Drake's SimulatorConfig inside a
    # scenario does not pickle); loading one here first reports a bad scenario in one line.
    choices = [dict(scenario=args.scenario, n=args.n, pipeline=p, attack=args.attack,
                    eps=args.eps, seed=None if args.seed == "none" else args.seed,
                    duration=args.duration, interval=args.interval) for p in pipelines]
    first = _scenario_for(choices[0])
    if args.eps is not None and first.attack.kind not in ("sa", "ea"):
        from drake_cert.errors import ConfigError

        raise ConfigError(f"--eps {args.eps:g} is the budget of an attack, and the drive has "
                          f"none (attack {first.attack.kind!r}): give --attack sa or ea with it")
    seed_source = "scenario"
    if args.seed == "none" or first.seed is None:  # one draw, shared by every pipeline
        from drake_cert.systems.driving import entropy_seed

        seed, seed_source = entropy_seed(), "os-entropy"
        choices = [dict(c, seed=seed) for c in choices]
    common = _setup(args)
    from drake_cert.systems.driving import (
        check_initial_speed,
        check_look_ahead,
        check_perception_budget,
        check_route_is_seen,
        moving_envelope,
    )

    table, _ = moving_envelope(common["designs"], common["conditions"], first.perception.preset)
    check_route_is_seen(first, table)
    check_look_ahead(first, table)
    check_initial_speed(first, table)
    for choice in choices:
        check_perception_budget(_scenario_for(choice), common["conditions"], table)
    if len(choices) == 1:
        results = [_drive_with_bar(choices[0], common, position=0)]
    else:  # one process per pipeline: the drives are independent, the machine has 2+ cores
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(len(choices),
                                 mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = [pool.submit(_drive_with_bar, c, common, i)
                       for i, c in enumerate(choices)]
            results = [f.result() for f in futures]
    for r in results:
        r.summary["seed_source"] = seed_source
    _write_outputs(args, results)
    if args.json:
        out = [r.summary for r in results]
        print(json.dumps(out[0] if len(out) == 1 else out, indent=None))
    else:
        print(format_summaries([r.summary for r in results]))
    return 0


def _scenario_for(choices: dict):
    """The scenario (shipped name or file) with the command line's choices applied: a dict
    of ``scenario``, ``n``, ``pipeline``, ``attack``, ``eps``, ``seed`` and optionally
    ``duration`` and ``interval`` (None: the scenario's own)."""
    import dataclasses

    from drake_cert.systems.driving import with_overrides
    from drake_cert.systems.scenario import load_scenario

    n, duration, interval = choices["n"], choices.get("duration"), choices.get("interval")
    pipeline, attack, eps, seed = (choices["pipeline"], choices["attack"], choices["eps"],
                                   choices["seed"])
    loaded = load_scenario(choices["scenario"])
    if n is not None:
        loaded = dataclasses.replace(loaded, perception=dataclasses.replace(loaded.perception,
                                                                            n=n))
    if duration is not None:
        loaded = dataclasses.replace(loaded, t_final_s=float(duration))
    if interval is not None:
        loaded = dataclasses.replace(loaded, perception=dataclasses.replace(loaded.perception,
                                                                            interval=interval))
    return with_overrides(loaded, pipeline=pipeline, attack=attack, eps=eps, seed=seed)


def _drive_with_bar(choices: dict, common: dict, position: int):
    """Drive one scenario with a progress bar in simulated seconds (runs in a worker too)."""
    from drake_cert.certification.sampler import retain_freed_memory
    from drake_cert.cli.progress import progress_bar
    from drake_cert.systems.driving import DriveProgress, drive_scenario

    retain_freed_memory()  # a --compare worker process runs this, not cli.main
    scenario = _scenario_for(choices)

    def calibration_bar(frames):
        return progress_bar(frames, unit="frame", position=position, leave=False,
                            desc=f"{scenario.name}: calibrating the conformal set")

    horizon = scenario.route_length_m / 10.0  # a guess; the bar grows past it if needed
    with progress_bar(total=round(horizon, 1), unit="sim s", position=position,
                      desc=f"{scenario.name} {scenario.perception.pipeline}",
                      bar_format="{l_bar}{bar}| {n:.1f} sim s [{elapsed}]") as bar:
        return drive_scenario(scenario, progress=DriveProgress(drive=bar.update,
                                                               calibration=calibration_bar),
                              **common)


def per_axle_design_lines(summaries, ratio: float) -> list[str]:
    """For a per-axle vehicle: the design intervals each drive used, front and rear tire
    (kN/rad), from the summary's ``design_intervals_n_per_rad`` when present."""
    lines = []
    for s in summaries:
        for lo, hi in s.get("design_intervals_n_per_rad") or ():
            lines.append(f"  {s['pipeline']}: design [{lo / 1e3:.1f}, {hi / 1e3:.1f}] kN/rad "
                         f"front, [{ratio * lo / 1e3:.1f}, {ratio * hi / 1e3:.1f}] rear")
    return lines


def format_summaries(summaries: list[dict]) -> str:
    """A small side-by-side table of the drives."""
    keys = (("pipeline", "{}"), ("attack", "{}"), ("left_lane", "{}"),
            ("peak_abs_e1_m", "{:.3f}"), ("time_left_lane_s", "{:.2f}"),
            ("mean_speed_mps", "{:.2f}"), ("min_speed_mps", "{:.2f}"),
            ("distance_m", "{:.1f}"), ("interval_covers_true_fraction", "{:.3f}"),
            ("design_covers_true_fraction", "{:.3f}"), ("time_unprotected_s", "{:.2f}"),
            ("abstention_fraction", "{:.3f}"), ("certified_wrong_fraction", "{:.3f}"),
            ("envelope_fraction", "{:.3f}"),
            ("envelope_time_fraction", "{:.3f}"),
            ("certificate_failure_bound", "{:.4f}"), ("interval", "{}"),
            ("tolerated_wrong_frames", "{}"), ("looks_per_side", "{}"),
            ("frame_miscoverage", "{:.4f}"), ("calibration_failure_bound", "{:.4f}"),
            ("guarantee_failure_bound", "{:.2e}"),
            ("design_switches", "{}"), ("switching_method", "{}"),
            ("switching_certificate_met", "{}"), ("loop_switching_decay_per_s", "{:.3f}"),
            ("ending", "{}"), ("simulated_s", "{:.1f}"), ("real_time_factor", "{:.2f}"),
            ("decision", "{}"), ("mean_samples_per_tick", "{:.0f}"), ("precision", "{}"),
            ("backend", "{}"))
    s0 = summaries[0]
    source = " from OS entropy" if s0.get("seed_source") == "os-entropy" else ""
    lines = [f"scenario {s0['scenario']} (seed {s0['seed']}{source})"]
    vehicle = s0.get("vehicle")
    if vehicle:
        front = vehicle["tire_stiffness_scale"]
        rear = vehicle.get("rear_tire_stiffness_scale") or front
        tires = f"x{front:g}" if rear == front else f"front x{front:g}, rear x{rear:g}"
        lines.append(f"vehicle: mass {vehicle['mass_kg']:g} kg, lf {vehicle['lf_m']:g} m, "
                     f"lr {vehicle['lr_m']:g} m, tire stiffness {tires}")
        if rear != front:
            lines.append(f"  per axle: every interval is the front tire's C; the rear tire's is "
                         f"{rear / front:.4g} C (--plot shows both)")
            lines += per_axle_design_lines(summaries, rear / front)
    for key, fmt in keys:
        cells = []
        for s in summaries:
            v = s.get(key)
            cells.append("-" if v is None else fmt.format(v))
        lines.append(f"  {key:<30}" + "".join(f"{c:>14}" for c in cells))
    for s in summaries:
        for warning in s.get("warnings") or ():
            lines.append(f"  WARNING: {s['pipeline']}: {warning}")
        if s.get("standing_assumption"):
            lines.append(f"  NOTE: {s['pipeline']} ({s['interval']} interval): the guarantee "
                         "assumes the smoothed classifier right on the clean frame (the "
                         "standing assumption, DESIGN 3.4); --interval conformal drops it")
    return "\n".join(lines)


def _write_outputs(args, results) -> None:
    from drake_cert.io import atomic_write_bytes, atomic_write_text

    if args.plot:
        from drake_cert.systems.drive_plot import drive_figure_png

        atomic_write_bytes(args.plot, drive_figure_png(results))
    if args.meshcat:
        from drake_cert.systems.meshcat_view import record_drives

        meshcat = record_drives({r.summary["pipeline"]: r.tape for r in results},
                                results[0].route, lane_width_m=results[0].lane_width_m)
        atomic_write_text(args.meshcat, meshcat.StaticHtml())
    if args.out:
        from drake_cert.systems.drive_plot import tape_bytes

        atomic_write_bytes(args.out, tape_bytes(results, args.out))
