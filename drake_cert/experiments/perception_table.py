"""The perception table: what the run-time stiffness intervals promise, measured.

For each preset, on the SAME test frames (round-robin over labels), at the same budgets:

* classification -- the base classifier f (sigma = 0) and the smoothed classifier g (sigma > 0),
  clean and under the stability (SA) and efficiency (EA) attacks, each attack made against the
  model it reports (PGD on f, SmoothAdv on g). For g: accuracy at the observed frame, the
  safe-set run-time interval of the paper (:func:`runtime_classification_interval`; covers the
  true stiffness only if g is right on the clean frame) and the robust conformal interval
  (:mod:`drake_cert.certification.conformal`; covers it with probability >= 1 - alpha_total
  with no such assumption): coverage of the true stiffness with its 95 % Clopper-Pearson
  interval, mean width, and the guarantee beside it.
* regression -- the base regressor (sigma = 0: mean absolute error clean and attacked) and the
  median-smoothed regressor h (sigma > 0): coverage and width of ``[lower - beta, upper +
  beta]`` (:func:`runtime_interval`), guarantee ``1 - alpha - alpha_c - alpha_m``.

Every number comes from :func:`certify_classifier` / :func:`certify_regressor`, the functions
``drake-cert certify`` runs, with the model in the stated precision. Work shared between cells
is computed once and is identical to what each cell would compute alone (same seed streams):
the conformal calibrations and the clean certificates of g. Each cell is written atomically as
JSON as soon as it is done, so an interrupted run resumes with the next cell; a stored cell
is reused only if it was made with the same settings and the same model file (SHA-256).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from drake_cert.certification.classifier import SmoothedClassifier
from drake_cert.certification.regressor import MedianSmoothedRegressor
from drake_cert.certification.sampler import with_precision
from drake_cert.certification.seeds import frame_choice_seed
from drake_cert.config import ConditionsTable
from drake_cert.errors import ConfigError
from drake_cert.experiments.perception_eval import (
    CalibrationInputs,
    CertifySettings,
    EvalFrames,
    calibrate_classifier,
    calibrate_regressor,
    certify_classifier,
    certify_regressor,
    clopper_pearson_interval,
    decision_shares,
    json_safe,
    select_frames,
)
from drake_cert.io import atomic_write_text

PRESETS = ("carla-like", "rtk-like", "robotcar-like")
ATTACKS = ("none", "sa", "ea")
DATA_SEED = 0  # the synthetic splits the shipped models were trained and tested on


@dataclasses.dataclass(frozen=True)
class TableSettings:
    """Sizes and levels of the table (budgets: L2 in [0, 1] pixel space)."""

    sigma: float = 0.25  # smoothing noise of g and h
    budgets: tuple[float, ...] = (0.25, 0.5)
    frames: int = 300  # test frames per preset (every cell uses the same ones)
    n0: int = 64
    n: int = 500
    alpha: float = 0.001
    calibration_n: int = 500  # samples per calibration frame (both calibrations)
    conformal_per_class: int = 150  # classification calibration frames per label
    regression_per_class: int = 100  # regression calibration frames per label
    attack_steps: int = 10
    precision: str = "auto"  # fp32 or bf16; "auto" is resolved on construction
    compile: str = "on"
    batch_size: int = 1000
    seed: int = 0
    tasks: tuple[str, ...] = ("classify", "regress")

    def __post_init__(self):
        from drake_cert.certification.sampler import resolve_precision

        object.__setattr__(self, "precision", resolve_precision(self.precision))

    def validate(self) -> None:
        if not self.budgets or any(not (math.isfinite(e) and e > 0) for e in self.budgets):
            raise ConfigError(f"budgets {self.budgets} must be positive numbers")
        if self.sigma <= 0:
            raise ConfigError(f"sigma = {self.sigma} must be > 0 (sigma 0 is f, always run)")
        unknown = set(self.tasks) - {"classify", "regress"}
        if unknown or not self.tasks:
            raise ConfigError(f"tasks {self.tasks} must be among classify, regress")
        self.certify("carla-like", "classify", self.sigma, "none", self.budgets[0]).validate()

    def identity(self) -> dict:
        """What a stored cell must have been made with to be reused (all but ``tasks``)."""
        d = dataclasses.asdict(self)
        d.pop("tasks")
        d["budgets"] = list(d["budgets"])
        return d

    def certify(self, preset: str, task: str, sigma: float, attack: str,
                eps: float) -> CertifySettings:
        """The :class:`CertifySettings` of one cell (what ``drake-cert certify`` would use)."""
        return CertifySettings(
            preset=preset, sigma=sigma, task=task, attack=attack, eps=eps, n0=self.n0, n=self.n,
            alpha=self.alpha, frames=self.frames, batch_size=self.batch_size, seed=self.seed,
            compile=self.compile, attack_steps=self.attack_steps,
            calibration_per_class=self.regression_per_class, calibration_n=self.calibration_n,
            conformal=task == "classify" and sigma > 0,
            conformal_per_class=self.conformal_per_class, precision=self.precision)

    def cells(self, task: str) -> list[tuple[str, float, str, float]]:
        """(model, sigma, attack, eps) of every cell of a task, in run order."""
        out = []
        for model, sigma in (("f", 0.0), ("g", self.sigma)):
            for attack in ATTACKS:
                for eps in self.budgets:
                    out.append((model, sigma, attack, eps))
        return out


def cell_key(task: str, model: str, attack: str, eps: float) -> str:
    return f"{task}_{model}_{attack}_eps{eps:g}"


class CellStore:
    """One JSON file per (preset, cell) under ``root``; written atomically."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def path(self, preset: str, key: str) -> Path:
        return self.root / preset / f"{key}.json"

    def get(self, preset: str, key: str) -> dict | None:
        p = self.path(preset, key)
        return json.loads(p.read_text()) if p.exists() else None

    def put(self, preset: str, key: str, cell: dict) -> None:
        atomic_write_text(self.path(preset, key),
                          json.dumps(json_safe(cell), indent=1, allow_nan=False))


