"""The reproduction's calibrations, computed before its frames and spread over its executor:
h's conformal beta per (preset, sigma) (DESIGN 3) and, for the pipeline g_conformal, g's robust
conformal calibration per (preset, sigma). A beta comes from its own seed stream
(``regression_calibration`` (preset, sigma) of the root seed) and g's calibration is the
drive's, the model's own (docs/design.md 3.6), so a pair's numbers are those it gets computed
alone, in any run; the run's store keeps them as they arrive.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING

from drake_cert.certification.seeds import Purpose
from drake_cert.config import load_conditions
from drake_cert.experiments.reproduce_config import (
    ReproduceConfig,
    calibration_seed,
    evaluated_run_model,
    run_model,
)

if TYPE_CHECKING:
    from drake_cert.experiments.run_store import RunStore


def calibration_beta(config: ReproduceConfig, preset: str, sigma: float, model,
                     conditions) -> float:
    """The h pipeline's conformal beta for (preset, sigma), ``model`` from :func:`run_model`
    evaluated as the run evaluates it: Mondrian split conformal on
    ``calibration_per_class`` frames per label of the calibration split (DESIGN 3), with its own
    seed stream; infinite (the envelope) when too few frames for alpha_c."""
    from drake_cert.certification.regressor import MedianSmoothedRegressor, calibrate_conformal
    from drake_cert.certification.sampler import CalibrationSampling
    from drake_cert.perception.datasets import load_split

    c = config
    cal = load_split(preset, "calibration", conditions=conditions,
                     frames_per_class=c.calibration_per_class)
    sampling = CalibrationSampling(
        n=c.calibration_n, batch_size=min(c.batch_size, c.calibration_n),
        seed=calibration_seed(c, Purpose.REGRESSION_CALIBRATION, preset, sigma))
    calib = calibrate_conformal(
        MedianSmoothedRegressor(evaluated_run_model(c, model), sigma, device=c.device),
        cal.images, cal.stiffness_n_per_rad.tolist(),
        cal.labels.tolist(), sampling=sampling, alpha_m=c.alpha_m, alpha_c=c.alpha_c)
    return calib.beta


@dataclasses.dataclass(frozen=True)
class CalibrationTask:
    preset: str
    sigma: float


class CalibrationWorker:
    """Computes the h pipeline's beta for one (preset, sigma) (an executor worker)."""

    def __init__(self, config: ReproduceConfig):
        self.config, self.conditions = config, load_conditions()

    def __call__(self, task: CalibrationTask) -> float:
        model = run_model(self.config, task.preset, "regress", task.sigma)
        return calibration_beta(self.config, task.preset, task.sigma, model, self.conditions)


@dataclasses.dataclass(frozen=True)
class CalibrationLedger:
    """Where :func:`map_calibrations` keeps its results: ``stored``, the calibrations so far
    keyed by (preset, sigma), and ``put(stored, cpu_s)``, which writes them back."""

    stored: dict
    put: Callable[[dict, float], None]


def map_calibrations(tasks: list[CalibrationTask], make_worker, ledger: CalibrationLedger,
                     executor=None, progress: Callable[[int], None] | None = None,
                     spent: list[float] | None = None) -> dict:
    """The calibration of every (preset, sigma) task, spread over ``executor``; those already in
    ``ledger.stored`` (keyed by (preset, sigma)) are not recomputed, each new one is handed to
    ``ledger.put(stored, cpu_s)`` as it arrives with its workers' CPU seconds (a stopped run
    keeps them, and the store's ledger their cost); the seconds are also appended to
    ``spent``."""
    from drake_cert.experiments.executors import LocalExecutor, cpu_timed

    stored, put = ledger.stored, ledger.put

    todo = [t for t in tasks if (t.preset, t.sigma) not in stored]

    def store_calibration(index: int, result) -> None:
        value, cpu_s = result
        stored[(todo[index].preset, todo[index].sigma)] = value
        if spent is not None:
            spent.append(cpu_s)
        put(stored, cpu_s)

    if progress is not None:
        progress(len(tasks) - len(todo))
    (executor or LocalExecutor()).map(cpu_timed(make_worker), todo, progress,
                                      on_result=store_calibration)
    return {(t.preset, t.sigma): stored[(t.preset, t.sigma)] for t in tasks}


