"""Reproduce the paper's experiments as per-frame episodes (paper section V, DESIGN 7, issue 8).

For every test frame of a preset (true label, true stiffness, true friction) and every cell
(pipeline x sigma x attack x budget): the attack on the pipeline under test, its perception
output, the run-time stiffness interval, the design chosen for that interval, the design's
safe speed (0 = stop) and one closed-loop episode on the Fiala plant with the frame's true
stiffness and friction (:mod:`drake_cert.experiments.episodes`).

Pipelines (the same frames, attacks and budgets for each):
- ``f``: the non-robust classifier (sigma = 0); the predicted label's interval and design;
  SA/EA are L2 PGD on f.
- ``g``: the smoothed classifier at sigma; CERTIFY at the observed frame and the run-time
  interval at budget eps (DESIGN 3), the envelope when nothing is certified; SA/EA are
  SmoothAdv PGD on g (expectation over the smoothing noise). Its ``certificate`` is the
  certified radius of the label range the run-time interval came from (0 on the envelope);
  ``safe_set_radius`` is the paper's R_S(a), infinite when S(a) is the whole family.
- ``f_reg``: the non-robust regressor; its prediction (clipped to the preset's envelope) gets
  the narrowest design containing it.
- ``h``: the median-smoothed regressor; order-statistic bounds at eps widened by the Mondrian
  conformal beta (DESIGN 3), the narrowest design containing that interval.

Seeds: one root seed; every frame and purpose has its own ``numpy.random.SeedSequence``
(spawn key ``(preset, frame, purpose, cell)``), so no attack draws the noise of the
certificate it attacks, and a frame's rows can be recomputed alone
(:func:`recompute_frame`) with the same numbers, whatever the executor.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.errors import ConfigError

PIPELINES = ("f", "g", "f_reg", "h")
ATTACK_KINDS = ("none", "sa", "ea")

# Purposes of the seed streams (spawn-key entries; distinct by construction). A cell's
# blocks draw their attack and certificate noise from SeedSequence([cell seed, purpose, frame])
# (systems.streams), the cell seed being the root's child (preset, CELL, cell).
FRAME_CHOICE, CALIBRATION, CELL, CONFORMAL = 0, 1, 2, 3


@dataclasses.dataclass(frozen=True)
class ReproduceConfig:
    """What to reproduce; budgets are L2 norms in [0, 1] pixel space."""

    presets: tuple[str, ...] = ("carla-like", "rtk-like", "robotcar-like")
    sigmas: tuple[float, ...] = (0.25, 0.5, 1.0)
    eps: float = 0.25  # budget of the main tables (attack and certificate)
    sweep_eps: tuple[float, ...] = (0.0, 0.25, 0.5, 1.0, 1.5, 2.0)  # classification sweep
    sweep_sigma: float = 0.5  # the g of the sweep
    frames: int = 100  # test frames per preset; every cell sees the same frames
    n0: int = 100
    n: int = 10_000
    alpha: float = 0.001
    batch_size: int = 250  # noisy copies per forward pass (larger batches page-fault: slower)
    attack_steps: int = 20
    attack_noise_draws: int = 8
    regression: bool = True
    calibration_per_class: int = 100  # conformal calibration frames per label
    calibration_n: int = 1000  # samples per calibration frame
    alpha_c: float = 0.01
    alpha_m: float = 0.001
    interval: str = "safe_set"  # g's interval: "safe_set" (paper) or "conformal" (DESIGN 3)
    conformal_per_class: int = 150  # robust conformal calibration frames per label (>= 124)
    conformal_n: int = 500  # samples per conformal calibration frame
    precision: str = "bf16"  # model arithmetic for attacks, certificates and calibration alike
    seed: int = 0

    @staticmethod
    def quick(seed: int = 0) -> ReproduceConfig:
        """A few frames per cell, small n, one budget: the CI-sized run (< 2 min on 2 cores)."""
        return ReproduceConfig(sigmas=(0.25, 0.5, 1.0), eps=0.25, sweep_eps=(0.25,),
                               sweep_sigma=0.25, frames=2, n0=20, n=200, batch_size=200,
                               attack_steps=4, attack_noise_draws=2, calibration_per_class=6,
                               calibration_n=100, seed=seed)

    def validate(self) -> None:
        conditions = load_conditions()
        known = [p.name for p in conditions.presets]
        for p in self.presets:
            if p not in known:
                raise ConfigError(f"unknown preset {p!r}; expected one of {known}")
        for name in ("frames", "n0", "n", "batch_size", "calibration_per_class",
                     "calibration_n"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name} = {getattr(self, name)} must be a positive integer")
        for s in (*self.sigmas, self.sweep_sigma):
            if not (math.isfinite(s) and s > 0):
                raise ConfigError(f"sigma = {s!r} must be positive")
        for e in (self.eps, *self.sweep_eps):
            if not (math.isfinite(e) and e >= 0):
                raise ConfigError(f"eps = {e!r} must be a finite number >= 0")
        if not 0 < self.alpha < 1:
            raise ConfigError(f"alpha = {self.alpha!r} must be in (0, 1)")
        if self.interval not in ("safe_set", "conformal"):
            raise ConfigError(f"interval {self.interval!r} is not 'safe_set' or 'conformal'")
        for name in ("conformal_per_class", "conformal_n"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name} = {getattr(self, name)} must be a positive integer")
        from drake_cert.certification.sampler import PRECISIONS

        if self.precision not in PRECISIONS:
            raise ConfigError(f"precision {self.precision!r} is not one of {', '.join(PRECISIONS)}")
        if self.seed < 0:
            raise ConfigError(f"seed = {self.seed} must be >= 0")

    def cells(self) -> list[tuple[str, float, str, float]]:
        """Every (pipeline, sigma, attack, eps) evaluated on each frame, in a fixed order.

        Main tables: f, g (each sigma), f_reg and h (each sigma), clean and under SA and EA,
        at budget ``eps`` (a clean frame's run-time interval is also taken at ``eps``).
        Sweep: f and g at ``sweep_sigma`` under SA and EA at every other budget (eps = 0:
        g's clean interval at budget 0).
        """
        out: list[tuple[str, float, str, float]] = []
        for kind in ATTACK_KINDS:
            out.append(("f", 0.0, kind, self.eps))
            out.extend(("g", s, kind, self.eps) for s in self.sigmas)
            if self.regression:
                out.append(("f_reg", 0.0, kind, self.eps))
                out.extend(("h", s, kind, self.eps) for s in self.sigmas)
        for eps in sorted(set(self.sweep_eps) - {self.eps}):
            if eps == 0:
                out.append(("g", self.sweep_sigma, "none", 0.0))
                continue
            for kind in ("sa", "ea"):
                out += [("f", 0.0, kind, eps), ("g", self.sweep_sigma, kind, eps)]
        return out


def preset_key(preset: str) -> int:
    """A preset's stable spawn-key entry: its position in the conditions table (not in the
    run's preset list), so a preset gets the same frames and streams in any selection."""
    return [p.name for p in load_conditions().presets].index(preset)


def seed_of(config: ReproduceConfig, *key: int) -> int:
    """A 63-bit integer seed of the stream with spawn key ``key`` under the root seed."""
    from drake_cert.certification.seeds import seed_from_sequence

    return seed_from_sequence(np.random.SeedSequence(entropy=config.seed,
                                                     spawn_key=tuple(int(k) for k in key)))


def frame_indices(config: ReproduceConfig, preset_index: int, labels) -> np.ndarray:
    """The test frames of a preset: round-robin over classes from a seeded permutation."""
    from drake_cert.experiments.perception_eval import select_frames

    return select_frames(labels, config.frames, seed_of(config, preset_index, FRAME_CHOICE))


@dataclasses.dataclass(frozen=True)
class FrameTask:
    preset: str
    position: int  # which of the preset's chosen frames (0 .. frames - 1)


def calibration_beta(config: ReproduceConfig, preset: str, sigma: float, model,
                     conditions) -> float:
    """The h pipeline's conformal beta for (preset, sigma): Mondrian split conformal on
    ``calibration_per_class`` frames per label of the calibration split (DESIGN 3), with its own
    seed stream; infinite (the envelope) when too few frames for alpha_c."""
    from drake_cert.certification.regressor import MedianSmoothedRegressor, calibrate_conformal
    from drake_cert.perception.datasets import load_split

    c = config
    cal = load_split(preset, "calibration", conditions=conditions,
                     frames_per_class=c.calibration_per_class)
    calib = calibrate_conformal(
        MedianSmoothedRegressor(model, sigma), cal.images, cal.stiffness_n_per_rad.tolist(),
        cal.labels.tolist(), n=c.calibration_n, batch_size=min(c.batch_size, c.calibration_n),
        alpha_m=c.alpha_m, alpha_c=c.alpha_c,
        seed=seed_of(c, preset_key(preset), CALIBRATION,
                     c.sigmas.index(sigma) if sigma in c.sigmas else 99))
    return calib.beta


def run_model(config: ReproduceConfig, preset: str, task: str, sigma: float):
    """The shipped model of (preset, task, sigma) in the run's precision: the one module that
    the run's attacks, certificates and calibrations all evaluate."""
    from drake_cert.certification.sampler import with_precision
    from drake_cert.perception.models import load_model

    return with_precision(load_model(preset, task, sigma), config.precision)


@dataclasses.dataclass(frozen=True)
class CalibrationTask:
    preset: str
    sigma: float


class CalibrationWorker:
    """Computes the h pipeline's beta for one (preset, sigma) (an executor worker)."""

    def __init__(self, config: ReproduceConfig):
        import torch

        torch.set_num_threads(1)
        self.config, self.conditions = config, load_conditions()

    def __call__(self, task: CalibrationTask) -> float:
        model = run_model(self.config, task.preset, "regress", task.sigma)
        return calibration_beta(self.config, task.preset, task.sigma, model, self.conditions)


def map_calibrations(tasks: list[CalibrationTask], make_worker, stored: dict,
                     put: Callable[[dict], None], executor=None,
                     progress: Callable[[int], None] | None = None) -> dict:
    """The calibration of every (preset, sigma) task, spread over ``executor``; those already in
    ``stored`` (keyed by (preset, sigma)) are not recomputed, each new one is handed to
    ``put(stored)`` as it arrives (a stopped run keeps them)."""
    from drake_cert.experiments.executors import LocalExecutor

    todo = [t for t in tasks if (t.preset, t.sigma) not in stored]

    def keep(index: int, value) -> None:
        stored[(todo[index].preset, todo[index].sigma)] = value
        put(stored)

    if progress is not None:
        progress(len(tasks) - len(todo))
    (executor or LocalExecutor()).map(make_worker, todo, progress, on_result=keep)
    return {(t.preset, t.sigma): stored[(t.preset, t.sigma)] for t in tasks}


def calibration_betas(config: ReproduceConfig, executor=None, store: RunStore | None = None,
                      identity: str = "", progress: Callable[[int], None] | None = None) -> dict:
    """Every (preset, sigma) beta of the run, spread over ``executor`` before the frames (read
    back from ``store`` when it holds them under ``identity``)."""
    if not config.regression:
        return {}
    tasks = [CalibrationTask(p, s) for p in config.presets for s in config.sigmas]
    stored = store.betas(identity) if store is not None else {}
    put = (lambda b: store.put_betas(identity, b)) if store is not None else (lambda b: None)
    return map_calibrations(tasks, lambda: CalibrationWorker(config), stored, put, executor,
                            progress)


def conformal_sigmas(config: ReproduceConfig) -> list[float]:
    """Every sigma g certifies with in the run, ascending (a calibration's seed index)."""
    return sorted({*config.sigmas, config.sweep_sigma})


def conformal_calibration(config: ReproduceConfig, preset: str, sigma: float, conditions=None):
    """The robust conformal calibration of g at (preset, sigma): ``conformal_per_class``
    held-out frames per label, ``conformal_n`` samples each, from the seed stream
    (preset, CONFORMAL, index of sigma in :func:`conformal_sigmas`)."""
    from drake_cert.certification.classifier import SmoothedClassifier
    from drake_cert.certification.conformal import calibrate_robust_conformal
    from drake_cert.perception.datasets import load_split

    cal = load_split(preset, "calibration", conditions=conditions or load_conditions(),
                     frames_per_class=config.conformal_per_class)
    classifier = SmoothedClassifier(run_model(config, preset, "classify", sigma),
                                    len(cal.label_names), sigma)
    return calibrate_robust_conformal(
        classifier, cal.images, cal.labels.tolist(), n=config.conformal_n,
        batch_size=min(config.batch_size, config.conformal_n),
        root_seed=seed_of(config, preset_key(preset), CONFORMAL,
                          conformal_sigmas(config).index(sigma)))


class ConformalWorker:
    """Computes g's robust conformal calibration for one (preset, sigma) (an executor worker)."""

    def __init__(self, config: ReproduceConfig):
        import torch

        torch.set_num_threads(1)
        self.config, self.conditions = config, load_conditions()

    def __call__(self, task: CalibrationTask):
        return conformal_calibration(self.config, task.preset, task.sigma, self.conditions)


def conformal_calibrations(config: ReproduceConfig, executor=None, store: RunStore | None = None,
                           identity: str = "", progress: Callable[[int], None] | None = None
                           ) -> dict:
    """g's robust conformal calibration for every (preset, sigma) the run certifies with
    (empty unless ``config.interval`` is "conformal"), spread over ``executor`` and kept in
    ``store`` like the betas; each pair's numbers are those it gets computed alone."""
    if config.interval != "conformal":
        return {}
    tasks = [CalibrationTask(p, s) for p in config.presets for s in conformal_sigmas(config)]
    stored = store.conformal(identity) if store is not None else {}
    put = (lambda c: store.put_conformal(identity, c)) if store is not None else (lambda c: None)
    return map_calibrations(tasks, lambda: ConformalWorker(config), stored, put, executor,
                            progress)


class FrameWorker:
    """Evaluates every cell on one frame. Loads designs, models and calibrations once."""

    def __init__(self, config: ReproduceConfig, betas: dict | None = None,
                 designs: list | None = None, conformal: dict | None = None):
        import torch

        from drake_cert.experiments.episodes import EpisodeRunner
        from synthesis.table import synthesize_table

        torch.set_num_threads(1)
        self.config = config
        self.vehicle, self.settings = load_vehicle(), load_settings()
        self.conditions = load_conditions()
        self.designs = designs if designs is not None else synthesize_table(
            self.vehicle, self.conditions, self.settings)
        self.episodes = EpisodeRunner(self.vehicle, self.settings)
        self._models: dict = {}
        self._betas: dict = dict(betas or {})
        self._frames: dict = {}
        self._blocks: dict = {}
        self._conformal: dict = dict(conformal or {})

    # ------------------------------------------------------------------ loading (cached)
    def model(self, preset: str, task: str, sigma: float):
        key = (preset, task, sigma)
        if key not in self._models:
            self._models[key] = run_model(self.config, preset, task, sigma)
        return self._models[key]

    def frames(self, preset: str):
        from drake_cert.perception.datasets import load_split

        if preset not in self._frames:
            test = load_split(preset, "test", conditions=self.conditions)
            idx = frame_indices(self.config, preset_key(preset), test.labels)
            self._frames[preset] = (test, idx)
        return self._frames[preset]

    def beta(self, preset: str, sigma: float) -> float:
        """Run-time conformal beta of the median-smoothed regressor (largest over labels)."""
        key = (preset, sigma)
        if key not in self._betas:
            self._betas[key] = calibration_beta(self.config, preset, sigma,
                                                self.model(preset, "regress", sigma),
                                                self.conditions)
        return self._betas[key]

    # ------------------------------------------------------------------ one frame
    def __call__(self, task: FrameTask) -> list[dict]:
        from systems.camera import CameraFrame

        c = self.config
        p_idx = preset_key(task.preset)
        test, idx = self.frames(task.preset)
        i = int(idx[task.position])
        label = int(test.labels[i])
        names = list(test.label_names)
        friction = self.conditions.condition(names[label]).friction_mu
        frame = CameraFrame(image=test.images[i], time_s=0.0, tick=task.position,
                            position_m=0.0, label_index=label,
                            stiffness_n_per_rad=float(test.stiffness_n_per_rad[i]),
                            friction_mu=friction)
        truth = dict(preset=task.preset, frame=i, position=task.position,
                     true_label=names[label], stiffness_n_per_rad=frame.stiffness_n_per_rad,
                     friction_mu=friction, seed=f"{c.seed}/{p_idx}/{task.position}")
        rows = []
        for cell_index, cell in enumerate(c.cells()):
            pipeline, sigma, kind, eps = cell
            attacker, perception, interval = self.blocks(task.preset, cell_index, cell)
            seen = attacker.perturb(frame)
            result = perception.perceive(seen, 0.0)
            decision = interval.request(result)
            design = interval.designs[decision.design_index]
            outcome = self.episodes.outcome(design, frame.stiffness_n_per_rad, friction)
            lo, hi = decision.interval
            row = dict(truth, pipeline=pipeline, sigma=sigma, attack=kind, eps=eps,
                       task="regress" if pipeline in ("f_reg", "h") else "classify",
                       predicted=self.prediction(result, names),
                       interval_lo=lo, interval_hi=hi, certificate=float(decision.radius),
                       safe_set_radius=self.safe_set_radius(result, task.preset, names),
                       certified=decision.status == "certified",
                       design_labels="+".join(design.labels), velocity_mps=outcome.speed_mps,
                       left_lane=outcome.left_lane, peak_abs_e1_m=outcome.peak_abs_e1_m,
                       interval_covers=bool(lo <= frame.stiffness_n_per_rad <= hi))
            rows.append(row)
        return rows

    def blocks(self, preset: str, cell_index: int, cell: tuple):
        """The Diagram's own attacker, perception and interval blocks for one cell (cached).

        Their random streams are ``SeedSequence([cell seed, purpose, frame position])`` with
        the cell seed spawned from the root seed: distinct for every (preset, cell, frame).
        """
        from synthesis.selection import preset_designs
        from systems.attacker import Attacker
        from systems.certified_interval import CertifiedInterval
        from systems.perception_smoothing import PerceptionSmoothing

        key = (preset, cell_index)
        if key in self._blocks:
            return self._blocks[key]
        c = self.config
        pipeline, sigma, kind, eps = cell
        task = "regress" if pipeline in ("f_reg", "h") else "classify"
        mode = "certified" if pipeline in ("g", "h") else "base"
        model = self.model(preset, task, sigma)
        seed = seed_of(c, preset_key(preset), CELL, cell_index)
        labels = list(self.conditions.preset(preset).labels)
        attacker = Attacker(kind, eps=eps, target="smoothed" if mode == "certified" else "base",
                            model=model, sigma=sigma, task=task, seed=seed,
                            steps=c.attack_steps, noise_draws=c.attack_noise_draws)
        perception = PerceptionSmoothing(
            model, mode=mode, task=task, sigma=sigma if sigma > 0 else 1.0, n0=c.n0, n=c.n,
            alpha=c.alpha, batch_size=min(c.batch_size, c.n), seed=seed, label_names=labels,
            eps=eps)
        beta = self.beta(preset, sigma) if pipeline == "h" else 0.0
        conformal = None
        if pipeline == "g" and c.interval == "conformal":
            if (preset, sigma) not in self._conformal:
                self._conformal[(preset, sigma)] = conformal_calibration(c, preset, sigma,
                                                                         self.conditions)
            conformal = self._conformal[(preset, sigma)]
        interval = CertifiedInterval(preset_designs(self.designs, self.conditions, preset),
                                     self.conditions, preset, eps=eps, mode=mode, task=task,
                                     regression_beta=beta, conformal=conformal,
                                     label_names=labels)
        self._blocks[key] = (attacker, perception, interval)
        return self._blocks[key]

    @staticmethod
    def prediction(result, names):
        if result.certificate is not None:
            return names[result.certificate.top_label]
        if result.base_label is not None and result.task == "classify":
            return names[result.base_label]
        if result.regression is not None:
            return float(result.regression[0])
        if result.base_value_n_per_rad is not None:
            return float(result.base_value_n_per_rad)
        return None

    def safe_set_radius(self, result, preset, names) -> float:
        """The paper's R_S(a) of the certificate's top label a (inf when S(a) is every label)."""
        cert = result.certificate
        if cert is None:
            return 0.0
        if cert.abstained:
            return 0.0
        safe = self.conditions.safe_set(preset, names[cert.top_label])
        return float(cert.radius_for([names.index(m) for m in safe]))


def tasks_for(config: ReproduceConfig) -> list[FrameTask]:
    """Every frame of the run, frame-major (all presets' frame 0, then frame 1, ...), so that a
    run stopped early holds about as many frames of each preset."""
    return [FrameTask(p, k) for k in range(config.frames) for p in config.presets]


def model_files(config: ReproduceConfig) -> list[tuple[str, str, float]]:
    """(preset, task, sigma) of every model the run evaluates."""
    sigmas = sorted({0.0, *config.sigmas, config.sweep_sigma})
    out = [(p, "classify", s) for p in config.presets for s in sigmas]
    if config.regression:
        out += [(p, "regress", s) for p in config.presets for s in sorted({0.0, *config.sigmas})]
    return out


def run_identity(config: ReproduceConfig, designs: list) -> str:
    """What a stored frame must have been made with to be reused: every setting but the
    frame count (the first k frames of a preset do not depend on it), the SHA-256 of every
    model file, of the data tables (vehicle, settings, conditions) and of the design table
    (rounded to 6 significant digits). A SHA-256 hex digest."""
    import hashlib
    import json
    from pathlib import Path

    from drake_cert.perception.models import file_sha256, model_path

    settings = dataclasses.asdict(config)
    settings.pop("frames")

    def rounded(x):
        if isinstance(x, float):
            return float(f"{x:.6g}")
        if isinstance(x, dict):
            return {k: rounded(v) for k, v in sorted(x.items())}
        if isinstance(x, list | tuple):
            return [rounded(v) for v in x]
        return x

    data = Path(__file__).resolve().parents[1] / "data"
    blob = dict(
        settings=rounded(settings),
        models={f"{p}/{t}/{s}": file_sha256(model_path(p, t, s))
                for p, t, s in model_files(config)},
        data={f.name: file_sha256(f) for f in sorted(data.glob("*.yaml"))},
        designs=rounded([dataclasses.asdict(d) for d in designs]),
    )
    text = json.dumps(blob, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


class RunStore:
    """What a reproduction has finished, under ``root``: one JSON file per frame (its rows),
    ``calibration.json`` (the h betas) and ``conformal.json`` (g's robust conformal
    calibrations), each written atomically as it arrives and reused only by a run with the same
    :func:`run_identity`. A stopped run resumes where it stopped."""

    def __init__(self, root):
        from pathlib import Path

        from drake_cert.io import git_revision

        self.root = Path(root)
        self.revision = git_revision()

    def _frame_path(self, task: FrameTask):
        return self.root / task.preset / f"frame-{task.position:04d}.json"

    def _read(self, path, identity: str):
        import json

        if not path.exists():
            return None
        try:
            stored = json.loads(path.read_text())
        except (OSError, ValueError):
            return None  # unreadable: recompute
        return stored if stored.get("identity") == identity else None

    def frame(self, identity: str, task: FrameTask) -> list[dict] | None:
        stored = self._read(self._frame_path(task), identity)
        return None if stored is None else stored["rows"]

    def put_frame(self, identity: str, task: FrameTask, rows: list[dict]) -> None:
        self._write(self._frame_path(task), identity, rows=rows)

    def betas(self, identity: str) -> dict:
        stored = self._read(self.root / "calibration.json", identity)
        if stored is None:
            return {}
        return {(p, float(s)): float(b) for p, s, b in stored["betas"]}

    def put_betas(self, identity: str, betas: dict) -> None:
        self._write(self.root / "calibration.json", identity,
                    betas=[[p, s, b] for (p, s), b in sorted(betas.items())])

    def conformal(self, identity: str) -> dict:
        from drake_cert.certification.conformal import RobustConformalCalibration

        stored = self._read(self.root / "conformal.json", identity)
        if stored is None:
            return {}
        return {(p, float(s)): RobustConformalCalibration.from_json(c)
                for p, s, c in stored["calibrations"]}

    def put_conformal(self, identity: str, calibrations: dict) -> None:
        self._write(self.root / "conformal.json", identity,
                    calibrations=[[p, s, c.to_json()] for (p, s), c in
                                  sorted(calibrations.items())])

    def _write(self, path, identity: str, **content) -> None:
        import json

        from drake_cert.io import atomic_write_text

        text = json.dumps(dict(identity=identity, git_revision=self.revision, **content),
                          separators=(",", ":"))
        atomic_write_text(path, text + "\n")


def run_reproduction(config: ReproduceConfig, executor=None,
                     progress: Callable[[str, int], Callable[[int], None]] | None = None,
                     store: RunStore | None = None,
                     stop: Callable[[], bool] | None = None,
                     designs: list | None = None) -> list[dict]:
    """Every per-frame row of the reproduction, in (preset, frame, cell) order.

    ``designs``: the design table of the shipped vehicle, conditions and settings (synthesized
    here when not given; a caller that also draws ``traces.png`` passes the one it drew with).
    ``progress(desc, total)`` returns the update callable of one phase's progress bar.
    With a ``store``, finished frames and betas are read back from it and new ones written to
    it as they arrive; once ``stop()`` is True no new frame starts and the rows of the frames
    finished so far come back (fewer than ``frames`` per preset: the tables count them).
    """
    from drake_cert.experiments.executors import LocalExecutor
    from synthesis.table import synthesize_table

    config.validate()
    executor = executor or LocalExecutor()
    bar = progress or (lambda desc, total: None)
    if designs is None:
        designs = synthesize_table(load_vehicle(), load_conditions(), load_settings())
    identity = run_identity(config, designs) if store is not None else ""
    tasks = tasks_for(config)
    done = {t: store.frame(identity, t) for t in tasks} if store is not None else {}
    todo = [t for t in tasks if done.get(t) is None]
    stored = len(tasks) - len(todo)
    if stop is not None and stop():
        todo = []  # nothing will run: no calibration either
    betas, conformal = {}, {}
    if todo:
        if config.regression:
            betas = calibration_betas(config, executor, store, identity, bar(
                "calibration (h)", len(config.presets) * len(config.sigmas)))
        if config.interval == "conformal":
            conformal = conformal_calibrations(config, executor, store, identity, bar(
                "calibration (conformal g)",
                len(config.presets) * len(conformal_sigmas(config))))

    def keep(index: int, rows: list[dict]) -> None:
        done[todo[index]] = rows
        if store is not None:
            store.put_frame(identity, todo[index], rows)

    update = bar("frames", len(tasks))
    if update is not None:
        update(stored)
    executor.map(lambda: FrameWorker(config, betas, designs, conformal), todo, update,
                 on_result=keep, stop=stop)
    order = {p: i for i, p in enumerate(config.presets)}
    finished = sorted((t for t in tasks if done.get(t) is not None),
                      key=lambda t: (order[t.preset], t.position))
    return [row for t in finished for row in done[t]]


def recompute_frame(config: ReproduceConfig, preset: str, position: int) -> list[dict]:
    """The rows of one frame, computed alone (same numbers as in the full run)."""
    config.validate()
    return FrameWorker(config)(FrameTask(preset, position))