@dataclasses.dataclass(frozen=True)
class CellReport:
    """How :func:`run_preset` reports: ``progress(desc)`` wraps a cell's frame iterator (a
    bar); ``log(message)`` gets one line per computed cell."""

    progress: Callable[[str], Callable[[Iterable], Iterable]] | None = None
    log: Callable[[str], None] = print


def run_preset(preset: str, ts: TableSettings, table: ConditionsTable, store: CellStore, *,
               models: str | Path | None = None,
               report: CellReport | None = None) -> dict[str, dict]:
    """Every cell of one preset (computed, or read back from ``store``); key -> cell.
    ``report`` (:class:`CellReport`, default: no bars, lines printed): progress and log."""
    report = report or CellReport()
    progress, log = report.progress, report.log
    from drake_cert.perception.datasets import load_split
    from drake_cert.perception.models import file_sha256, load_model, model_path

    ts.validate()
    table.preset(preset)
    bar = progress or (lambda desc: None)
    out: dict[str, dict] = {}
    test = None
    identity = ts.identity()

    def stored(task: str, model_name: str, sigma: float, attack: str, eps: float) -> dict | None:
        """The stored cell, if made with these settings and the model file as it is now."""
        cell = store.get(preset, cell_key(task, model_name, attack, eps))
        if cell is None or cell.get("settings") != identity:
            return None
        if cell.get("model_sha256") != file_sha256(model_path(preset, task, sigma, models)):
            return None
        return cell

    for task in ts.tasks:
        todo = []
        for model_name, sigma, attack, eps in ts.cells(task):
            if (cell := stored(task, model_name, sigma, attack, eps)) is not None:
                out[cell_key(task, model_name, attack, eps)] = cell
            else:
                todo.append((model_name, sigma, attack, eps))
        if not todo:
            continue
        shared: dict = {"clean_cache": {}}
        for model_name, sigma, attack, eps in todo:
            key = cell_key(task, model_name, attack, eps)
            model = load_model(preset, task, sigma, models)
            size = int(model.meta.get("image_size", 64))
            if test is None or test[0] != size:
                k = len(table.preset(preset).labels)
                split = load_split(preset, "test", seed=DATA_SEED, size=size,
                                   frames_per_class=math.ceil(ts.frames / k), conditions=table)
                idx = select_frames(split.labels, ts.frames, frame_choice_seed(ts.seed))
                test = (size, split, idx)
            _, split, idx = test
            frames = (split.images[idx], split.labels[idx], split.stiffness_n_per_rad[idx])
            settings = ts.certify(preset, task, sigma, attack, eps)
            start = time.perf_counter()
            calibration = None
            if sigma > 0:  # one conformal calibration per preset and task, shared by its cells
                if "calibration" not in shared:
                    calibrate = (_classification_calibration if task == "classify"
                                 else _regression_calibration)
                    shared["calibration"] = calibrate(model, preset, settings, table, size,
                                                      bar(f"{preset} calibrate {task}"))
                calibration = shared["calibration"]
            if task == "classify":
                records, summary = certify_classifier(
                    model, EvalFrames(*frames, tuple(split.label_names)), table, settings,
                    bar(f"{preset} {key}"), CalibrationInputs(
                        made=calibration,
                        clean_cache=shared["clean_cache"] if sigma > 0 else None))
            else:
                records, summary = certify_regressor(
                    model, EvalFrames(*frames), table.envelope(preset), settings,
                    bar(f"{preset} {key}"), CalibrationInputs(made=calibration))
            cell = {"preset": preset, "task": task, "model": model_name, "sigma": sigma,
                    "attack": attack, "eps": eps, "summary": summary, "records": records,
                    "seconds": time.perf_counter() - start, "settings": identity,
                    "model_sha256": file_sha256(model_path(preset, task, sigma, models))}
            store.put(preset, key, cell)
            out[key] = json.loads(json.dumps(json_safe(cell)))
            log(f"{preset} {key}: {cell['seconds']:.0f} s")
    return out


