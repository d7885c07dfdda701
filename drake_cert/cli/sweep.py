"""``drake-cert sweep``: train candidate classifiers and pick the one to ship.

For one preset and sigma: the shipped classifier (the baseline) and candidates trained by
``drake-cert train`` (one model folder each under ``--root``): consistency regularization at
each ``--lambdas`` value and the tail-weighted loss at each ``--tails`` pair, at each
``--widths`` width. All are certified on the same held-out test frames, clean and under the
stability attack at each budget; the table reports, per candidate and cell, the label ranges
certified right, certified WRONG and abstaining, and per label the own-label tail (frames g
gives under half the votes for their own label). The pick is, among the candidates that do not
certify wrong more than the baseline (its 95 % upper bound), the one with the fewest
abstentions (``--rank abstain``) or the thinnest worst-label tail (``--rank tail``; docs/design.md
3.2). Writes ``sweep.json``, ``sweep.md`` and ``sweep.png`` to
``--out``; each candidate's evaluation is stored as it finishes and reused when the model
file (SHA-256) and settings are the same, so an interrupted sweep resumes. ``--device cuda``
trains and certifies on a GPU (torch only, no Drake needed).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from drake_cert.errors import ConfigError


def _floats(text: str) -> tuple[float, ...]:
    import argparse
    import math

    if text.strip().lower() == "none":
        return ()
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of numbers"
                                         ) from None
    if not values or not all(math.isfinite(v) and v >= 0 for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: give finite numbers >= 0")
    return values


def _tails(text: str) -> tuple[tuple[float, float], ...]:
    import argparse

    try:
        pairs = tuple(tuple(float(x) for x in item.split(":")) for item in text.split(",")
                      if item.strip())
    except ValueError:
        pairs = ((),)
    if not pairs or any(len(p) != 2 for p in pairs):  # the ranges: default_candidates
        raise argparse.ArgumentTypeError(f"{text!r}: give q:beta pairs, comma-separated, with q "
                                         "in (0, 1] and beta in [0, 1], e.g. 0.25:0.5")
    return pairs


def _comma_ints(text: str, allowed, what: str) -> tuple[int, ...]:
    """The comma-separated integers of ``text``, each passing ``allowed``; an argparse error
    naming ``what`` otherwise."""
    import argparse

    try:
        values = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        values = ()
    if not values or not all(allowed(v) for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: give {what}, comma-separated")
    return values


def _widths(text: str) -> tuple[int, ...]:
    from drake_cert.cli.train import WIDTH_RANGE

    lo, hi = WIDTH_RANGE
    return _comma_ints(text, lambda v: lo <= v <= hi,
                       f"channel counts between {lo} and {hi} (train's --width)")


def _pools(text: str) -> tuple[int, ...]:
    from drake_cert.cli.train import POOLS

    return _comma_ints(text, lambda v: v in POOLS,
                       f"pixel-block sizes from {', '.join(map(str, POOLS))} (train's --pool)")


def configure(parser) -> None:
    from drake_cert.cli.certify import _positive_int

    parser.add_argument("--preset", required=True, help="preset name, e.g. robotcar-like")
    parser.add_argument("--sigma", type=float, required=True, help="smoothing noise (> 0)")
    parser.add_argument("--lambdas", type=_floats, default=(5.0, 10.0, 20.0),
                        help="consistency-regularization weights to train, comma-separated, "
                             "or 'none' (default: 5,10,20; m = 2 copies, eta = 0.5)")
    parser.add_argument("--tails", type=_tails, default=(),
                        help="tail-weighted candidates to train, q:beta pairs comma-separated "
                             "(e.g. 0.25:0.5; default: none)")
    parser.add_argument("--widths", type=_widths, default=(16,),
                        help="network widths of the trained candidates, comma-separated "
                             "(default: 16)")
    parser.add_argument("--pools", type=_pools, default=(1,),
                        help="input pooling of the trained candidates (train's --pool), "
                             "comma-separated (default: 1)")
    parser.add_argument("--rank", choices=("abstain", "tail"), default="abstain",
                        help="among eligible candidates pick the fewest abstentions in the "
                             "ranking cell, or the thinnest worst-label own-label tail (the "
                             "frames that set the drive's conformal thresholds; default: "
                             "abstain)")
    parser.add_argument("--budgets", type=_floats, default=None,
                        help="budgets eps, comma-separated (default: sigma)")
    parser.add_argument("--frames", type=_positive_int, default=600,
                        help="held-out test frames every candidate is certified on")
    parser.add_argument("--n0", type=_positive_int, default=100, help="selection samples")
    parser.add_argument("--n", type=_positive_int, default=1000, help="estimation samples")
    parser.add_argument("--alpha", type=float, default=1.0e-4,
                        help="failure probability of each certificate")
    parser.add_argument("--root", default=None,
                        help="candidate model folders (default: sweeps/<preset>_sigma<S>)")
    parser.add_argument("--out", default=None, help="table, plot and JSON (default: --root)")
    parser.add_argument("--models", default=None,
                        help="folder of the baseline model (default: the shipped models)")
    parser.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--seed", type=int, default=0, help="training and certification seed")
    parser.add_argument("--epochs", type=int, default=None,
                        help="training epochs of the candidates (default: train's rule)")
    parser.add_argument("--note", default="",
                        help="a line for the table's header, e.g. the machine that certified")
    parser.add_argument("--frames-per-class", type=int, default=None,
                        help="training frames per class of the candidates (default: the "
                             "preset's count)")


def run(args) -> int:
    import torch

    from drake_cert.certification.sampler import resolve_device
    from drake_cert.cli.progress import progress_bar
    from drake_cert.config import load_conditions
    from drake_cert.experiments import training_sweep as sweep
    from drake_cert.io import atomic_write_text
    from drake_cert.perception.datasets import load_split
    from drake_cert.perception.models import (
        check_sigma,
        file_sha256,
        load_model_file,
        model_path,
        sigma_tag,
        training_of,
    )

    sigma = check_sigma(args.sigma)
    table = load_conditions()
    table.preset(args.preset)
    resolve_device(args.device)
    torch.set_num_threads(max(1, int(args.threads)))
    settings = sweep.SweepSettings(preset=args.preset, sigma=sigma,
                                   budgets=args.budgets or (sigma,), frames=args.frames,
                                   n0=args.n0, n=args.n, alpha=args.alpha, device=args.device,
                                   seed=args.seed, rank=args.rank)
    settings.certify_settings("sa", settings.ranking_eps).validate()
    root = Path(args.root or f"sweeps/{args.preset}_sigma{sigma_tag(sigma)}")
    out = Path(args.out) if args.out else root
    candidates = sweep.default_candidates(args.lambdas, args.tails, args.widths, args.pools)
    paths = {}
    for cand in candidates:
        if cand.train_options is None:
            paths[cand.name] = model_path(args.preset, "classify", sigma, args.models)
            continue
        paths[cand.name] = model_path(args.preset, "classify", sigma, root / cand.name)
        if not paths[cand.name].exists():
            _train(args, sigma, root / cand.name, cand.train_options)
    test = load_split(args.preset, "test", seed=sweep.DATA_SEED, conditions=table)
    results, tails, identity, header = {}, {}, _identity(settings), []
    for cand in candidates:
        store = root / f"{cand.name}.eval.json"
        sha = file_sha256(paths[cand.name])
        stored = json.loads(store.read_text()) if store.exists() else None
        model = load_model_file(paths[cand.name])
        header.append(f"- {cand.name}: {_trained(model)} ({paths[cand.name]}, SHA-256 "
                      f"{sha[:12]})")
        if (stored and stored["sha256"] == sha and stored["settings"] == identity
                and "tail" in stored):
            results[cand.name], tails[cand.name] = stored["rows"], stored["tail"]
            continue

        def progress(it, name=cand.name):
            return progress_bar(it, desc=f"sweep {name}", leave=False)

        rows, tail = sweep.evaluate_candidate(model, test, settings, table, progress)
        sweep.write_json(store, {"sha256": sha, "settings": identity, "rows": rows, "tail": tail,
                                 "training": training_of(model),
                                 "file": str(paths[cand.name])})
        results[cand.name], tails[cand.name] = rows, tail
    choice = sweep.pick_candidate(results, settings, tails)
    header = ["Candidates (training method, epochs, where trained, fit time):", *header, ""]
    if args.note:
        header = [args.note, "", *header]
    text = sweep.render(results, choice, settings, header, tails)
    out.mkdir(parents=True, exist_ok=True)
    sweep.write_json(out / "sweep.json", {"settings": identity, "results": results,
                                          "tails": tails, "choice": choice,
                                          "files": {k: str(v) for k, v in paths.items()}})
    atomic_write_text(out / "sweep.md", text)
    sweep.plot(results, out / "sweep.png", settings)
    print(text)
    print(f"drake-cert sweep: wrote {out / 'sweep.md'}, sweep.json, sweep.png", file=sys.stderr)
    return 0


def _trained(model) -> str:
    """How a candidate was trained, in words, from its file's metadata."""
    from drake_cert.perception.models import training_of

    t = training_of(model)
    method = ", ".join([t["method"], *(f"{k} {v:g}" for k, v in t.items() if k != "method")])
    m = model.meta.get("train_metrics", {})
    fit = model.meta.get("seconds", {}).get("fit")
    width = getattr(getattr(model, "backbone", model), "width", None)
    method += f", width {width}" if width is not None else ""
    pool = getattr(getattr(model, "backbone", model), "pool", 1)
    method += f", {pool} x {pool} pixel blocks averaged first" if pool != 1 else ""
    frames = model.meta.get("train_frames_per_class")
    method += f", {frames} training frames a label" if frames else ""
    return (f"{method}; {m.get('epochs', '?')} epochs on {m.get('device', 'cpu')}"
            + (f", {fit:.0f} s" if fit is not None else ""))


def _identity(settings) -> dict:
    import dataclasses

    return {k: (list(v) if isinstance(v, tuple) else v)
            for k, v in dataclasses.asdict(settings).items() if k not in ("device", "rank")}


def _train(args, sigma: float, folder: Path, options: tuple[str, ...]) -> None:
    """Train one candidate with ``drake-cert train`` into its own model folder."""
    from drake_cert import cli
    from drake_cert.perception.models import sigma_tag

    argv = ["train", "--preset", args.preset, "--task", "classify", "--sigma", sigma_tag(sigma),
            "--models", str(folder), "--seed", str(args.seed), "--device", str(args.device),
            "--threads", str(args.threads), *options]
    if args.epochs is not None:
        argv += ["--epochs", str(args.epochs)]
    if args.frames_per_class is not None:
        argv += ["--frames-per-class", str(args.frames_per_class)]
    if cli.main(argv) != 0:
        raise ConfigError(f"training the candidate in {folder} failed (its message is above)")
