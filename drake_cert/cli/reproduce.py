"""``drake-cert reproduce``: the paper's tables from per-frame episodes (DESIGN 7).

Writes ``results.csv`` (one row per cell), ``frames.csv`` (one row per frame and cell),
``tables.md`` (ours beside the paper's numbers), plots and ``meta.json`` under ``--out``.
``--quick`` is the CI-sized run; the default is n = 10,000 with ``--frames`` test frames per
preset; ``--executor ray`` spreads frames over Ray workers (same rows, row for row).
Finished frames are kept under ``--out``/store as they arrive: a run stopped (Ctrl-C, or
``--budget-min``) resumes where it stopped, and the tables of a partial run count the
frames they hold.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", metavar="DIR", default="results/reproduce",
                        help="output folder")
    parser.add_argument("--quick", action="store_true",
                        help="a few frames per cell, small n, one budget (CI-sized)")
    parser.add_argument("--presets", nargs="+", default=None,
                        help="presets (default: carla-like rtk-like robotcar-like)")
    parser.add_argument("--frames", type=int, default=None,
                        help="test frames per preset (default: 100, or 2 with --quick)")
    parser.add_argument("--n", type=int, default=None,
                        help="estimation samples per certificate (default: 10000, 200 quick)")
    parser.add_argument("--eps", type=float, default=None,
                        help="L2 budget of the main tables (default: 0.25)")
    parser.add_argument("--sigmas", type=float, nargs="+", default=None,
                        help="noise levels of g and h (default: 0.25 0.5 1.0)")
    parser.add_argument("--sweep-eps", type=float, nargs="+", default=None,
                        help="budgets of the sweep (default: 0 0.25 0.5 1 1.5 2; --quick: eps)")
    parser.add_argument("--calibration-per-class", type=int, default=None,
                        help="h's conformal calibration frames per label (default: 400, "
                             "quick 6)")
    parser.add_argument("--calibration-n", type=int, default=None,
                        help="samples per h calibration frame (default: 500, quick 100)")
    parser.add_argument("--interval", default=None, help=argparse.SUPPRESS)  # gone: says so
    parser.add_argument("--conformal-per-class", type=int, default=None,
                        help="robust conformal calibration frames per label of g_conformal "
                             "(default 2000, the drive's: its votes ship beside the "
                             "classifiers; quick 6)")
    parser.add_argument("--no-conformal", action="store_true",
                        help="leave out the pipeline g_conformal (g's certificates read by the "
                             "robust conformal interval) and its calibration")
    parser.add_argument("--no-regression", action="store_true",
                        help="skip the regression tables")
    parser.add_argument("--seed", type=int, default=0, help="root seed")
    parser.add_argument("--executor", choices=("local", "ray"), default="local",
                        help="in-process, or Ray (local on demand, or --address)")
    parser.add_argument("--workers", type=int, default=2, help="Ray workers")
    parser.add_argument("--address", default=None,
                        help="existing Ray cluster: HOST:PORT of its head (`ray start --head "
                             "--port PORT`), auto, or ray://host:10001")
    parser.add_argument("--precision", choices=("auto", "fp32", "bf16"), default="auto",
                        help="model arithmetic of attacks, certificates and calibration (auto: "
                             "fp32 where ONNX Runtime is installed, else bf16 where the CPU has "
                             "it natively, else fp32; the environment "
                             "variable DRAKE_CERT_PRECISION=fp32|bf16 fixes what auto means)")
    parser.add_argument("--device", default="cpu",
                        help="where the certificates and calibrations sample the models: cpu "
                             "(default) or cuda[:N] (torch; refused where CUDA is absent). The "
                             "attacks and the Drake episodes stay on the CPU")
    parser.add_argument("--backend", choices=("auto", "torch", "onnxruntime"), default="auto",
                        help="CPU evaluation of the noisy samples (auto: ONNX Runtime where "
                             "installed and fp32, else torch; torch on a CUDA device)")
    parser.add_argument("--decisions", choices=("sequential", "fixed"), default="sequential",
                        help="g's cells read only as a decision at their budget (clean and "
                             "the budget sweep): sequential (stop once decided; default) or "
                             "fixed (n0 + n each). The radius columns keep fixed n")
    parser.add_argument("--budget-min", type=float, default=None,
                        help="start no new frame after this many minutes; write the tables of "
                             "the frames finished so far (rerun to resume)")
    parser.add_argument("--from-store", action="store_true",
                        help="compute nothing: write the tables of the frames stored under "
                             "--out/store (by a run with the same settings)")
    parser.add_argument("--fresh", action="store_true",
                        help="ignore the frames stored under --out/store and recompute them")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")


def build_config(args):
    import dataclasses

    from drake_cert.errors import ConfigError
    from drake_cert.experiments.reproduce_config import ReproduceConfig

    if args.backend == "onnxruntime" and args.precision == "bf16":
        raise ConfigError("--backend onnxruntime evaluates in fp32: use --precision fp32, or "
                          "--backend torch for bf16")
    if args.interval is not None:
        raise ConfigError("--interval is gone: every run has both intervals, g (the safe-set "
                          "interval) and g_conformal (the robust conformal interval) on the same "
                          "frames, attacks and noise; --no-conformal leaves g_conformal out")
    config = ReproduceConfig.quick(args.seed) if args.quick else ReproduceConfig(seed=args.seed)
    changes = {}
    if args.presets:
        changes["presets"] = tuple(args.presets)
    if args.frames is not None:
        changes["frames"] = args.frames
    if args.n is not None:
        changes["n"] = args.n
        changes["batch_size"] = min(config.batch_size, args.n) if args.n > 0 else 1
    if args.eps is not None:
        changes["eps"] = args.eps
        if args.quick:
            changes["sweep_eps"] = (args.eps,)
    if args.no_regression:
        changes["regression"] = False
    if args.sigmas:
        changes["sigmas"] = tuple(args.sigmas)
    if args.sweep_eps:
        changes["sweep_eps"] = tuple(args.sweep_eps)
    if args.calibration_per_class is not None:
        changes["calibration_per_class"] = args.calibration_per_class
    if args.calibration_n is not None:
        changes["calibration_n"] = args.calibration_n
    if args.no_conformal:
        changes["conformal"] = False
    changes["precision"] = args.precision
    changes["device"], changes["backend"] = args.device, args.backend
    changes["decisions"] = args.decisions
    if args.conformal_per_class is not None:
        changes["conformal_per_class"] = args.conformal_per_class
    config = dataclasses.replace(config, **changes)
    config.validate()
    return config


def _machine(precision: str) -> dict:
    """The CPU this invocation ran on (its model name and vector flags) and its cores."""
    from drake_cert.experiments.run_store import arithmetic
    from drake_cert.threads import available_cores

    info = arithmetic(precision)
    return dict(cpu=info["cpu"], cpu_flags=info["cpu_flags"], cores=available_cores())


def log_run(path, entry: dict) -> list[dict]:
    """Append ``entry`` to the store's list of invocations (atomically); the whole list."""
    from drake_cert.io import atomic_write_text

    runs = json.loads(path.read_text()) if path.exists() else []
    runs.append(entry)
    atomic_write_text(path, json.dumps(runs, indent=1) + "\n")
    return runs


