"""The drive's conformal calibration per stiffness bin, checked on held-out frames (docs/design.md
3.6): for each label and bin, the calibration frames, the order statistic, the threshold and the
miss-rate bound that holds given the calibration, beside the miss rate measured on held-out
frames of the test split (a frame misses when its score, the Clopper-Pearson lower bound at
beta_cal of its own-label votes among n samples, falls below its label's threshold: the
conformal step's event), with a 95% Clopper-Pearson interval; then each label's average, and
the outer tenth of each label's interval (its edges, where misses gather).

The model is evaluated as a shipped scenario's drive evaluates it (backend and precision as
resolved here); the thresholds come from the votes shipped with the model. Held-out votes are
drawn from their own noise root. Prints, writes nothing.

Run: ``.venv/bin/python benchmarks/conformal_bins.py [--scenario dry_to_snow]
[--frames-per-label 1000]`` (about 5 min for robotcar-like on 2 cores).
"""

import argparse
import time

import numpy as np

from drake_cert.certification import conformal as rc
from drake_cert.certification.classifier import SmoothedClassifier
from drake_cert.certification.pac_conformal import bin_edges, bin_index
from drake_cert.certification.sampler import CalibrationSampling, with_precision
from drake_cert.certification.statistics import clopper_pearson_one_sided
from drake_cert.cli.progress import progress_bar
from drake_cert.config import load_conditions
from drake_cert.perception.datasets import load_split
from drake_cert.perception.models import load_model
from drake_cert.systems import driving
from drake_cert.systems.scenario import load_scenario

HELD_OUT_ROOT = 20261205  # noise root of the held-out votes (not the calibration's)


def share_ci(k: int, m: int) -> str:
    """``k/m`` with its two-sided 95% Clopper-Pearson interval."""
    lo, up = clopper_pearson_one_sided(np.array([k]), m, 0.025)
    return f"{k}/{m} = {k / m:.3f} [{lo[0]:.3f}, {up[0]:.3f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="dry_to_snow")
    parser.add_argument("--frames-per-label", type=int, default=1000)
    args = parser.parse_args()
    sc, conditions = load_scenario(args.scenario), load_conditions()
    p = sc.perception
    model = with_precision(load_model(p.preset, p.task, p.sigma), p.precision)
    evaluated = driving._evaluated_model(model, sc, conditions, p.sigma)
    cal = driving.drive_conformal_calibration(evaluated, sc, conditions)
    spec = driving.conformal_votes_spec(sc, conditions)
    test = load_split(p.preset, "test", conditions=conditions,
                      frames_per_class=args.frames_per_label)
    start = time.perf_counter()
    sampling = CalibrationSampling(n=spec.n, batch_size=spec.batch_size, seed=HELD_OUT_ROOT,
                                   progress=lambda it: progress_bar(it, desc="held-out votes"))
    counts = rc.true_label_counts(SmoothedClassifier(evaluated, cal.num_classes, p.sigma),
                                  test.images, test.labels.tolist(), sampling=sampling)
    seconds = time.perf_counter() - start
    scores = rc.calibration_scores(counts, spec.n, cal.beta_cal)
    labels, stiffness = test.labels.numpy(), test.stiffness_n_per_rad.numpy()
    print(f"{args.scenario} ({p.preset}, sigma {p.sigma:g}, {spec.backend} {spec.precision}): "
          f"{len(labels)} held-out frames, n = {spec.n}, {seconds:.0f} s; calibration "
          f"{spec.frames_per_label} frames a label, "
          f"{p.conformal_bins_per_label} bins, target {p.conformal_alpha_c:g}, delta_cal "
          f"{cal.delta_cal:g}: alpha_c {cal.alpha_c:.4f}, per-frame p {cal.alpha_total:.4f}")
    print("| label | stiffness bin (kN/rad) | calibration frames | k | bin threshold | bound | "
          "held-out miss at the label threshold |")
    print("|---|---|---|---|---|---|---|")
    worst = (0.0, "")
    for lab, (name, lo, hi) in enumerate(spec.conditions):
        q = cal.thresholds[lab]
        mine = labels == lab
        which = bin_index(stiffness[mine], bin_edges(lo, hi, p.conformal_bins_per_label))
        miss = scores[mine] < q
        for b, row in enumerate(cal.bins[lab]):
            k, m = int(miss[which == b].sum()), int((which == b).sum())
            worst = max(worst, (k / m, f"{name} bin {b}"))
            print(f"| {name} | {row.stiffness_lo_n_per_rad / 1e3:.0f}-"
                  f"{row.stiffness_hi_n_per_rad / 1e3:.0f} | {row.frames} | {row.order} | "
                  f"{row.threshold:.3f} | {row.miss_bound:.3f} | {share_ci(k, m)} |")
        print(f"| {name} | all (label threshold {q:.3f}) | {cal.frames_per_label[lab]} | | | | "
              f"{share_ci(int(miss.sum()), int(mine.sum()))} |")
        for side, keep in (("least-grip tenth", stiffness[mine] < lo + 0.1 * (hi - lo)),
                           ("grippiest tenth", stiffness[mine] > hi - 0.1 * (hi - lo))):
            ci = share_ci(int(miss[keep].sum()), int(keep.sum()))
            print(f"| {name} | {side} | | | | | {ci} |")
    print(f"worst bin on held-out frames: {worst[1]}, {worst[0]:.3f} (bound {cal.alpha_c:.3f})")


if __name__ == "__main__":
    main()
