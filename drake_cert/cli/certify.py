"""``drake-cert certify``: certify a (smoothed) perception model on test frames, maybe attacked.

Prints accuracy, mean certified radius (abstain = 0), abstain rate and run-time interval
statistics (width, coverage of the true stiffness); ``--json`` prints every number and the
per-frame records on stdout. ``--sigma 0`` evaluates the base model f (no certificate).
``--frames-dir DIR`` certifies a user's class-per-folder frames (``DIR/<label>/*.png``, as
``drake-cert generate --export`` writes them, with an optional ``stiffness.csv``) instead of
the synthetic test split. torch is imported only when the command runs (``--help`` is fast).
"""

from __future__ import annotations

import argparse
import json
import math

from drake_cert.errors import ConfigError

DATA_SEED = 0  # the synthetic splits the shipped models were trained and tested on


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text} must be a positive integer")
    return value


def _finite(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text} must be finite")
    return value


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", required=True, help="carla-like, rtk-like or robotcar-like")
    parser.add_argument("--sigma", type=_finite, required=True,
                        help="smoothing noise (0: the base model f, no certificate)")
    parser.add_argument("--task", choices=("classify", "regress"), default="classify",
                        help="classify: smoothed classifier; regress: median-smoothed "
                             "stiffness regressor")
    parser.add_argument("--attack", choices=("none", "sa", "ea"), default="none",
                        help="PGD stability (sa) or efficiency (ea) attack at budget --eps")
    parser.add_argument("--eps", type=_finite, default=0.5,
                        help="L2 budget in [0,1] pixel space: attack and run-time interval")
    parser.add_argument("--n", type=_positive_int, default=10_000, help="estimation samples")
    parser.add_argument("--n0", type=_positive_int, default=100, help="selection samples")
    parser.add_argument("--alpha", type=_finite, default=0.001, help="failure probability")
    parser.add_argument("--frames", type=_positive_int, default=50, help="test frames")
    parser.add_argument("--batch-size", type=_positive_int, default=1000,
                        help="noisy copies evaluated per forward pass")
    parser.add_argument("--seed", type=int, default=0, help="noise, attack and frame choice")
    parser.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    parser.add_argument("--compile", choices=("auto", "on", "off"), default="auto",
                        help="torch.compile the model (auto: when the run draws >= 50k samples)")
    parser.add_argument("--attack-steps", type=_positive_int, default=20,
                        help="PGD steps of the attack")
    parser.add_argument("--calibration-per-class", type=_positive_int, default=100,
                        help="regression: calibration frames per label for the conformal beta")
    parser.add_argument("--calibration-n", type=_positive_int, default=1000,
                        help="regression: samples per calibration frame")
    parser.add_argument("--size", type=_positive_int, default=None,
                        help="frame side in pixels (default: the model's training size)")
    parser.add_argument("--models", default=None, help="model folder (default: shipped models)")
    parser.add_argument("--frames-dir", metavar="DIR", default=None,
                        help="certify these class-per-folder frames (DIR/<label>/*.png, labels "
                             "of --preset; resized to the model's size) instead of the "
                             "synthetic test split (default: the test split)")
    parser.add_argument("--precision", choices=("auto", "fp32", "bf16"), default="auto",
                        help="model arithmetic (auto: fp32 where ONNX Runtime is installed, else "
                             "bf16 where the CPU has it natively, else fp32; "
                             "DRAKE_CERT_PRECISION=fp32|bf16 fixes what auto means); "
                             "certificates are those of the model as evaluated")
    parser.add_argument("--conformal", action="store_true",
                        help="classify: also the robust conformal interval (holds the true "
                             "stiffness w.p. >= 1 - alpha_total = 0.99 under any L2 "
                             "perturbation <= eps, without assuming the classifier is right)")
    parser.add_argument("--conformal-per-class", type=_positive_int, default=200,
                        help="calibration frames per label for --conformal (>= 124 for a "
                             "non-trivial threshold; samples per frame: --calibration-n)")
    parser.add_argument("--json", action="store_true", help="print all results as JSON")


