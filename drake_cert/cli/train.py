"""``drake-cert train``: train a classifier or a stiffness regressor (noise-augmented at sigma).

The regressor (``--task regress``) is by default a one-output network trained end to end
under the same noise, its backbone initialised from the classifier at the same sigma
(``--regressor net``); ``--regressor head`` fits the older ridge head on the classifier's
frozen features instead. Both need the classifier file.

One model per file (``drake_cert/data/models/<preset>/<task>_sigma<S>.pt`` by default), so an
interrupted ``--all`` resumes with the next missing model; a classifier also writes a
checkpoint after every epoch (``<file>.ckpt``) and an interrupted run resumes from it. After
each model the folder's ``MANIFEST.yaml`` records every file's command line, SHA-256 and
metrics.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import yaml

from drake_cert.errors import ConfigError, ModelNotFoundError

ALL_PRESETS = ("carla-like", "rtk-like", "robotcar-like")
ALL_SIGMAS = (0.0, 0.25, 0.5, 1.0)
FRAME_PASSES = 30_000  # default epochs: enough to see ~30k frames, at least MIN_EPOCHS
MIN_EPOCHS = 6
WIDTH_RANGE = (2, 256)  # --width: channels of a classifier's first stage
POOLS = (1, 2, 4)  # --pool: pixel blocks averaged before a classifier's network


def configure(parser) -> None:
    parser.add_argument("--preset", help="preset name (conditions table), e.g. carla-like")
    parser.add_argument("--task", choices=("classify", "regress"), default=None,
                        help="classify: noise-augmented classifier; regress: stiffness "
                             "regressor (needs the classifier at the same sigma, see "
                             "--regressor); default classify, both with --all")
    parser.add_argument("--regressor", choices=("net", "head", "band"), default="net",
                        help="regress: 'net' trains the whole one-output network end to end "
                             "under the noise (backbone initialised from the classifier); "
                             "'band' the same network with two outputs, the stiffness's "
                             "lower and upper conditional quantiles (pinball loss); "
                             "'head' fits a ridge head on the classifier's frozen features "
                             "(default: net)")
    parser.add_argument("--sigma", default=None,
                        help="Gaussian noise std in [0, 1] pixel space (0 = non-robust model)")
    parser.add_argument("--all", action="store_true",
                        help=f"train every preset in {', '.join(ALL_PRESETS)} x sigma in "
                             f"{', '.join(f'{s:g}' for s in ALL_SIGMAS)} x task, "
                             "skipping models that exist")
    parser.add_argument("--epochs", type=int, default=None,
                        help=f"classifier and end-to-end regressor epochs (default: "
                             f"max({MIN_EPOCHS}, "
                             f"ceil({FRAME_PASSES} / training frames)))")
    parser.add_argument("--method", choices=("gaussian", "consistency", "tail"),
                        default="gaussian",
                        help="classifier training: 'gaussian' augmentation (cross-entropy on "
                             "one noisy copy), 'consistency' regularization (m noisy copies; "
                             "+ lambda * KL to their mean softmax + eta * its entropy) or "
                             "'tail' ((1 - beta) mean + beta mean of the worst q of a batch's "
                             "losses); docs/design.md 3.2; default gaussian")
    parser.add_argument("--tail-fraction", type=float, default=0.25,
                        help="tail: the worst share q of a batch's frames (default 0.25)")
    parser.add_argument("--tail-weight", type=float, default=0.5,
                        help="tail: weight beta of their mean loss (default 0.5)")
    parser.add_argument("--band-quantiles", type=float, nargs=2, default=None,
                        metavar=("LO", "HI"),
                        help="band: the two ends' quantile levels, 0 < LO < HI < 1 "
                             "(default 0.05 0.95)")
    parser.add_argument("--width", type=int, default=16,
                        help="classifier: channels of the network's first stage, then 2x and "
                             "4x (default 16; the run-time cost grows about as its square)")
    parser.add_argument("--pool", type=int, default=1, choices=POOLS,
                        help="classifier: average pool x pool pixel blocks before the network "
                             "(the noise is still added to the full frame; each convolution "
                             "costs 1/pool^2 as much; default 1: none)")
    parser.add_argument("--consistency-lambda", type=float, default=10.0,
                        help="consistency: weight lambda of the KL term (default 10)")
    parser.add_argument("--consistency-eta", type=float, default=0.5,
                        help="consistency: weight eta of the mean softmax's entropy (default 0.5)")
    parser.add_argument("--copies", type=int, default=2,
                        help="consistency: noisy copies m of each frame per step (default 2)")
    parser.add_argument("--device", default="cpu",
                        help="where to train: cpu (default) or cuda (torch only, no Drake "
                             "needed; the noise streams are the CPU's either way)")
    parser.add_argument("--seed", type=int, default=0, help="data and training seed")
    parser.add_argument("--frames-per-class", type=int, default=None,
                        help="training frames per class (default: the preset's count)")
    parser.add_argument("--models", default=None,
                        help="model folder (default: the shipped drake_cert/data/models)")
    parser.add_argument("--conditions", default=None, help="conditions YAML (default: shipped)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (1 is fastest on a busy machine)")
    parser.add_argument("--force", action="store_true", help="retrain models that exist")
    parser.add_argument("--json", action="store_true", help="print the metrics as JSON on stdout")


def check(args) -> None:
    """The model folder and the conditions file, before torch is imported (``cli.main`` runs
    this first): a file where the folder should be costs no training."""
    from drake_cert.config import load_conditions
    from drake_cert.io import check_writable_folder

    if args.models is not None:
        check_writable_folder(args.models, "--models")
    load_conditions(args.conditions)


def default_epochs(train_frames: int) -> int:
    """Epochs so that a model sees about FRAME_PASSES frames, at least MIN_EPOCHS."""
    return max(MIN_EPOCHS, math.ceil(FRAME_PASSES / max(1, train_frames)))


def run(args) -> int:
    import torch

    from drake_cert.certification.sampler import resolve_device
    from drake_cert.config import load_conditions
    from drake_cert.perception.models import check_sigma

    torch.set_num_threads(max(1, int(args.threads)))
    table = load_conditions(args.conditions)
    args.device = resolve_device(args.device)
    train_config(args)  # a bad method parameter: ConfigError before any work
    if args.seed < 0:
        raise ConfigError(f"--seed {args.seed} must be >= 0")
    if args.epochs is not None and args.epochs <= 0:
        raise ConfigError(f"--epochs {args.epochs} must be positive")
    if args.frames_per_class is not None and args.frames_per_class <= 0:
        raise ConfigError(f"--frames-per-class {args.frames_per_class} must be positive")
    lo, hi = WIDTH_RANGE
    if not lo <= args.width <= hi:
        raise ConfigError(f"--width {args.width} must be between {lo} and {hi} channels")
    band_q = getattr(args, "band_quantiles", None)
    if band_q is not None and not 0.0 < band_q[0] < band_q[1] < 1.0:
        raise ConfigError(f"--band-quantiles {band_q[0]:g} {band_q[1]:g} must be two levels "
                          "0 < LO < HI < 1")
    if band_q is not None and getattr(args, "regressor", "net") != "band":
        raise ConfigError("--band-quantiles needs --task regress --regressor band")
    if args.all:
        presets = [args.preset] if args.preset else list(ALL_PRESETS)
        sigmas = [check_sigma(args.sigma)] if args.sigma is not None else list(ALL_SIGMAS)
        tasks = [args.task] if args.task is not None else ["classify", "regress"]
        jobs = [(p, t, s) for p in presets for s in sigmas for t in tasks]
    else:
        if args.preset is None or args.sigma is None:
            raise ConfigError("give --preset and --sigma (or --all)")
        jobs = [(args.preset, args.task or "classify", check_sigma(args.sigma))]
    for preset, _, _ in jobs:
        table.preset(preset)  # unknown preset: ConfigError before any work
    results = []
    for preset, task, sigma in jobs:
        result = train_one(table, preset, task, sigma, args)
        if result is not None:
            results.append(result)
    if args.json:
        json.dump(results, sys.stdout, indent=2)
        print()
    return 0


def train_config(args):
    """The classifier's :class:`TrainConfig` of the command line (method and its parameters)."""
    from drake_cert.perception.training import TrainConfig, consistency_config, tail_config

    base = TrainConfig(width=int(getattr(args, "width", 16)), pool=int(getattr(args, "pool", 1)))
    if getattr(args, "method", "gaussian") == "consistency":
        return consistency_config(args.consistency_lambda, copies=args.copies,
                                  eta=args.consistency_eta, base=base)
    if getattr(args, "method", "gaussian") == "tail":
        return tail_config(args.tail_fraction, args.tail_weight, base=base)
    return base