def run(args) -> int:
    from pathlib import Path

    from drake_cert.config import load_conditions, load_settings, load_vehicle
    from drake_cert.errors import ConfigError
    from drake_cert.experiments.executors import make_executor
    from drake_cert.experiments.run_store import RunStore
    from drake_cert.io import check_writable, provenance
    from drake_cert.synthesis.table import synthesize_table

    config = _resolved_config(args)
    out = Path(args.out)
    if args.budget_min is not None and not args.budget_min > 0:
        raise ConfigError(f"--budget-min = {args.budget_min} must be a positive number")
    if args.from_store and args.fresh:
        raise ConfigError("--from-store and --fresh exclude each other")
    check_writable(out / "results.csv", "--out")
    if args.fresh and (out / "store").exists():
        import shutil

        shutil.rmtree(out / "store")
    # On CUDA the workers share the GPUs: each asks Ray for its share (episodes use its CPU).
    executor = make_executor(args.executor, args.workers, args.address,
                             gpus_per_worker=0.0 if config.device == "cpu"
                             else 1.0 / max(args.workers, 1))
    started = provenance(seed=config.seed)  # the revision and time the run started with
    start = time.perf_counter()
    deadline = None if args.budget_min is None else start + 60.0 * args.budget_min
    stop = (lambda: True) if args.from_store else None if deadline is None \
        else (lambda: time.perf_counter() > deadline)
    designs = synthesize_table(load_vehicle(), load_conditions(), load_settings())  # once
    store = RunStore(out / "store")
    cpu: dict = {}  # the workers' CPU seconds per stage, this invocation
    rows = _reproduce_with_progress(config, executor, store, stop, designs, cpu)
    wall = time.perf_counter() - start
    done = {p: len({r["position"] for r in rows if r["preset"] == p}) for p in config.presets}
    complete = all(k == config.frames for k in done.values())
    if not rows:
        if args.from_store:
            why = store.explain(config, designs)
            raise ConfigError(f"{out / 'store'} holds no frame made with these settings"
                              + (f": {why}" if why else ""))
        print(json.dumps({"out": str(out), "wall_s": round(wall, 1), "frames_done": done,
                          "complete": False}))
        return 0
    _write_reproduction(args, config, out, store, designs,
                        _Outcome(rows, started, wall, cpu, done, complete))
    return 0