def _classification_calibration(model, preset: str, settings: CertifySettings,
                                table: ConditionsTable, size: int, progress):
    from drake_cert.perception.datasets import load_split

    cal = load_split(preset, "calibration", seed=DATA_SEED, size=size,
                     frames_per_class=settings.conformal_per_class, conditions=table)
    smooth = SmoothedClassifier(with_precision(model, settings.precision),
                                len(cal.label_names), settings.sigma,
                                device=settings.device, compile=settings.compile_model(1 << 30))
    return calibrate_classifier(smooth, (cal.images, cal.labels), settings, progress)


def _regression_calibration(model, preset: str, settings: CertifySettings,
                            table: ConditionsTable, size: int, progress):
    from drake_cert.experiments.perception_eval import check_regression_calibration
    from drake_cert.perception.datasets import load_split

    cal = load_split(preset, "calibration", seed=DATA_SEED, size=size,
                     frames_per_class=settings.calibration_per_class, conditions=table)
    check_regression_calibration(cal.labels, cal.labels, settings.alpha_c)
    smooth = MedianSmoothedRegressor(with_precision(model, settings.precision), settings.sigma,
                                     device=settings.device,
                                     compile=settings.compile_model(1 << 30))
    return calibrate_regressor(smooth, (cal.images, cal.stiffness_n_per_rad, cal.labels),
                               settings, progress)


# ---------------------------------------------------------------------------------------------
# Rows and rendering


