"""Certify a perception model on test frames, optionally under attack (the `certify` command).

One function per task. Each takes the model, the frames and :class:`CertifySettings`, and
returns per-frame records and a summary of plain numbers (metrics are defined in
:func:`summarize_classification` / :func:`summarize_regression`). Frames are taken
round-robin over the classes from a seeded permutation, so any count is balanced.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable, Iterable

import numpy as np
import torch

from drake_cert.certification.attacks import AttackSettings, attack
from drake_cert.certification.classifier import SmoothedClassifier, check_enough_samples
from drake_cert.certification.conformal import (
    ALPHA_C,
    BETA_CAL,
    ConformalLevels,
    calibrate_robust_conformal,
    conformal_interval,
)
from drake_cert.certification.intervals import runtime_classification_interval, runtime_interval
from drake_cert.certification.regressor import MedianSmoothedRegressor, calibrate_conformal
from drake_cert.certification.sampler import (
    CalibrationSampling,
    resolve_precision,
    with_precision,
)
from drake_cert.certification.seeds import stream_seed, streams
from drake_cert.certification.statistics import (
    clopper_pearson_one_sided,
    min_calibration_frames,
    percentile_bound_indices,
)
from drake_cert.config import ConditionsTable
from drake_cert.errors import CertificationError

COMPILE_AUTO_SAMPLES = 50_000  # "auto" compiles from this many samples (pays back ~20 s)


@dataclasses.dataclass(frozen=True)
class CertifySettings:
    """What to certify and how; budgets are L2 in [0, 1] pixel space."""

    preset: str
    sigma: float  # smoothing noise; 0 = the base model f, no certificate
    task: str = "classify"  # "classify" or "regress"
    attack: str = "none"  # "none", "sa" (stability) or "ea" (efficiency)
    eps: float = 0.5  # attack budget and certificate budget of the run-time interval
    n0: int = 100  # selection samples
    n: int = 10_000  # estimation samples
    alpha: float = 0.001  # certificate failure probability
    frames: int = 50  # test frames
    batch_size: int = 1000
    seed: int = 0
    device: str = "cpu"
    compile: str = "auto"  # "auto", "on" or "off"
    attack_steps: int = 20
    attack_noise_draws: int = 8  # SmoothAdv noise draws per PGD step (sigma > 0)
    calibration_per_class: int = 100  # regression: calibration frames per label (Mondrian)
    calibration_n: int = 1000  # regression: samples per calibration frame
    alpha_c: float = 0.01  # regression: conformal miscoverage
    alpha_m: float = 0.001  # regression: level of the calibration median interval
    conformal: bool = False  # classify: also the robust conformal interval (needs calibration)
    conformal_alpha_c: float = ALPHA_C  # its conformal miscoverage (alpha_total adds 2 betas)
    conformal_beta: float = BETA_CAL  # its Monte-Carlo levels (calibration and test each)
    conformal_per_class: int = 200  # its calibration frames per label (>= 1/alpha_c - 1)
    precision: str = "auto"  # the model as evaluated everywhere (attack too): fp32 or bf16;
    # "auto" is resolved on construction (sampler.resolve_precision)

    def __post_init__(self):  # resolve_precision names a bad value in CertificationError
        object.__setattr__(self, "precision", resolve_precision(self.precision))

    def validate(self) -> None:
        if self.task not in ("classify", "regress"):
            raise CertificationError(f"task {self.task!r} is not 'classify' or 'regress'")
        if self.attack not in ("none", "sa", "ea"):
            raise CertificationError(f"attack {self.attack!r} is not one of none, sa, ea")
        if not (math.isfinite(self.sigma) and self.sigma >= 0):
            raise CertificationError(f"sigma = {self.sigma!r} must be a finite number >= 0")
        if not (math.isfinite(self.eps) and self.eps >= 0):
            raise CertificationError(f"eps = {self.eps!r} must be a finite number >= 0")
        for key in ("n0", "n", "frames", "batch_size", "attack_steps", "attack_noise_draws",
                    "calibration_per_class", "calibration_n", "conformal_per_class"):
            if getattr(self, key) <= 0:
                raise CertificationError(f"{key.replace('_', '-')} = {getattr(self, key)} "
                                         "must be a positive integer")
        for key in ("alpha", "alpha_c", "alpha_m", "conformal_alpha_c", "conformal_beta"):
            if not 0 < getattr(self, key) < 1:
                raise CertificationError(f"{key} = {getattr(self, key)!r} must be in (0, 1)")
        if self.compile not in ("auto", "on", "off"):
            raise CertificationError(f"compile = {self.compile!r} is not auto, on or off")
        if self.seed < 0:
            raise CertificationError(f"seed = {self.seed} must be >= 0")
        need = min_calibration_frames(self.alpha_c)
        if self.task == "regress" and self.sigma > 0 and self.calibration_per_class < need:
            raise CertificationError(
                f"calibration-per-class = {self.calibration_per_class} frames is too few for "
                f"the conformal beta at alpha_c = {self.alpha_c:g}: it needs at least {need} "
                "calibration frames per label (with fewer, beta is infinite and the run-time "
                "interval is the whole envelope)")

    def compile_model(self, samples: int) -> bool:
        """Compile when asked, or ("auto") when the run draws enough samples to pay it back."""
        return self.compile == "on" or (self.compile == "auto" and samples >= COMPILE_AUTO_SAMPLES)

    def attack_settings(self) -> AttackSettings:
        return AttackSettings(eps=self.eps, steps=self.attack_steps,
                              noise_draws=self.attack_noise_draws, seed=self.seed)

    def frame_streams(self, i: int) -> dict[str, int]:
        """Seeds of test frame i's streams (attack, selection, estimation, ...): independent
        children of the root seed (:mod:`drake_cert.certification.seeds`)."""
        return streams(self.seed, i)


def select_frames(labels: torch.Tensor, count: int, seed: int) -> np.ndarray:
    """Indices of ``count`` frames, round-robin over classes from a seeded permutation.

    Pass ``seeds.frame_choice_seed(root_seed)`` so that frame choice has a stream of its own.
    """
    labels = labels.numpy()
    if count > len(labels):
        raise CertificationError(f"{count} frames asked for but the split has {len(labels)}")
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(labels))
    queues = [list(order[labels[order] == k]) for k in np.unique(labels)]
    chosen: list[int] = []
    while len(chosen) < count:
        for q in queues:
            if q and len(chosen) < count:
                chosen.append(int(q.pop(0)))
    return np.array(chosen)


def _attacked(model, images: torch.Tensor, settings: CertifySettings,
              chunk: int = 16) -> torch.Tensor:
    if settings.attack == "none" or settings.eps == 0:
        return images
    if any(p.device.type != "cpu" for p in model.parameters()):
        # the attack's streams (random start, noise draws) are the CPU's: it runs there, on a
        # copy, so a model that certification moved to a GPU is attacked as on a CPU machine
        model = copy.deepcopy(model).cpu()
    out = []
    for i in range(0, len(images), chunk):
        # Each frame attacks with its own stream (random start, noise draws), batched.
        frame_seeds = [settings.frame_streams(j)["attack"]
                       for j in range(i, min(i + chunk, len(images)))]
        out.append(attack(model, images[i:i + chunk], settings.attack,
                          settings.attack_settings(), task=settings.task, sigma=settings.sigma,
                          frame_seeds=frame_seeds))
    return torch.cat(out)


def _progress(progress: Callable[[Iterable], Iterable] | None, it: Iterable) -> Iterable:
    return progress(it) if progress is not None else it


@dataclasses.dataclass(frozen=True)
class EvalFrames:
    """The test frames a certification runs on."""

    images: torch.Tensor  # [N, C, H, W] in [0, 1]
    labels: torch.Tensor  # [N] true label indices
    stiffness: torch.Tensor  # [N] true tire stiffness, N/rad
    label_names: tuple[str, ...] = ()  # the labels' condition names (classifier)


@dataclasses.dataclass(frozen=True)
class CalibrationInputs:
    """What a certification may start from besides its test frames (all optional).

    ``frames``: held-out calibration frames, ``(images, labels)`` for the classifier's robust
    conformal interval, ``(images, stiffness, labels)`` for the regressor's conformal beta;
    ``made``: a calibration made before with the same settings (skips calibrating);
    ``clean_cache``: a dict of the classifier's clean certificates by frame index, filled and
    read, so several attacks on the same frames share them.
    """

    frames: tuple | None = None
    made: object = None
    clean_cache: dict | None = None


def certify_classifier(model: torch.nn.Module, frames: EvalFrames, table: ConditionsTable,
                       settings: CertifySettings,
                       progress: Callable[[Iterable], Iterable] | None = None,
                       inputs: CalibrationInputs | None = None) -> tuple[list[dict], dict]:
    """Certify (sigma > 0) or evaluate (sigma = 0) a classifier on frames, clean and attacked.

    For sigma > 0, each frame gets the certificate of :meth:`SmoothedClassifier.certify` with
    the safe set S(a) of the predicted label, at the clean frame and (when attacked) at the
    attacked frame, and the run-time interval at budget eps at the observed frame. With
    ``settings.conformal``, ``inputs.frames = (images, labels)`` of held-out frames calibrates
    the robust conformal interval (:mod:`drake_cert.certification.conformal`), reported
    beside the certificate's interval from the same samples; ``inputs.made``, a calibration
    made before with the same settings, skips that step. Every frame and purpose draws from
    its own stream (:meth:`CertifySettings.frame_streams`), so the clean certificate of frame
    i is the same in every call with the same seed, n0, n and alpha: ``inputs.clean_cache``
    (a dict, filled and read by frame index) lets several attacks on the same frames share it.
    """
    inputs = inputs or CalibrationInputs()
    images, labels, stiffness = frames.images, frames.labels, frames.stiffness
    label_names = list(frames.label_names)
    calibration, robust, clean_cache = inputs.frames, inputs.made, inputs.clean_cache
    settings.validate()
    model = with_precision(model, settings.precision)  # certify, attack, calibrate: one model
    k = len(label_names)
    if settings.sigma > 0:
        check_enough_samples(settings.n, settings.alpha, k)
    adversarial = _attacked(model, images, settings)
    attacked = adversarial is not images
    if settings.sigma == 0:
        records = _base_records(model, images, adversarial, attacked, labels, stiffness)
        return records, summarize_classification(records, settings)
    safe = {i: [label_names.index(n) for n in table.safe_set(settings.preset, name)]
            for i, name in enumerate(label_names)}
    per_frame = (settings.n0 + settings.n) * (2 if attacked else 1)
    smooth = SmoothedClassifier(model, k, settings.sigma, device=settings.device,
                                compile=settings.compile_model(per_frame * len(images)))
    if settings.conformal and robust is None:
        if calibration is None:
            raise CertificationError("the conformal interval needs calibration frames")
        robust = calibrate_classifier(smooth, calibration, settings, progress)
    records = []
    context = _RecordContext(robust, table, settings, label_names)
    for i in _progress(progress, range(len(images))):
        st = settings.frame_streams(i)
        clean = clean_cache.get(i) if clean_cache is not None else None
        if clean is None:
            clean = smooth.certify(images[i], settings.n0, settings.n, settings.alpha,
                                   settings.batch_size, safe_set=safe, seed=st["estimation"],
                                   selection_seed=st["selection"])
            if clean_cache is not None:
                clean_cache[i] = clean
        seen = smooth.certify(adversarial[i], settings.n0, settings.n, settings.alpha,
                              settings.batch_size, safe_set=safe,
                              seed=st["attacked_estimation"],
                              selection_seed=st["attacked_selection"]) if attacked else clean
        records.append(_certified_record(clean, seen, int(labels[i]), float(stiffness[i]),
                                         context))
    summary = summarize_classification(records, settings)
    summary["compile_seconds"] = smooth.compile_seconds
    if robust is not None:
        summary.update(summarize_conformal(records, robust))
    return records, summary


def _base_records(model: torch.nn.Module, images: torch.Tensor, adversarial: torch.Tensor,
                  attacked: bool, labels: torch.Tensor, stiffness: torch.Tensor) -> list[dict]:
    """:func:`certify_classifier`'s records at sigma = 0: the base model's labels, clean and
    (when attacked) on the attacked frames."""
    with torch.inference_mode():
        clean_pred = model(images).argmax(1)
        adv_pred = model(adversarial).argmax(1) if attacked else clean_pred
    return [{"label": int(labels[i]), "clean_prediction": int(clean_pred[i]),
             "prediction": int(adv_pred[i]), "stiffness_n_per_rad": float(stiffness[i])}
            for i in range(len(images))]


@dataclasses.dataclass(frozen=True)
class _RecordContext:
    """What every frame's record of :func:`certify_classifier` is read against."""

    robust: object  # the robust conformal calibration, or None
    table: ConditionsTable
    settings: CertifySettings
    label_names: list[str]


