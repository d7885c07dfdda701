"""``drake-cert synthesize``: gains, filter gain and safe speed for every label range.

Loads the vehicle, road conditions and settings (shipped defaults unless given), synthesizes
one design per contiguous label range of each preset (``drake_cert.synthesis.table``) and prints a
table (or ``--json`` on stdout). ``--out FILE`` writes the design table as YAML (atomically,
with schema version and provenance) for ``drake-cert verify`` and the simulator. Exit 0 on
success, also when some ranges have no safe speed (they say which condition failed); 1 when
no range has a safe speed (nothing is written; the message names the binding condition,
almost always the sign of a unit mistake in a vehicle file); 2 on bad input. The switching
certificate of each preset (docs/design.md 5.6) is computed and summarised on stderr, and
written with the table.
"""

from __future__ import annotations

import argparse
import json
import math
import sys


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--vehicle", metavar="FILE", default=None,
                        help="vehicle YAML (default: the shipped Rajamani car)")
    parser.add_argument("--conditions", metavar="FILE", default=None,
                        help="road conditions and presets YAML (default: shipped)")
    parser.add_argument("--settings", metavar="FILE", default=None,
                        help="controller and synthesis settings YAML (default: shipped)")
    parser.add_argument("--out", metavar="FILE", default=None,
                        help="write the design table here (YAML); default: print only")
    parser.add_argument("--json", action="store_true",
                        help="print the designs as JSON on stdout (machine-readable)")
    parser.add_argument("--gains", choices=("joint", "separate"), default="joint",
                        help="joint (default): every design's gain from one LMI with a common "
                             "Lyapunov matrix, so switching among them is stable at any rate; "
                             "separate: one LMI per range (then switching rests on an average "
                             "dwell time, which the car does not enforce; drives report "
                             "whether it was met)")


def design_record(design) -> dict:
    """JSON record of one design: every saved field plus ``stiffness_interval``."""
    from drake_cert.synthesis.design_io import design_to_dict

    record = design_to_dict(design)
    record["margins"] = {k: (v if math.isfinite(v) else None)  # JSON has no infinities
                         for k, v in record["margins"].items()}
    record["stiffness_interval"] = [design.stiffness_lo_n_per_rad, design.stiffness_hi_n_per_rad]
    return record


def format_table(designs) -> str:
    """Readable table: labels, interval, k_m, k, speed, the limit that binds it, and the failed
    condition or the margins.

    Label ranges are written as ``simulate --labels`` reads them (``a+b``)."""
    from drake_cert.config import format_label_range

    rows = [("labels", "interval (kN/rad)", "k_m", "k", "speed (m/s)", "limited by",
             "failed / margins")]
    for d in designs:
        if d.failed_condition:
            note = f"FAILED: {d.failed_condition}"
        else:
            note = ", ".join(f"{k}={v:.3g}" for k, v in d.margins.items()
                             if k != "gain_decay_per_s")
        rows.append((
            format_label_range(d.labels) or "(interval)",
            f"{d.stiffness_lo_n_per_rad / 1e3:g}-{d.stiffness_hi_n_per_rad / 1e3:g}",
            "[" + " ".join(f"{x:.3g}" for x in d.k_m) + "]",
            f"{d.filter_gain:g}",
            f"{d.speed_mps:.2f}",
            d.speed_limited_by or "-",
            note,
        ))
    widths = [max(len(r[i]) for r in rows) for i in range(6)]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r[:6], widths, strict=True)) + "  "
                     + r[6] for r in rows)


def format_joint_solve(report: dict) -> str:
    """One line: how the joint gain program was solved and whether its solution was kept."""
    how = "rescaled, " if report["rescaled"] else ""
    if not report["accepted"]:
        return (f"joint gains: Clarabel {report['solver_status']} ({how}no certifying solution): "
                "every range uses its own gain LMI")
    note = ("" if report["solver_status"] == "optimal" else
            " (kept: its matrix proves the decay at every corner, docs/design.md 5.6)")
    cond_x = report["lyapunov_condition_number"]
    return (f"joint gains: Clarabel {report['solver_status']}{note}; {how}matrix proves "
            f"{report['proved_decay_per_s']:.4g}/s, cond X {cond_x:.3g}")


def format_capped(capped) -> str:
    """One line per design whose filter gain was lowered so its preset's L1 loops share a
    matrix (:func:`drake_cert.synthesis.table.with_switchable_l1_loops`)."""
    return "\n".join(
        f"filter gain of {'+'.join(labels)} capped {k0:.4g} -> {k1:.4g} 1/s so its preset's L1 "
        f"loops share a Lyapunov matrix: safe speed {v0:.2f} -> {v1:.2f} m/s"
        for labels, k0, k1, v0, v1 in capped)


