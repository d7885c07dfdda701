"""``drake-cert verify DESIGN``: re-check a saved design or design table independently.

Reloads the file ``drake-cert synthesize --out`` writes (or a single-design file), recomputes
every condition by the separate code path of ``synthesis.verify`` and prints the margins.
With ``--vehicle``, ``--settings``, ``--conditions`` (reference files) the file's embedded
copies must equal them (else exit 1 naming the field) and every condition is recomputed with
them; without them verify checks the file against its own embedded inputs and says so on
stderr (a self-consistent edit of the file would pass). Exit 0 when every design's claims
hold, 1 naming the first failed condition, 2 when a file cannot be read.
"""

from __future__ import annotations

import argparse
import json
import math
import sys


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("design", metavar="DESIGN",
                        help="design table or single-design YAML file")
    parser.add_argument("--vehicle", metavar="FILE", default=None,
                        help="reference vehicle YAML: the file's embedded vehicle must equal it")
    parser.add_argument("--settings", metavar="FILE", default=None,
                        help="reference settings YAML: the file's embedded settings must equal it")
    parser.add_argument("--conditions", metavar="FILE", default=None,
                        help="reference conditions YAML: the file's embedded conditions must "
                             "equal it")
    parser.add_argument("--json", action="store_true",
                        help="print the verification report as JSON on stdout")


def _finite_or_none(margins: dict) -> dict:
    """JSON has no infinities: a margin that could not be computed (-inf) becomes null."""
    return {k: (float(v) if math.isfinite(v) else None) for k, v in margins.items()}


def _report_dict(report) -> dict:
    first = report.first_failure
    return {
        "ok": report.ok,
        "checked_against": report.checked_against,
        "input_failures": [{"condition": c, "message": m} for c, m in report.input_failures],
        "first_failure": None if first is None else {
            "index": first[0], "labels": first[1], "condition": first[2], "message": first[3]},
        "switching_failures": [{"condition": c, "message": m}
                               for c, m in report.switching_failures],
        "notes": list(report.notes),
        "designs": [{"index": d.index, "labels": d.labels, "speed_mps": d.speed_mps,
                     "margins": _finite_or_none(d.margins),
                     "failures": [{"condition": c, "message": m} for c, m in d.failures]}
                    for d in report.designs],
    }


def _format_line(d) -> str:
    status = "ok  " if d.ok else "FAIL"
    margins = ", ".join(f"{k}={v:.4g}" for k, v in d.margins.items())
    return f"{status} [{d.index}] {'+'.join(d.labels) or '(interval)'} " \
           f"speed {d.speed_mps:.2f} m/s: {margins}"


def run(args: argparse.Namespace) -> int:
    from drake_cert.cli.progress import progress_bar
    from drake_cert.config import load_conditions, load_settings, load_vehicle
    from synthesis.design_io import load_design_file
    from synthesis.verify import verify_design_table

    table = load_design_file(args.design)
    references = {
        "vehicle": load_vehicle(args.vehicle) if args.vehicle else None,
        "settings": load_settings(args.settings) if args.settings else None,
        "conditions": load_conditions(args.conditions) if args.conditions else None,
    }
    with progress_bar(total=len(table.designs), desc="verify", unit="design",
                      leave=False) as bar:
        report = verify_design_table(table, lambda i, n: bar.update(1),
                                     **references)
    if report.checked_against == "embedded":
        print("drake-cert verify: checked against the design file's own embedded vehicle, "
              "settings and conditions (give --vehicle/--settings/--conditions to check "
              "against reference files)", file=sys.stderr)
    else:
        print(f"drake-cert verify: checked against the reference {report.checked_against}",
              file=sys.stderr)
    for note in report.notes:
        print(f"drake-cert verify: note: {note}", file=sys.stderr)
    if args.json:
        json.dump(_report_dict(report), sys.stdout, indent=1)
        print()
    else:
        for d in report.designs:
            print(_format_line(d))
    first = report.first_failure
    if first is not None:
        index, labels, condition, message = first
        where = ("the design file" if index is None
                 else f"design {index} ({'+'.join(labels) or 'interval'})")
        print(f"drake-cert verify: {where} fails {condition}: {message}", file=sys.stderr)
        return 1
    print(f"drake-cert verify: all {len(report.designs)} designs hold", file=sys.stderr)
    return 0