def _certified_record(clean, seen, label: int, y: float, context: _RecordContext) -> dict:
    """:func:`certify_classifier`'s record of one frame of true ``label`` and stiffness ``y``
    from its clean and seen (attacked, or clean) certificates."""
    robust, table = context.robust, context.table
    settings, label_names = context.settings, context.label_names
    rt = runtime_classification_interval(seen, table, settings.preset, settings.eps,
                                         label_names)
    extra = {}
    if robust is not None:
        ci = conformal_interval(seen, robust, table, settings.preset, settings.eps,
                                label_names)
        extra = {"conformal_label_set": list(ci.label_set),
                 "conformal_interval_n_per_rad": list(ci.interval),
                 "conformal_covered": bool(ci.stiffness_lo_n_per_rad <= y
                                           <= ci.stiffness_hi_n_per_rad)}
    return extra | {
        "label": label, "stiffness_n_per_rad": y,
        "clean_prediction": clean.label, "clean_radius": clean.radius,
        "clean_own_share": float(clean.counts[label]) / max(1, int(clean.counts.sum())),
        "clean_radius_label": clean.radius_for([clean.top_label]) if not clean.abstained
        else 0.0,
        "prediction": seen.label, "radius": seen.radius,
        "interval_labels": list(rt.labels), "interval_n_per_rad": list(rt.interval),
        "interval_certified": rt.certified, "interval_radius": rt.radius,
        "interval_holds_label": label_names[label] in rt.labels,
        "covered": rt.stiffness_lo_n_per_rad <= y <= rt.stiffness_hi_n_per_rad,
    }