def check(args: argparse.Namespace) -> None:
    """Before torch is imported (``cli.main`` runs this first): a ``--size`` whose frames
    would not fit in memory, with how much they would take."""
    from drake_cert.config import check_frame_size

    if args.size is not None:
        check_frame_size(args.size, "--size", args.batch_size)


def settings_from_args(args: argparse.Namespace):
    """The validated :class:`CertifySettings` of the command line."""
    from drake_cert.experiments.perception_eval import CertifySettings

    settings = CertifySettings(
        preset=args.preset, sigma=args.sigma, task=args.task, attack=args.attack, eps=args.eps,
        n0=args.n0, n=args.n, alpha=args.alpha, frames=args.frames, batch_size=args.batch_size,
        seed=args.seed, device=args.device, compile=args.compile, attack_steps=args.attack_steps,
        calibration_per_class=args.calibration_per_class, calibration_n=args.calibration_n,
        conformal=getattr(args, "conformal", False),
        conformal_per_class=getattr(args, "conformal_per_class", 200),
        precision=getattr(args, "precision", "auto"))
    settings.validate()
    return settings


def run(args: argparse.Namespace) -> int:
    from drake_cert.certification.sampler import resolve_device
    from drake_cert.certification.seeds import frame_choice_seed
    from drake_cert.cli.progress import progress_bar
    from drake_cert.config import load_conditions
    from drake_cert.experiments.perception_eval import (
        CalibrationInputs,
        EvalFrames,
        certify_classifier,
        certify_regressor,
        json_safe,
        select_frames,
    )
    from drake_cert.io import provenance
    from drake_cert.perception.datasets import load_split
    from drake_cert.perception.models import check_sigma, load_model, training_of

    settings = settings_from_args(args)
    table = load_conditions()
    table.preset(settings.preset)  # ConfigError naming the preset
    check_sigma(settings.sigma)
    resolve_device(settings.device)
    model = load_model(settings.preset, settings.task, settings.sigma, args.models)
    size = model_frame_size(model, args.size)
    test = frames_to_certify(args.frames_dir, settings, table, size)
    index = select_frames(test.labels, min(settings.frames, len(test)),
                          frame_choice_seed(settings.seed))
    images, labels = test.images[index], test.labels[index]
    stiffness = test.stiffness_n_per_rad[index]

    def progress(it):  # on stderr, also with --json (its JSON is on stdout): a log shows it
        return progress_bar(it, desc=f"certify {settings.preset} sigma={settings.sigma:g}",
                            leave=False)

    if settings.task == "classify":
        conformal_cal = None
        if settings.conformal and settings.sigma > 0:
            cal = load_split(settings.preset, "calibration", seed=DATA_SEED, size=size,
                             frames_per_class=settings.conformal_per_class)
            conformal_cal = (cal.images, cal.labels)
        frames = EvalFrames(images, labels, stiffness, tuple(test.label_names))
        records, summary = certify_classifier(model, frames, table, settings, progress,
                                              CalibrationInputs(frames=conformal_cal))
    else:
        calibration = None
        if settings.sigma > 0:
            cal = load_split(settings.preset, "calibration", seed=DATA_SEED, size=size,
                             frames_per_class=settings.calibration_per_class)
            calibration = (cal.images, cal.stiffness_n_per_rad, cal.labels)
        records, summary = certify_regressor(model, EvalFrames(images, labels, stiffness),
                                             table.envelope(settings.preset), settings, progress,
                                             CalibrationInputs(frames=calibration))
    summary["training"] = training_of(model)
    if args.json:
        print(json.dumps(json_safe({"summary": summary, "records": records,
                                    "provenance": provenance(settings.seed)}), indent=1,
                         allow_nan=False))
    else:
        print(format_summary(summary))
    return 0