def format_switching(certificates) -> str:
    """One line per preset: the switching certificate's method, decay rate and dwell for the
    state-feedback loops, and whether the L1 loops have a common matrix (docs/design.md 5.6)."""
    lines = []
    for c in certificates:
        if c.method == "none":
            lines.append(f"switching ({c.family}): no design with a safe speed")
            continue
        what = ("common Lyapunov matrix, any switching rate" if c.method == "common" else
                f"average dwell {c.dwell_time_s:.3g} s (not enforced by the car)")
        if c.loop_lyapunov_matrix is not None:
            loops = (f"L1 loops: common matrix on [s, u - u_ff], decay "
                     f"{c.loop_decay_rate_per_s:.3g}/s, any switching rate (the estimate carried "
                     "across a switch)")
        elif c.loop_modes:
            loops = (f"L1 loops: no common matrix; one per design, decay "
                     f"{c.loop_decay_rate_per_s:.3g}/s, average dwell {c.loop_dwell_time_s:.3g} s "
                     "(not enforced by the car; each drive says whether it kept it)")
        else:
            loops = "L1 loops: no common matrix, switching among them NOT certified"
        lines.append(f"switching ({c.family}): state-feedback loops {c.method}: {what}; decay "
                     f"{c.decay_rate_per_s:.3g}/s over {len(c.designs_covered)} designs; {loops}")
    return "\n".join(lines)


def binding_condition(designs) -> str:
    """The condition that fails most often among designs without a safe speed (first on ties)."""
    failed = [d.failed_condition for d in designs if d.failed_condition]
    return max(dict.fromkeys(failed), key=failed.count) if failed else "none"


def no_safe_speed_note(stopped) -> str:
    """What to change when some label ranges have no safe speed (the car stops there)."""
    from drake_cert.config import format_label_range

    names = ", ".join(f"{format_label_range(d.labels)} ({d.failed_condition})" for d in stopped)
    hint = {"l1_condition": "the L1 condition fails up to the filter gain the sample period "
                            "allows: give the vehicle's tires per axle if they differ "
                            "(docs/usage.md), or a shorter controller.sample_period_s "
                            "(docs/design.md 5.3a)",
            "grip": "the tires cannot hold the design curve at any speed: check the "
                    "conditions' friction and synthesis.normalised_slip_max",
            }.get(binding_condition(stopped), "see docs/design.md 5.3 for the failing condition")
    return (f"{len(stopped)} label range{'s have' if len(stopped) > 1 else ' has'} no safe "
            f"speed, the car stops there: {names}; {hint}")


def check(args: argparse.Namespace) -> None:
    """``--out`` writable and the three files loaded and checked (``cli.main`` runs this
    before cvxpy and pydrake's systems are imported); keeps them as ``args.loaded``."""
    from drake_cert.config import load_conditions, load_settings, load_vehicle

    if args.out:
        from drake_cert.io import check_writable

        check_writable(args.out, "--out")  # before the synthesis, not after it
    args.loaded = (load_vehicle(args.vehicle), load_conditions(args.conditions),
                   load_settings(args.settings))


def run(args: argparse.Namespace) -> int:
    from drake_cert.cli.progress import progress_bar
    from drake_cert.errors import ConfigError
    from drake_cert.io import provenance
    from drake_cert.synthesis.design_io import (
        DesignTable,
        save_design_table,
        with_switching_certificates,
    )
    from drake_cert.synthesis.table import DesignCache, joint_solve_report, synthesize_table

    if not hasattr(args, "loaded"):
        check(args)
    vehicle, conditions, settings = args.loaded

    def progress(ranges):
        return progress_bar(ranges, desc="synthesize", unit="range", leave=False)

    cache = DesignCache()
    designs = synthesize_table(vehicle, conditions, settings, progress, gains=args.gains,
                               cache=cache)
    joint = joint_solve_report(cache)
    if not any(d.has_safe_speed for d in designs):
        print(format_table(designs))
        print(f"drake-cert synthesize: no design has a safe speed; binding condition: "
              f"{binding_condition(designs)} (check the vehicle file's units: kg, kg m^2, m); "
              "nothing written", file=sys.stderr)
        return 1
    prov = provenance(seed=None)  # deterministic: no seed
    if joint is not None:
        prov["joint_gain_solve"] = joint
        print(format_joint_solve(joint), file=sys.stderr)
    if cache.capped:
        prov["filter_gains_capped"] = [
            {"labels": list(labels), "filter_gain_before": k0, "filter_gain": k1,
             "speed_before_mps": v0, "speed_mps": v1} for labels, k0, k1, v0, v1 in cache.capped]
        print(format_capped(cache.capped), file=sys.stderr)
    table = with_switching_certificates(DesignTable(designs, vehicle, settings, prov, conditions))
    print(format_switching(table.switching), file=sys.stderr)
    stopped = [d for d in designs if not d.has_safe_speed]
    if stopped:
        print(no_safe_speed_note(stopped), file=sys.stderr)
    if args.out:
        try:
            save_design_table(args.out, table)
        except OSError as e:
            raise ConfigError(f"cannot write --out {args.out}: {e.strerror}") from None
        print(f"wrote {len(designs)} designs to {args.out}", file=sys.stderr)
    if args.json:
        from drake_cert.synthesis.switching import certificate_to_dict

        json.dump({"schema_version": prov["schema_version"], "provenance": prov,
                   "designs": [design_record(d) for d in designs],
                   "switching": [certificate_to_dict(c) for c in table.switching]},
                  sys.stdout, indent=1)
        print()
    else:
        print(format_table(designs))
    return 0