def coverage(records: list[dict], field: str = "covered") -> dict:
    """Share of records whose interval holds the true stiffness, with its 95 % Clopper-Pearson
    interval and the counts."""
    hits = int(sum(bool(r[field]) for r in records))
    lo, hi = clopper_pearson_interval(hits, len(records))
    return {"covered": hits, "frames": len(records), "share": hits / len(records),
            "ci95": [lo, hi]}


def _width(records: list[dict], field: str) -> float:
    return float(np.mean([r[field][1] - r[field][0] for r in records]))


def classification_row(f_cell: dict, g_cell: dict) -> dict:
    """One row: f and g on the same frames under one attack at one budget."""
    g = g_cell["records"]
    right = [r for r in g if r["clean_prediction"] == r["label"]]
    return {
        "attack": g_cell["attack"], "eps": g_cell["eps"], "frames": len(g),
        "f_accuracy": f_cell["summary"]["accuracy"],
        "g_accuracy": g_cell["summary"]["accuracy"],
        "g_abstain": g_cell["summary"]["abstain_rate"],
        "safe_set_certified": 1 - g_cell["summary"]["envelope_rate"],
        # cells stored before the outcomes were recorded have no "interval_holds_label"
        "outcomes": decision_shares(g) if all("interval_holds_label" in r for r in g) else None,
        "safe_set": coverage(g) | {"width_n_per_rad": _width(g, "interval_n_per_rad")},
        "safe_set_given_clean_right": coverage(right) if right else None,
        "conformal": coverage(g, "conformal_covered")
        | {"width_n_per_rad": _width(g, "conformal_interval_n_per_rad")},
        "conformal_guarantee": g_cell["summary"]["conformal_guarantee"],
    }


def regression_row(f_cell: dict, h_cell: dict) -> dict:
    s = h_cell["summary"]
    return {
        "attack": h_cell["attack"], "eps": h_cell["eps"], "frames": len(h_cell["records"]),
        "f_mae_n_per_rad": f_cell["summary"]["mae_n_per_rad"],
        "h_mae_n_per_rad": s["mae_n_per_rad"],
        "interval": coverage(h_cell["records"])
        | {"width_n_per_rad": s["interval_width_mean"]},
        "beta_n_per_rad": s["beta_n_per_rad"],
        "guarantee": 1 - s["alpha"] - REGRESSION_ALPHA_C - REGRESSION_ALPHA_M,
    }


REGRESSION_ALPHA_C = CertifySettings.alpha_c
REGRESSION_ALPHA_M = CertifySettings.alpha_m


def rows(cells: dict[str, dict], ts: TableSettings) -> dict[str, list[dict]]:
    """The table's rows of one preset from its cells (missing cells are skipped)."""
    out: dict[str, list[dict]] = {"classify": [], "regress": []}
    for attack in ATTACKS:
        for eps in ts.budgets:
            for task, make in (("classify", classification_row), ("regress", regression_row)):
                f_cell = cells.get(cell_key(task, "f", attack, eps))
                g_cell = cells.get(cell_key(task, "g", attack, eps))
                if f_cell is not None and g_cell is not None:
                    out[task].append(make(f_cell, g_cell))
    return out


def _outcomes(o: dict | None) -> str:
    if o is None:
        return "-"
    lo, hi = o["certified_wrong_rate_ci95"]
    return (f"{o['certified_right_rate']:.3f} / {o['certified_wrong_rate']:.3f} "
            f"[{lo:.3f}, {hi:.3f}] / {o['interval_abstain_rate']:.3f}")


def _cov(c: dict) -> str:
    return f"{c['share']:.3f} [{c['ci95'][0]:.3f}, {c['ci95'][1]:.3f}]"