def calibrate_classifier(smooth: SmoothedClassifier, calibration: tuple,
                         settings: CertifySettings,
                         progress: Callable[[Iterable], Iterable] | None = None):
    """The robust conformal calibration of ``smooth`` on ``calibration = (images, labels)``
    (:func:`calibrate_robust_conformal` with the settings' levels and root seed)."""
    return calibrate_robust_conformal(
        smooth, calibration[0], [int(v) for v in calibration[1]],
        sampling=CalibrationSampling(n=settings.calibration_n, batch_size=settings.batch_size,
                                     seed=settings.seed, progress=progress),
        levels=ConformalLevels(alpha_c=settings.conformal_alpha_c,
                               beta_cal=settings.conformal_beta,
                               beta_test=settings.conformal_beta))


def clopper_pearson_interval(successes: int, trials: int,
                             level: float = 0.95) -> tuple[float, float]:
    """Two-sided Clopper-Pearson confidence interval of a share (e.g. a measured coverage)."""
    lo, hi = clopper_pearson_one_sided(successes, trials, (1 - level) / 2)
    return float(lo), float(hi)


def summarize_conformal(records: list[dict], robust) -> dict:
    """Robust conformal interval metrics: coverage of the true stiffness with its 95 %
    Clopper-Pearson interval, the guarantee ``1 - alpha_total`` beside it, mean width (N/rad),
    and the calibration (thresholds q_l, frames per label); also the certificate interval's
    coverage interval for comparison."""
    covered = np.array([r["conformal_covered"] for r in records])
    widths = [r["conformal_interval_n_per_rad"][1] - r["conformal_interval_n_per_rad"][0]
              for r in records]
    old = int(sum(bool(r["covered"]) for r in records))
    return {
        "conformal_interval_coverage": float(covered.mean()),
        "conformal_interval_coverage_ci95": list(clopper_pearson_interval(int(covered.sum()),
                                                                          len(covered))),
        "conformal_guarantee": 1 - robust.alpha_total,
        "conformal_interval_width_mean": float(np.mean(widths)),
        "conformal_thresholds": {str(k): v for k, v in robust.thresholds.items()},
        "conformal_calibration_frames": {str(k): v for k, v in robust.frames_per_label.items()},
        "interval_coverage_ci95": list(clopper_pearson_interval(old, len(records))),
    }