def calibration_betas(config: ReproduceConfig, executor=None, store: RunStore | None = None,
                      identity: str = "", progress: Callable[[int], None] | None = None,
                      spent: list[float] | None = None) -> dict:
    """Every (preset, sigma) beta of the run, spread over ``executor`` before the frames (read
    back from ``store`` when it holds them under ``identity``)."""
    if not config.regression:
        return {}
    tasks = [CalibrationTask(p, s) for p in config.presets for s in config.sigmas]
    stored = store.betas(identity) if store is not None else {}
    put = (lambda b, s: store.put_betas(identity, b, s)) if store is not None \
        else (lambda b, s: None)
    return map_calibrations(tasks, lambda: CalibrationWorker(config),
                            CalibrationLedger(stored, put), executor, progress, spent)


def conformal_sigmas(config: ReproduceConfig) -> list[float]:
    """Every sigma g certifies with in the run, ascending."""
    return sorted({*config.sigmas, config.sweep_sigma})


def conformal_calibration(config: ReproduceConfig, preset: str, sigma: float, conditions=None):
    """g's robust conformal calibration at (preset, sigma): the drive's
    (:func:`drake_cert.systems.driving.drive_conformal_calibration`, docs/design.md 3.6) with
    the run's settings: the model's true-label votes on ``conformal_per_class`` calibration
    frames a label, ``conformal_n`` samples each (read from the file shipped beside the model
    when its spec matches, else the calibration cache's, else drawn), thresholds bounded in
    ``conformal_bins_per_label`` stiffness bins a label at ``conformal_alpha_c`` outside an
    event of probability ``conformal_delta_cal``. The model is evaluated on the CPU as a drive
    evaluates it (the run's backend and precision)."""
    from drake_cert.certification.backends import evaluated_model
    from drake_cert.systems import driving

    scenario = conformal_scenario(config, preset, sigma)
    p = scenario.perception
    model = evaluated_model(run_model(config, preset, "classify", sigma), backend=p.backend,
                            precision=p.precision)
    return driving.drive_conformal_calibration(model, scenario, conditions or load_conditions())


def conformal_scenario(config: ReproduceConfig, preset: str, sigma: float):
    """A scenario whose perception settings are the run's g_conformal calibration at (preset,
    sigma): what :func:`conformal_calibration` hands the drive's calibration (the model on the
    CPU, in the run's backend and precision)."""
    from drake_cert.systems.scenario import PerceptionSettings, Scenario

    c = config
    return Scenario(name="reproduce", perception=PerceptionSettings(
        preset=preset, task="classify", sigma=float(sigma), precision=c.precision,
        backend=c.backend if c.device == "cpu" else "torch",
        conformal_frames_per_class=c.conformal_per_class, conformal_calibration_n=c.conformal_n,
        conformal_alpha_c=c.conformal_alpha_c, conformal_bins_per_label=c.conformal_bins_per_label,
        conformal_delta_cal=c.conformal_delta_cal))


class ConformalWorker:
    """Computes g's robust conformal calibration for one (preset, sigma) (an executor worker)."""

    def __init__(self, config: ReproduceConfig):
        self.config, self.conditions = config, load_conditions()

    def __call__(self, task: CalibrationTask):
        return conformal_calibration(self.config, task.preset, task.sigma, self.conditions)


def conformal_calibrations(config: ReproduceConfig, executor=None, store: RunStore | None = None,
                           identity: str = "", progress: Callable[[int], None] | None = None,
                           spent: list[float] | None = None) -> dict:
    """g's robust conformal calibration for every (preset, sigma) the run certifies with
    (empty without the pipeline g_conformal), spread over ``executor`` and kept in ``store``
    like the betas; each pair's numbers are those it gets computed alone."""
    if not config.conformal:
        return {}
    tasks = [CalibrationTask(p, s) for p in config.presets for s in conformal_sigmas(config)]
    stored = store.conformal(identity) if store is not None else {}
    put = (lambda c, s: store.put_conformal(identity, c, s)) if store is not None \
        else (lambda c, s: None)
    return map_calibrations(tasks, lambda: ConformalWorker(config),
                            CalibrationLedger(stored, put), executor, progress, spent)