def render(all_rows: dict[str, dict[str, list[dict]]], ts: TableSettings,
           header: list[str] | None = None) -> str:
    """Markdown of the table (one section per preset)."""
    lines = ["# Perception: run-time stiffness intervals, clean and attacked", ""]
    lines += header or []
    lines += [
        f"Settings: test frames per preset {ts.frames} (round-robin over labels, the same "
        f"frames in every cell); sigma = {ts.sigma:g} for g and h; n0 = {ts.n0}, n = {ts.n}, "
        f"alpha = {ts.alpha:g}; models evaluated in {ts.precision} (certificates are those of "
        f"the {ts.precision} model); attacks: L2 PGD, {ts.attack_steps} steps, against f for "
        "f's columns and SmoothAdv (8 noise draws per step) against g / h for theirs, at the "
        "budget eps of the row, which is also the budget of the run-time intervals. "
        f"Conformal calibration: {ts.conformal_per_class} held-out frames per label "
        f"(classification), {ts.regression_per_class} (regression), {ts.calibration_n} "
        "samples each. Coverage: share of frames whose interval holds the TRUE stiffness, "
        "with its 95 % Clopper-Pearson interval. Label range at eps: share of frames whose "
        "certified range holds the true label (right), misses it (WRONG: the safe-set interval "
        "then excludes the truth), or none is certified (abstain: the envelope). Widths in "
        "kN/rad.", ""]
    for preset, r in all_rows.items():
        lines += [f"## {preset}", ""]
        if r["classify"]:
            lines += [
                "| attack | eps | f acc. | g acc. | g abstain | label range at eps: certified "
                "right / WRONG [95% CI] / abstain | safe-set interval: certified "
                "/ coverage [95% CI] / width | coverage if g right on clean | robust "
                "conformal: coverage [95% CI] / width | guarantee (conformal) |",
                "|---|---|---|---|---|---|---|---|---|---|"]
            for row in r["classify"]:
                given = row["safe_set_given_clean_right"]
                lines.append(
                    f"| {row['attack']} | {row['eps']:g} | {row['f_accuracy']:.3f} | "
                    f"{row['g_accuracy']:.3f} | {row['g_abstain']:.3f} | "
                    f"{_outcomes(row.get('outcomes'))} | "
                    f"{row['safe_set_certified']:.2f} / {_cov(row['safe_set'])} / "
                    f"{row['safe_set']['width_n_per_rad'] / 1e3:.1f} | "
                    f"{_cov(given) if given else '-'} | {_cov(row['conformal'])} / "
                    f"{row['conformal']['width_n_per_rad'] / 1e3:.1f} | "
                    f">= {row['conformal_guarantee']:.2f} |")
            lines.append("")
        if r["regress"]:
            lines += [
                "| attack | eps | f MAE | h MAE | h interval: coverage [95% CI] / width | "
                "beta | guarantee |", "|---|---|---|---|---|---|---|"]
            for row in r["regress"]:
                lines.append(
                    f"| {row['attack']} | {row['eps']:g} | {row['f_mae_n_per_rad'] / 1e3:.1f} "
                    f"| {row['h_mae_n_per_rad'] / 1e3:.1f} | {_cov(row['interval'])} / "
                    f"{row['interval']['width_n_per_rad'] / 1e3:.1f} | "
                    f"{row['beta_n_per_rad'] / 1e3:.1f} | >= {row['guarantee']:.3f} |")
            lines.append("")
    lines += [
        "Safe-set interval (the paper's): the narrowest contiguous label range certified at "
        "the observed frame beyond eps, the envelope otherwise; it promises that the "
        "PREDICTION cannot be pushed out of the range, so it holds the true stiffness only "
        "when g is right on the clean frame (its column 'coverage if g right'). Robust "
        "conformal interval: holds the true stiffness with probability >= 1 - alpha_total "
        "under any L2 perturbation <= eps, with no assumption on g (docs/design.md 8, soundness). "
        "Regression: [lower - beta, upper + beta] from median smoothing and a per-label "
        "conformal beta (largest over labels at run time); guarantee 1 - alpha - alpha_c - "
        "alpha_m. A measured coverage below its guarantee is a failure only when the "
        "guarantee lies above the whole confidence interval.", ""]
    return "\n".join(lines)