def _single_command(preset: str, task: str, sigma: float, args) -> list[str]:
    """The equivalent single-model command line (recorded in the model's provenance)."""
    from drake_cert.perception.models import sigma_tag

    cmd = ["drake-cert", "train", "--preset", preset, "--task", task, "--sigma", sigma_tag(sigma)]
    regressor = getattr(args, "regressor", "net") if task == "regress" else "net"
    head = regressor == "head"
    if regressor != "net":
        cmd += ["--regressor", regressor]
    if regressor == "band" and getattr(args, "band_quantiles", None) is not None:
        cmd += ["--band-quantiles", *(f"{q:g}" for q in args.band_quantiles)]
    if args.epochs is not None and not head:
        cmd += ["--epochs", str(args.epochs)]
    if task == "classify" and getattr(args, "method", "gaussian") == "consistency":
        cmd += ["--method", "consistency", "--consistency-lambda", f"{args.consistency_lambda:g}",
                "--consistency-eta", f"{args.consistency_eta:g}", "--copies", str(args.copies)]
    if task == "classify" and getattr(args, "method", "gaussian") == "tail":
        cmd += ["--method", "tail", "--tail-fraction", f"{args.tail_fraction:g}",
                "--tail-weight", f"{args.tail_weight:g}"]
    if task == "classify" and int(getattr(args, "width", 16)) != 16:
        cmd += ["--width", str(int(args.width))]
    if task == "classify" and int(getattr(args, "pool", 1)) != 1:
        cmd += ["--pool", str(int(args.pool))]
    if args.seed != 0:
        cmd += ["--seed", str(args.seed)]
    if args.frames_per_class is not None:
        cmd += ["--frames-per-class", str(args.frames_per_class)]
    if args.models is not None:
        cmd += ["--models", str(args.models)]
    if args.conditions is not None:
        cmd += ["--conditions", str(args.conditions)]
    return cmd