def summarize_classification(records: list[dict], settings: CertifySettings) -> dict:
    """Metrics over frames (all shares in [0, 1], radii in L2 pixel units, widths in N/rad).

    accuracy: prediction at the observed (attacked, if any) frame equals the true label
    (abstain counts as wrong); clean_accuracy: the same at the clean frame; abstain_rate,
    clean_abstain_rate: share of abstentions at the observed / clean frame; mean_radius:
    mean R_{S(a)} at the clean frame (abstain = 0) over the frames whose S(a) leaves some label
    out (when S(a) holds every label, e.g. the grippiest one, R is infinite: their share is
    unbounded_radius_rate); mean_radius_label: mean R_{a} for the single label {a};
    interval_width_mean, interval_coverage: run-time interval at budget eps at the observed
    frame, its mean width and the share holding the true stiffness; coverage_given_clean_right:
    that share among frames whose clean smoothed prediction is right; envelope_rate: share of
    run-time intervals that fell back to the envelope.
    """
    y = np.array([r["label"] for r in records])
    pred = np.array([r["prediction"] for r in records])
    clean = np.array([r["clean_prediction"] for r in records])
    out = {"frames": len(records), "preset": settings.preset, "task": settings.task,
           "sigma": settings.sigma, "attack": settings.attack, "eps": settings.eps,
           "n0": settings.n0, "n": settings.n, "alpha": settings.alpha,
           "precision": settings.precision,
           "accuracy": float(np.mean(pred == y)), "clean_accuracy": float(np.mean(clean == y))}
    if settings.sigma == 0:
        return out
    right = clean == y
    covered = np.array([r["covered"] for r in records])
    out.update({
        "abstain_rate": float(np.mean(pred == -1)),
        "clean_abstain_rate": float(np.mean(clean == -1)),
        "mean_radius": _mean_finite([r["clean_radius"] for r in records]),
        "unbounded_radius_rate": float(np.mean([math.isinf(r["clean_radius"])
                                                for r in records])),
        "mean_radius_label": float(np.mean([r["clean_radius_label"] for r in records])),
        "interval_width_mean": float(np.mean([r["interval_n_per_rad"][1] -
                                              r["interval_n_per_rad"][0] for r in records])),
        "interval_coverage": float(np.mean(covered)),
        "coverage_given_clean_right": float(np.mean(covered[right])) if right.any() else None,
        "envelope_rate": float(np.mean([not r["interval_certified"] for r in records])),
    })
    out.update(decision_shares(records))
    return out


