"""``drake-cert calibrate``: draw the robust conformal calibration votes of a scenario's model
(docs/design.md 3.6) and print its per-bin thresholds and the drive's guarantee inputs.

The votes are what a drive of the scenario reads: shipped beside the model when their spec
matches, else cached, else drawn here with a progress bar. ``--ship`` draws them anew and writes
them beside the model (atomically), as the shipped files were made.
"""

import json
import sys


def configure(parser) -> None:
    parser.add_argument("--scenario", default="dry_to_snow", metavar="NAME|FILE",
                        help="shipped scenario name or scenario file whose perception settings "
                             "(model, backend, conformal_* keys) name the calibration")
    parser.add_argument("--ship", action="store_true",
                        help="draw the votes anew and write them beside the model file "
                             "(<preset>/classify_sigma<S>.calibration.json)")
    parser.add_argument("--json", action="store_true",
                        help="print the calibration (thresholds, bins, bounds) as JSON")


def check(args) -> None:
    from drake_cert.errors import ConfigError
    from drake_cert.systems.scenario import load_scenario

    scenario = load_scenario(args.scenario)
    p = scenario.perception
    if p.task != "classify" or p.interval != "conformal":
        raise ConfigError(f"scenario {scenario.name!r} uses task {p.task!r} with interval "
                          f"{p.interval!r}: only the robust conformal interval (task classify, "
                          "interval conformal) has a calibration to draw")
    args.loaded = scenario


def run(args) -> int:
    from drake_cert.certification.sampler import with_precision
    from drake_cert.certification.shipped_calibration import write_shipped
    from drake_cert.cli.progress import progress_bar
    from drake_cert.config import load_conditions
    from drake_cert.perception.models import load_model, model_path
    from drake_cert.systems import driving

    scenario, conditions = args.loaded, load_conditions()
    p = scenario.perception
    model = with_precision(load_model(p.preset, p.task, p.sigma), p.precision)
    evaluated = driving._evaluated_model(model, scenario, conditions, p.sigma)

    def progress(iterable):
        return progress_bar(iterable, desc="calibration frames", unit="frame")

    votes = driving.conformal_votes(evaluated, scenario, conditions, progress,
                                    refresh=args.ship)
    if args.ship:
        path = write_shipped(model_path(p.preset, p.task, p.sigma), votes)
        print(f"wrote {path}", file=sys.stderr)
    cal = driving.drive_conformal_calibration(evaluated, scenario, conditions)
    if args.json:
        print(json.dumps(cal.to_json(), indent=1))
        return 0
    names = [c[0] for c in votes.spec.conditions]
    print(f"{p.preset} sigma {p.sigma:g} ({votes.spec.backend} {votes.spec.precision}): "
          f"{votes.spec.frames_per_label} frames a label, n = {votes.spec.n}, votes "
          f"{votes.source}; {p.conformal_bins_per_label} stiffness bins a label, target "
          f"{p.conformal_alpha_c:g}, delta_cal {cal.delta_cal:g}")
    for lab, name in enumerate(names):
        rows = ", ".join(f"[{r.stiffness_lo_n_per_rad / 1e3:.0f}-"
                         f"{r.stiffness_hi_n_per_rad / 1e3:.0f}] k {r.order}/{r.frames} "
                         f"q {r.threshold:.3f} <= {r.miss_bound:.3f}" for r in cal.bins[lab])
        print(f"  {name}: threshold {cal.thresholds[lab]:.3f} (t at eps {p.eps:g}: "
              f"{cal.threshold(lab, p.eps):.4f}); bins {rows}")
    print(f"per-frame miss bound in every bin given the calibration: alpha_c {cal.alpha_c:.4f}"
          f" + beta_cal {cal.beta_cal:g} + beta_test {cal.beta_test:g} = {cal.alpha_total:.4f}")
    return 0
