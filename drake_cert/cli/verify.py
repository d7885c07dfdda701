"""``drake-cert verify DESIGN``: re-check a saved design or design table independently.

Reloads the file ``drake-cert synthesize --out`` writes (or a single-design file), recomputes
every condition by the separate code path of ``drake_cert.synthesis.verify`` and prints the margins.
With ``--vehicle``, ``--settings``, ``--conditions`` (reference files) the file's embedded
copies must equal them (else exit 1 naming the field) and every condition is recomputed with
them; without them verify checks the file against its own embedded inputs and says so on
stderr (a self-consistent edit of the file would pass).

Completeness (``--complete``, on by default when ``--conditions`` is given or a table of more
than one design embeds its conditions; ``--no-complete`` verifies the designs alone): the table must
hold a design for every label range the conditions define, i.e. every run of consecutive
labels of a preset in its friction order, singles and the whole family included (what
``drake-cert synthesize`` writes and the run time selects from); each missing range is named
on its own line. ``--json`` prints the report on stdout: the verdict, per design its label
range, interval, speed, whether it holds and why not, and the completeness and switching
verdicts. A table with more than one design with a safe speed must carry its switching
certificates (``--no-switching``: a note instead). Exit 0 when everything holds, 1 naming
the first failed condition (and every missing label range), 2 when a file cannot be read or
completeness cannot be checked.
"""

from __future__ import annotations

import argparse
import json
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
    parser.add_argument("--complete", action=argparse.BooleanOptionalAction, default=None,
                        help="fail (exit 1) when the table lacks a design for a label range of "
                             "the conditions (the reference --conditions, else the embedded "
                             "ones); default: on when --conditions is given or a table of "
                             "more than one design embeds its conditions (--no-complete: "
                             "the designs alone)")
    parser.add_argument("--switching", action=argparse.BooleanOptionalAction, default=True,
                        help="fail (exit 1) when a table with more than one design with a "
                             "safe speed has no switching certificate (default; "
                             "--no-switching: a note instead). A certificate that is present "
                             "is always rechecked")
    parser.add_argument("--json", action="store_true",
                        help="print the verification report as JSON on stdout (verdict, "
                             "per-design verdicts, completeness, switching)")


def _format_line(d) -> str:
    status = "ok  " if d.ok else "FAIL"
    margins = ", ".join(f"{k}={v:.4g}" for k, v in d.margins.items())
    limit = f" (limited by {d.limited_by})" if d.limited_by else ""
    speed = (f"speed {d.speed_mps:.2f} m/s{limit}" if d.speed_mps > 0
             else "no safe speed (certified: the car stops)")
    return f"{status} [{d.index}] {'+'.join(d.labels) or '(interval)'} {speed}: {margins}"


def claims_summary(designs) -> str:
    """What the verified designs claim, by kind: "N claims hold: S safe speeds, Z ranges
    certified to have none (labels, ...)"."""
    none = [d for d in designs if not d.speed_mps > 0]
    n, fast = len(designs), len(designs) - len(none)
    text = (f"{n} claim{'s hold' if n != 1 else ' holds'}: {fast} safe speed"
            f"{'s' if fast != 1 else ''}, {len(none)} range{'s' if len(none) != 1 else ''} "
            "certified to have none")
    if none:
        text += f" ({', '.join('+'.join(d.labels) or '(interval)' for d in none)}: the car " \
                "stops there; a route that needs such a range cannot be driven)"
    return text


def run(args: argparse.Namespace) -> int:
    from drake_cert.cli.progress import progress_bar
    from drake_cert.config import load_conditions, load_settings, load_vehicle
    from drake_cert.synthesis.design_io import load_design_file
    from drake_cert.synthesis.verify import (
        COMPLETENESS,
        completeness_reference,
        verify_design_table,
    )

    table = load_design_file(args.design)
    references = {
        "vehicle": load_vehicle(args.vehicle) if args.vehicle else None,
        "settings": load_settings(args.settings) if args.settings else None,
        "conditions": load_conditions(args.conditions) if args.conditions else None,
    }
    if args.complete is None and references["conditions"] is None:
        # a table (more than one design) that embeds its conditions is checked complete
        # against them, so one missing a label range does not pass as a whole
        args.complete = table.conditions is not None and len(table.designs) > 1 or None
    completeness_reference(table, references["conditions"], args.complete)  # exit 2 early
    with progress_bar(total=len(table.designs), desc="verify", unit="design",
                      leave=False) as bar:
        report = verify_design_table(table, lambda i, n: bar.update(1),
                                     complete=args.complete, require_switching=args.switching,
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
        json.dump(report.to_dict(), sys.stdout, indent=1)
        print()
    else:
        for d in report.designs:
            print(_format_line(d))
    first = report.first_failure
    if first is not None and first[2] != COMPLETENESS:
        index, labels, condition, message = first
        where = ("the design file" if index is None
                 else f"design {index} ({'+'.join(labels) or 'interval'})")
        print(f"drake-cert verify: {where} fails {condition}: {message}", file=sys.stderr)
    for _, message in report.completeness_failures:
        print(f"drake-cert verify: incomplete table: {message}", file=sys.stderr)
    if report.completeness_failures:
        print("drake-cert verify: (--no-complete verifies the designs it holds alone)",
              file=sys.stderr)
    if not report.ok:
        return 1
    complete = (f"; complete: a design for each of the {report.label_ranges} label ranges of "
                f"the {report.completeness_against}" if report.completeness_checked else "")
    print(f"drake-cert verify: {claims_summary(report.designs)}{complete}", file=sys.stderr)
    return 0