def frames_to_certify(frames_dir, settings, table, size: int):
    """A user's class-per-folder frames (``--frames-dir``), else the synthetic test split with
    enough frames per label for ``settings.frames``."""
    from drake_cert.perception.datasets import load_image_folder, load_split

    if frames_dir is not None:
        return load_image_folder(frames_dir, preset=settings.preset, size=size,
                                 conditions=table)
    per_class = math.ceil(settings.frames / len(table.preset(settings.preset).labels))
    return load_split(settings.preset, "test", seed=DATA_SEED, size=size,
                      frames_per_class=per_class)


def model_frame_size(model, size: int | None) -> int:
    """The frame side the model was trained on; ConfigError if ``--size`` asks for another."""
    trained = int(getattr(model, "meta", {}).get("image_size", 64))
    if size is not None and size != trained:
        raise ConfigError(f"--size {size}: the model was trained on {trained}x{trained} "
                          f"frames; certify frames of that size (leave --size out)")
    return trained


def format_summary(s: dict) -> str:
    """Human-readable lines of a summary (see drake_cert.experiments.perception_eval)."""
    head = (f"{s['preset']} {s['task']} sigma={s['sigma']:g} attack={s['attack']} "
            f"eps={s['eps']:g}: {s['frames']} frames")
    if s["task"] == "classify":
        if s["sigma"] == 0:
            return (f"{head} (base model f, no certificate)\n"
                    f"accuracy {s['accuracy']:.3f} (clean {s['clean_accuracy']:.3f})")
        return (f"{head}, n0={s['n0']}, n={s['n']}, alpha={s['alpha']:g}\n"
                f"accuracy {s['accuracy']:.3f} (clean {s['clean_accuracy']:.3f}), "
                f"abstain rate {s['abstain_rate']:.3f}\n"
                f"mean certified radius R_S(a) {_num(s['mean_radius'])} "
                f"(S(a) = all labels, unbounded: {s['unbounded_radius_rate']:.3f}; "
                f"single label: {s['mean_radius_label']:.3f}; abstain = 0)\n"
                f"run-time interval at eps={s['eps']:g}: mean width "
                f"{s['interval_width_mean']:,.0f} N/rad, coverage {s['interval_coverage']:.3f}"
                f", envelope rate {s['envelope_rate']:.3f}\n"
                f"label ranges certified at eps={s['eps']:g}: right {_share(s, 'certified_right')}"
                f", WRONG {_share(s, 'certified_wrong')}, abstain {_share(s, 'interval_abstain')}"
                + _conformal_line(s))
    if s["sigma"] == 0:
        return (f"{head} (base model f, no certificate)\n"
                f"mean abs error {s['mae_n_per_rad']:,.0f} N/rad "
                f"(clean {s['clean_mae_n_per_rad']:,.0f})")
    beta = s["beta_n_per_rad"]
    beta_text = (f"{beta:,.0f} N/rad" if math.isfinite(beta)
                 else "inf (too few calibration frames for alpha_c)")
    return (f"{head}, n={s['n']}, alpha={s['alpha']:g}\n"
            f"median abs error {s['mae_n_per_rad']:,.0f} N/rad, conformal beta {beta_text}\n"
            f"run-time interval at eps={s['eps']:g}: mean width "
            f"{s['interval_width_mean']:,.0f} N/rad (raw {s['raw_width_mean']:,.0f}), "
            f"coverage {s['interval_coverage']:.3f}")


def _conformal_line(s: dict) -> str:
    if "conformal_interval_coverage" not in s:
        return ""
    lo, hi = s["conformal_interval_coverage_ci95"]
    return (f"\nrobust conformal interval at eps={s['eps']:g}: mean width "
            f"{s['conformal_interval_width_mean']:,.0f} N/rad, coverage "
            f"{s['conformal_interval_coverage']:.3f} (95% CI {lo:.3f}-{hi:.3f}; guaranteed >= "
            f"{s['conformal_guarantee']:.3f} without assuming the classifier is right)")


def _share(s: dict, name: str) -> str:
    lo, hi = s[f"{name}_rate_ci95"]
    return f"{s[f'{name}_rate']:.3f} [{lo:.3f}, {hi:.3f}]"


def _num(value) -> str:
    return "-" if value is None else f"{value:.3f}"