def decision_shares(records: list[dict]) -> dict:
    """The three outcomes of the run-time interval at the observed frames, each a share of the
    frames with its 95 % Clopper-Pearson interval: ``certified_right`` (a label range
    certified beyond eps that holds the true label), ``certified_wrong`` (one that does not:
    under the safe-set interval the stiffness interval then excludes the truth, which is
    worse than abstaining) and ``interval_abstain`` (no range certified: the envelope; the
    same frames as ``envelope_rate``). Keys ``<name>_rate`` and ``<name>_rate_ci95``."""
    certified = np.array([bool(r["interval_certified"]) for r in records])
    holds = np.array([bool(r["interval_holds_label"]) for r in records])
    counts = {"certified_right": int((certified & holds).sum()),
              "certified_wrong": int((certified & ~holds).sum()),
              "interval_abstain": int((~certified).sum())}
    out = {}
    for name, hits in counts.items():
        out[f"{name}_rate"] = hits / len(records)
        out[f"{name}_rate_ci95"] = list(clopper_pearson_interval(hits, len(records)))
    return out


def _mean_finite(values: list[float]) -> float | None:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else None


def json_safe(value):
    """``value`` with infinities replaced by None (strict JSON has no infinity)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def certify_regressor(model: torch.nn.Module, frames: EvalFrames,
                      envelope: tuple[float, float], settings: CertifySettings,
                      progress: Callable[[Iterable], Iterable] | None = None,
                      inputs: CalibrationInputs | None = None) -> tuple[list[dict], dict]:
    """Median-smoothing certificates (sigma > 0) or plain predictions (sigma = 0) of a regressor.

    ``inputs.frames`` is ``(images, stiffness, labels)`` of calibration frames (sigma > 0):
    the conformal beta is computed on them first (:func:`calibrate_conformal`);
    ``inputs.made``, a :class:`ConformalCalibration` made before with the same settings, skips
    that. Each test frame gets ``certify_interval`` at budget eps at the observed frame and the
    run-time interval.
    """
    inputs = inputs or CalibrationInputs()
    images, labels, stiffness = frames.images, frames.labels, frames.stiffness
    calibration, conformal = inputs.frames, inputs.made
    settings.validate()
    model = with_precision(model, settings.precision)  # certify, attack, calibrate: one model
    if settings.sigma > 0:
        percentile_bound_indices(settings.n, settings.eps, settings.sigma, settings.alpha)
    adversarial = _attacked(model, images, settings)
    records = []
    if settings.sigma == 0:
        with torch.inference_mode():
            clean = model(images).reshape(-1)
            seen = model(adversarial).reshape(-1)
        for i in range(len(images)):
            records.append({"label": int(labels[i]), "stiffness_n_per_rad": float(stiffness[i]),
                            "clean_prediction_n_per_rad": float(clean[i]),
                            "prediction_n_per_rad": float(seen[i])})
        return records, summarize_regression(records, settings, None)
    samples = settings.n * len(images)
    if conformal is None:
        if calibration is None:
            raise CertificationError("median smoothing needs calibration frames for beta")
        check_regression_calibration(calibration[2], labels, settings.alpha_c)
        samples += settings.calibration_n * len(calibration[0])
    smooth = MedianSmoothedRegressor(model, settings.sigma, device=settings.device,
                                     compile=settings.compile_model(samples))
    cal = conformal if conformal is not None else calibrate_regressor(
        smooth, calibration, settings, progress)
    for i in _progress(progress, range(len(images))):
        median, lower, upper = smooth.certify_interval(
            adversarial[i], settings.eps, settings.n, settings.alpha, settings.batch_size,
            seed=settings.frame_streams(i)["estimation"])
        lo, hi = runtime_interval(lower, upper, cal.beta, envelope)
        y = float(stiffness[i])
        records.append({"label": int(labels[i]), "stiffness_n_per_rad": y,
                        "prediction_n_per_rad": median, "lower_n_per_rad": lower,
                        "upper_n_per_rad": upper, "interval_n_per_rad": [lo, hi],
                        "covered": lo <= y <= hi})
    summary = summarize_regression(records, settings, cal.beta)
    summary.update({"betas_n_per_rad": {str(k): v for k, v in cal.betas.items()},
                    "calibration_frames": cal.frames, "compile_seconds": smooth.compile_seconds})
    return records, summary


def check_regression_calibration(cal_labels, labels: torch.Tensor, alpha_c: float) -> None:
    """CertificationError unless every test label has enough calibration frames for the
    conformal beta at ``alpha_c``."""
    need = min_calibration_frames(alpha_c)
    counts = torch.bincount(torch.as_tensor(cal_labels), minlength=int(labels.max()) + 1)
    if len(cal_labels) == 0 or int(counts[torch.unique(labels)].min()) < need:
        raise CertificationError(
            f"calibration frames per label {counts.tolist()} are too few for the conformal "
            f"beta at alpha_c = {alpha_c:g}: each label needs at least {need}")


def calibrate_regressor(smooth: MedianSmoothedRegressor, calibration: tuple,
                        settings: CertifySettings,
                        progress: Callable[[Iterable], Iterable] | None = None):
    """The conformal beta of ``smooth`` on ``calibration = (images, stiffness, labels)``, each
    frame with its own calibration stream of the root seed."""
    cal_images, cal_stiffness, cal_labels = calibration
    sampling = CalibrationSampling(
        n=settings.calibration_n, batch_size=settings.batch_size, progress=progress,
        frame_seeds=[stream_seed(settings.seed, i, "calibration", split="calibration")
                     for i in range(len(cal_images))])
    return calibrate_conformal(smooth, cal_images, cal_stiffness.tolist(), cal_labels.tolist(),
                               sampling=sampling, alpha_m=settings.alpha_m,
                               alpha_c=settings.alpha_c)


def summarize_regression(records: list[dict], settings: CertifySettings,
                         beta: float | None) -> dict:
    """Metrics over frames (N/rad). mae: mean |prediction - true stiffness| at the observed
    frame (the smoothed median for sigma > 0); interval_width_mean, interval_coverage: the
    run-time interval at budget eps; raw_width_mean: the width of [lower, upper] before beta.
    """
    y = np.array([r["stiffness_n_per_rad"] for r in records])
    pred = np.array([r["prediction_n_per_rad"] for r in records])
    out = {"frames": len(records), "preset": settings.preset, "task": settings.task,
           "sigma": settings.sigma, "attack": settings.attack, "eps": settings.eps,
           "n": settings.n, "alpha": settings.alpha, "precision": settings.precision,
           "mae_n_per_rad": float(np.mean(abs(pred - y)))}
    if settings.sigma == 0:
        clean = np.array([r["clean_prediction_n_per_rad"] for r in records])
        out["clean_mae_n_per_rad"] = float(np.mean(abs(clean - y)))
        return out
    out.update({
        "beta_n_per_rad": beta,
        "raw_width_mean": float(np.mean([r["upper_n_per_rad"] - r["lower_n_per_rad"]
                                         for r in records])),
        "interval_width_mean": float(np.mean([r["interval_n_per_rad"][1] -
                                              r["interval_n_per_rad"][0] for r in records])),
        "interval_coverage": float(np.mean([r["covered"] for r in records])),
    })
    return out