def _resolved_config(args):
    """The run's configuration; with --from-store, "auto" precision is the stored frames'."""
    import dataclasses
    from pathlib import Path

    from drake_cert.experiments.run_store import RunStore

    config = build_config(args)
    if args.from_store and args.precision == "auto":
        # Nothing is computed: "auto" means the precision the stored frames were made in.
        made_in = RunStore(Path(args.out) / "store").precisions()
        if made_in and config.precision not in made_in:
            config = dataclasses.replace(config, precision=made_in[-1], backend=args.backend)
    return config


def _reproduce_with_progress(config, executor, store, stop, designs, cpu) -> list[dict]:
    """The reproduction's frame rows, with one progress bar per phase."""
    from drake_cert.cli.progress import progress_bar
    from drake_cert.experiments.reproduce import RunReport, run_reproduction

    bars = []

    def progress(desc, total):
        # One phase at a time: closing the previous bar here stops its clock at the phase's end
        # (closed only at the end of the run, every bar would show the whole run's time).
        if bars:
            bars[-1].close()
        bars.append(progress_bar(total=total, desc=desc, unit="task"))
        return bars[-1].update

    try:
        return run_reproduction(config, executor, store=store, stop=stop, designs=designs,
                                report=RunReport(progress=progress, cpu=cpu))
    finally:
        for b in bars:
            b.close()


@dataclasses.dataclass(frozen=True)
class _Outcome:
    """What one invocation of reproduce computed and how long it took."""

    rows: list  # the frame rows
    started: dict  # provenance (revision, time) the invocation started with
    wall: float  # wall-clock seconds of the frames phase
    cpu: dict  # the workers' CPU seconds per stage, this invocation
    done: dict  # preset -> frames done
    complete: bool  # every preset has all its frames


def _write_reproduction(args, config, out, store, designs, outcome: _Outcome) -> None:
    """Log the invocation, write the tables, claims and meta under ``out`` and print the
    summary line."""
    rows, started, wall = outcome.rows, outcome.started, outcome.wall
    cpu, done, complete = outcome.cpu, outcome.done, outcome.complete
    from drake_cert.config import load_conditions
    from drake_cert.experiments import claims, outputs, paper_claims, tables
    from drake_cert.experiments.reproduce import tasks_for
    from drake_cert.io import provenance

    runs = log_run(out / "store" / "runs.json", dict(
        started, wall_s=round(wall, 1), cpu_s=cpu, executor=args.executor,
        workers=args.workers if args.executor == "ray" else 1, frames_done=done,
        machine=_machine(config.precision)))
    summary = tables.summarize(rows, config.eps, config.seed)
    # The frames' revisions lead: the tables are theirs; this invocation only wrote them. Its
    # revision is the one it started from: by now it has written files that may be tracked
    # (the run log, the store), which would read as "-dirty".
    written_by = dict(provenance(seed=config.seed), git_revision=started["git_revision"])
    meta = dict(computed_by_revisions=store.revisions(tasks_for(config)),
                written_by_revision=written_by.pop("git_revision"), **written_by,
                wall_s=round(wall, 1),
                executor=args.executor, workers=args.workers if args.executor == "ray" else 1,
                machine=runs[-1]["machine"], frame_cells=len(rows), frames_done=done,
                complete=complete,
                total_wall_s=round(sum(r["wall_s"] for r in runs), 1),
                total_cpu_s=_total_cpu(runs),
                # every stored part's CPU, stopped invocations included ({}: made before it)
                store_cpu_s=store.cpu(store.identity(config, designs)), runs=runs)
    bounds = claims.conformal_miss_bounds(store.conformal(store.identity(config, designs)))
    written = outputs.write_results(out, outputs.RunResults(rows, summary, meta, bounds), config,
                                    load_conditions(), plots=not args.no_plots, designs=designs)
    document = json.loads((out / "claims.json").read_text())
    holds = {p: c["holds"] for p, c in claims.preset_claims(document).items()}
    paper = document["paper_claims"]
    print(json.dumps({"out": str(out), "wall_s": round(wall, 1),
                      "cpu_s": round(sum(cpu.values()), 1), "cells": len(summary),
                      "frame_cells": len(rows), "frames_done": done, "complete": complete,
                      "paper_claims": paper["counts"],
                      "paper_claims_failing": paper_claims.failing(paper),
                      "claims_hold": holds, "files": [str(p) for p in written]}))


def _total_cpu(runs: list[dict]) -> dict:
    """The workers' CPU seconds per stage over every invocation that recorded them, and their
    sum (``invocations_without``: earlier invocations that did not record CPU time)."""
    total: dict = {}
    for run in runs:
        for stage, seconds in (run.get("cpu_s") or {}).items():
            total[stage] = round(total.get(stage, 0.0) + seconds, 1)
    return dict(total, all=round(sum(total.values()), 1),
                invocations_without=sum("cpu_s" not in r for r in runs))
