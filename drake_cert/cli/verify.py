"""``drake-cert verify DESIGN``: re-check a saved design or design table independently.

Reloads the file ``drake-cert synthesize --out`` writes (or a single-design file), recomputes
every condition by the separate code path of ``synthesis.verify`` and prints the margins.
Exit 0 when every design's claims hold, 1 naming the first failed condition, 2 when the
file cannot be read.
"""

from __future__ import annotations

import argparse
import json
import math
import sys


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("design", metavar="DESIGN",
                        help="design table or single-design YAML file")
    parser.add_argument("--json", action="store_true",
                        help="print the verification report as JSON on stdout")


def _finite_or_none(margins: dict) -> dict:
    """JSON has no infinities: a margin that could not be computed (-inf) becomes null."""
    return {k: (float(v) if math.isfinite(v) else None) for k, v in margins.items()}


def _report_dict(report) -> dict:
    first = report.first_failure
    return {
        "ok": report.ok,
        "first_failure": None if first is None else {
            "index": first[0], "labels": first[1], "condition": first[2], "message": first[3]},
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
    from tqdm import tqdm

    from synthesis.design_io import load_design_file
    from synthesis.verify import VerificationReport, verify_design

    table = load_design_file(args.design)
    checks = []
    for i, design in enumerate(tqdm(table.designs, desc="verify", unit="design",
                                    file=sys.stderr, leave=False)):
        checks.append(verify_design(design, table.vehicle, table.settings, table.conditions, i))
    report = VerificationReport(checks)
    if args.json:
        json.dump(_report_dict(report), sys.stdout, indent=1)
        print()
    else:
        for d in report.designs:
            print(_format_line(d))
    first = report.first_failure
    if first is not None:
        index, labels, condition, message = first
        print(f"drake-cert verify: design {index} ({'+'.join(labels) or 'interval'}) fails "
              f"{condition}: {message}", file=sys.stderr)
        return 1
    print(f"drake-cert verify: all {len(report.designs)} designs hold", file=sys.stderr)
    return 0