def train_one(table, preset: str, task: str, sigma: float, args) -> dict | None:
    """Train (classify) or fit (regress) one model unless its file exists; returns its metrics."""
    from drake_cert.io import provenance
    from drake_cert.perception.datasets import load_split
    from drake_cert.perception.models import model_path, save_model, sigma_tag

    path = model_path(preset, task, sigma, args.models)
    name = f"{preset} {task} sigma={sigma_tag(sigma)}"
    if path.exists() and not args.force:
        print(f"drake-cert train: {name}: {path} exists; skipping (--force retrains)",
              file=sys.stderr)
        return None
    if task == "regress":
        _require_classifier(preset, sigma, args.models)
    t0 = time.perf_counter()
    train = load_split(preset, "train", seed=args.seed, frames_per_class=args.frames_per_class,
                       conditions=table)
    test = load_split(preset, "test", seed=args.seed, conditions=table)
    data_seconds = time.perf_counter() - t0
    command = _single_command(preset, task, sigma, args)
    meta = {"provenance": provenance(args.seed, command),
            "invoked_as": " ".join(["drake-cert", *sys.argv[1:]]),
            "preset": preset, "task": task, "sigma": sigma,
            "label_names": list(train.label_names), "image_size": train.size,
            "train_frames_per_class": len(train) // len(train.label_names)}
    t0 = time.perf_counter()
    ckpt = path.with_name(path.name + ".ckpt") if task == "classify" else None
    if task == "classify":
        from drake_cert.perception.training import training_method

        meta["training"] = training_method(train_config(args))
        model, train_metrics, test_metrics = _fit_classifier(train, test, sigma, args, ckpt,
                                                             name)
    else:
        model, train_metrics, test_metrics, extra = _fit_regressor(preset, train, test, sigma,
                                                                   args, name)
        meta.update(extra)
    seconds = time.perf_counter() - t0
    meta["train_metrics"] = train_metrics
    meta["test_metrics"] = test_metrics
    meta["seconds"] = {"data": round(data_seconds, 2), "fit": round(seconds, 2)}
    save_model(model, path, meta=meta)
    if ckpt is not None and ckpt.exists():
        ckpt.unlink()
    update_manifest(path.parent.parent, path, meta)
    shown = ", ".join(f"{k} {v:.4g}" for k, v in test_metrics.items() if k != "test_frames")
    print(f"drake-cert train: {name}: {shown} ({seconds:.0f} s) -> {path}", file=sys.stderr)
    return {"file": str(path), "preset": preset, "task": task, "sigma": sigma,
            "seconds": round(seconds, 2), **test_metrics}


def _require_classifier(preset: str, sigma: float, models) -> Path:
    """The classifier file a regressor head is fitted on; ModelNotFoundError if it is missing."""
    from drake_cert.perception.models import model_path, sigma_tag, train_command

    cpath = model_path(preset, "classify", sigma, models)
    if not cpath.exists():
        raise ModelNotFoundError(
            f"the regress model for {preset} at sigma {sigma_tag(sigma)} needs its classifier "
            f"{cpath}; make it first with: {train_command(preset, 'classify', sigma, models)}")
    return cpath


def _fit_classifier(train, test, sigma: float, args, ckpt: Path, name: str):
    """Train the noise-augmented classifier; returns (model, train metrics, test metrics)."""
    from drake_cert.perception.training import TrainRun, evaluate_accuracy, train_classifier

    epochs = args.epochs or default_epochs(len(train))
    run = TrainRun(progress=True, description=name, device=getattr(args, "device", "cpu"),
                   checkpoint=ckpt)
    model, train_metrics = train_classifier(train, sigma=sigma, epochs=epochs, seed=args.seed,
                                            config=train_config(args), run=run)
    test_metrics = {"test_accuracy_clean": evaluate_accuracy(model, test),
                    "test_accuracy_noisy": evaluate_accuracy(model, test, sigma=sigma,
                                                             seed=args.seed),
                    "test_frames": len(test)}
    return model, train_metrics, test_metrics


def band_quantiles(args) -> tuple[float, float]:
    """The band regressor's two quantile levels: ``--band-quantiles`` or the default."""
    from drake_cert.perception.training import BAND_QUANTILES

    chosen = getattr(args, "band_quantiles", None)
    return tuple(float(q) for q in chosen) if chosen is not None else BAND_QUANTILES


def _fit_regressor(preset: str, train, test, sigma: float, args, name: str = "regress"):
    """The stiffness regressor: end to end (``--regressor net``, default: a one-output
    network, backbone initialised from the classifier, trained under the noise with the
    classifier's epochs rule) or the ridge head on the classifier's frozen features
    (``--regressor head``). Returns (model, train metrics, test metrics, extra meta: the
    classifier file and SHA-256 it was fitted on / initialised from)."""
    from drake_cert.perception.models import file_sha256, load_model
    from drake_cert.perception.training import (
        TrainRun,
        evaluate_band,
        evaluate_mae,
        evaluate_mse,
        fit_regressor,
        train_regressor_end_to_end,
    )

    cpath = _require_classifier(preset, sigma, args.models)
    classifier = load_model(preset, "classify", sigma, args.models)
    sha = file_sha256(cpath)
    band = getattr(args, "regressor", "net") == "band"
    if getattr(args, "regressor", "net") == "head":
        model, train_metrics = fit_regressor(classifier, train, sigma=sigma, seed=args.seed)
        extra = {"regressor": "head", "classifier_file": cpath.name, "classifier_sha256": sha,
                 "training": {"method": "ridge_head"}}
    else:
        epochs = args.epochs or default_epochs(len(train))
        model, train_metrics = train_regressor_end_to_end(
            train, sigma=sigma, epochs=epochs, seed=args.seed, init=classifier,
            run=TrainRun(progress=True, description=name,
                         device=getattr(args, "device", "cpu")),
            quantiles=band_quantiles(args) if band else None)
        method = ({"method": "quantile_band_end_to_end", "quantiles": list(band_quantiles(args))}
                  if band else {"method": "huber_end_to_end"})
        extra = {"regressor": "band" if band else "end_to_end", "init_file": cpath.name,
                 "init_sha256": sha, "training": method}
    test_metrics = {"test_mse_clean_n_per_rad_sq": evaluate_mse(model, test),
                    "test_mse_noisy_n_per_rad_sq": evaluate_mse(model, test, sigma=sigma,
                                                                seed=args.seed),
                    "test_mae_noisy_n_per_rad": evaluate_mae(model, test, sigma=sigma,
                                                             seed=args.seed),
                    "test_frames": len(test)}
    if band:
        test_metrics.update(evaluate_band(model, test, sigma=sigma, seed=args.seed))
    return model, train_metrics, test_metrics, extra


NO_SWEEP = "none (one configuration, trained by its command; no sweep compared candidates)"


def update_manifest(root: Path, path: Path, meta: dict) -> None:
    """Record one model in ``<root>/MANIFEST.yaml``: command line, SHA-256, metrics."""
    from drake_cert.io import atomic_write_text
    from drake_cert.perception.models import file_sha256

    manifest_path = root / "MANIFEST.yaml"
    manifest = {}
    if manifest_path.exists():
        manifest = yaml.safe_load(manifest_path.read_text()) or {}
    models = manifest.get("models", {})
    metrics = {k: (round(v, 6) if isinstance(v, float) else v)
               for k, v in meta["test_metrics"].items()}
    models[str(path.relative_to(root))] = {
        "command": meta["provenance"]["command"],
        "git_revision": meta["provenance"]["git_revision"],
        "created_utc": meta["provenance"]["created_utc"],
        "sha256": file_sha256(path),
        "fit_seconds": meta["seconds"]["fit"],
        "training": meta.get("training", {}),
        "test_metrics": metrics,
        "sweep": NO_SWEEP,
    }
    manifest = {"description": "Shipped perception models; each was made by its command "
                               "(provenance is also inside each file).",
                "models": dict(sorted(models.items()))}
    atomic_write_text(manifest_path, yaml.safe_dump(manifest, sort_keys=False))
