"""Reproduce the paper's experiments as per-frame episodes (paper section V, DESIGN 7).

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
- ``g_conformal``: the same attacked frame and the same certificate as ``g`` (one attack, one
  certificate per frame and cell), read by the robust conformal interval (DESIGN 3; calibrated
  before the frames) instead of the safe-set one: the two intervals compared noise for noise.
- ``f_reg``: the non-robust regressor; its prediction (clipped to the preset's envelope) gets
  the narrowest design containing it.
- ``h``: the median-smoothed regressor; order-statistic bounds at eps widened by the Mondrian
  conformal beta (DESIGN 3), the narrowest design containing that interval.

Settings, seed streams and models: :mod:`drake_cert.experiments.reproduce_config`;
calibrations: :mod:`drake_cert.experiments.calibrations`; the resumable store:
:mod:`drake_cert.experiments.run_store`. A frame's rows can be recomputed alone
(:func:`recompute_frame`) with the same numbers, whatever the executor.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.errors import ConfigError
from drake_cert.experiments.calibrations import (
    calibration_beta,
    calibration_betas,
    conformal_calibration,
    conformal_calibrations,
    conformal_sigmas,
)
from drake_cert.experiments.reproduce_config import (
    FrameTask,
    ReproduceConfig,
    cell_seed,
    evaluated_run_model,
    frame_indices,
    max_certifiable_radius,
    noise_cell,
    preset_key,
    radius_cell,
    run_model,
)
from drake_cert.experiments.run_store import RunStore


def task_of(pipeline: str) -> str:
    """"regress" for the regression pipelines (f_reg, h), else "classify"."""
    return "regress" if pipeline in ("f_reg", "h") else "classify"


def mode_of(pipeline: str) -> str:
    """"certified" for the pipelines that certify (g, g_conformal, h), else "base"."""
    return "certified" if pipeline in ("g", "g_conformal", "h") else "base"


def cell_perception(config: ReproduceConfig, preset: str, cell: tuple,
                    decision: str = "fixed"):
    """One cell's perception settings as a scenario's ``perception`` block would give them:
    what its attacker (task, sigma), perception (and ``decision``) and interval blocks read.
    The base pipelines' sigma 0 is given as 1 (base mode samples no noise)."""
    from drake_cert.systems.scenario import PerceptionSettings

    pipeline, sigma, _, eps = cell
    return PerceptionSettings(
        preset=preset, task=task_of(pipeline), pipeline=mode_of(pipeline), eps=eps,
        sigma=sigma if sigma > 0 else 1.0, n0=config.n0, n=config.n, alpha=config.alpha,
        batch_size=min(config.batch_size, config.n), decision=decision)


class FrameWorker:
    """Evaluates every cell on one frame. Loads designs, models and calibrations once."""

    def __init__(self, config: ReproduceConfig, betas: dict | None = None,
                 designs: list | None = None, conformal: dict | None = None):
        from drake_cert.experiments.episodes import EpisodeRunner
        from drake_cert.synthesis.table import synthesize_table

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
        """The torch model on the CPU (what the attacks differentiate)."""
        key = (preset, task, sigma)
        if key not in self._models:
            self._models[key] = run_model(self.config, preset, task, sigma)
        return self._models[key]

    def evaluated(self, preset: str, task: str, sigma: float):
        """The module the certificates sample (:func:`evaluated_run_model`)."""
        key = (preset, task, sigma, "evaluated")
        if key not in self._models:
            self._models[key] = evaluated_run_model(self.config,
                                                    self.model(preset, task, sigma))
        return self._models[key]

    def frames(self, preset: str):
        from drake_cert.perception.datasets import load_split

        if preset not in self._frames:
            test = load_split(preset, "test", conditions=self.conditions)
            idx = frame_indices(self.config, preset, test.labels)
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
        from drake_cert.systems.camera import CameraFrame

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
        attacked: dict = {}  # noise cell -> the attacked frame (g_conformal shares g's attack)
        perceived: dict = {}  # perception block -> its result (a fixed-n g_conformal reads g's)
        for cell in c.cells():
            pipeline, sigma, kind, eps = cell
            attacker, perception, interval = self.blocks(task.preset, cell)
            if attacker is None:  # a cell that never certifies: no attack can change it
                attacked[noise_cell(cell)] = frame
            elif noise_cell(cell) not in attacked:
                attacked[noise_cell(cell)] = attacker.perturb(frame)
            if id(perception) not in perceived:
                perceived[id(perception)] = perception.perceive(attacked[noise_cell(cell)], 0.0)
            result = perceived[id(perception)]
            decision = interval.request(result)
            design = interval.designs[decision.design_index]
            outcome = self.episodes.outcome(design, frame.stiffness_n_per_rad, friction)
            lo, hi = decision.interval
            row = dict(truth, pipeline=pipeline, sigma=sigma, attack=kind, eps=eps,
                       task=task_of(pipeline),
                       predicted=self.prediction(result, names),
                       interval_lo=lo, interval_hi=hi, certificate=float(decision.radius),
                       safe_set_radius=self.safe_set_radius(result, task.preset, names),
                       certified=decision.status == "certified",
                       design_labels="+".join(design.labels), velocity_mps=outcome.speed_mps,
                       left_lane=outcome.left_lane, peak_abs_e1_m=outcome.peak_abs_e1_m,
                       interval_covers=bool(lo <= frame.stiffness_n_per_rad <= hi))
            rows.append(row)
        return rows

    def blocks(self, preset: str, cell: tuple):
        """The Diagram's own attacker, perception and interval blocks for one cell (cached).

        The attacker and the perception draw from the streams of the cell's seed
        (:func:`reproduce_config.cell_seed`) keyed by the frame's position, as a drive's blocks
        do by camera tick: distinct for every (preset, cell, frame). A g_conformal cell shares
        the attacker of its g cell (:func:`reproduce_config.noise_cell`) and, where the cell
        keeps a fixed-n certificate, its perception block (one certificate, two intervals); a
        cell decided sequentially (:meth:`decision_rule`) has its own perception block drawing
        from the same streams, which stops once its own range is decided; a cell that never
        certifies has no attacker (None) and a :class:`NeverCertifies` perception.
        """
        from drake_cert.systems.attacker import Attacker
        from drake_cert.systems.scenario import AttackSettingsYaml

        key = (preset, cell)
        if key in self._blocks:
            return self._blocks[key]
        c = self.config
        pipeline, sigma, kind, eps = cell
        task = task_of(pipeline)
        mode = mode_of(pipeline)
        conformal = None
        if pipeline == "g_conformal":
            if (preset, sigma) not in self._conformal:
                self._conformal[(preset, sigma)] = conformal_calibration(c, preset, sigma,
                                                                         self.conditions)
            conformal = self._conformal[(preset, sigma)]
        seed = cell_seed(c, preset, cell)
        shared = (preset, "noise", noise_cell(cell))
        rule = self.decision_rule(preset, cell)
        if rule == "never":
            self._blocks[key] = (None, NeverCertifies(self.evaluated(preset, task, sigma), task,
                                                      c.device), self._interval(preset, cell))
            return self._blocks[key]
        if shared not in self._blocks:
            attack = AttackSettingsYaml(kind=kind, eps=eps,
                                        target="smoothed" if mode == "certified" else "base",
                                        steps=c.attack_steps, noise_draws=c.attack_noise_draws)
            attacker = Attacker(attack, cell_perception(c, preset, cell),
                                model=self.model(preset, task, sigma), seed=seed)
            self._blocks[shared] = (attacker, self._perception(preset, cell, seed, "fixed"))
        attacker, perception = self._blocks[shared]  # fixed n: both g intervals read it
        if rule == "sequential":  # each interval decides its own range, from the same streams
            perception = self._perception(preset, cell, seed, rule, conformal)
        self._blocks[key] = (attacker, perception, self._interval(preset, cell, conformal))
        return self._blocks[key]

    def _interval(self, preset: str, cell: tuple, conformal=None):
        """The Diagram's certified-interval block for one cell."""
        from drake_cert.synthesis.selection import preset_designs
        from drake_cert.systems.certified_interval import CertifiedInterval, IntervalInputs

        pipeline, sigma, _, _ = cell
        beta = self.beta(preset, sigma) if pipeline == "h" else 0.0
        return CertifiedInterval(
            preset_designs(self.designs, self.conditions, preset), self.conditions,
            cell_perception(self.config, preset, cell), inputs=IntervalInputs(
                regression_beta=beta, conformal=conformal,
                label_names=list(self.conditions.preset(preset).labels)))

    def decision_rule(self, preset: str, cell: tuple) -> str:
        """"never" for a certifying cell whose budget n samples can never certify (its rows
        are the envelope's, with no attack and no sample: the outcome whatever the frame);
        "sequential" (config ``decisions``) for a g cell read only as a decision at its budget
        where n samples can reach that budget, and for h where its beta leaves candidate
        intervals; else "fixed" (Cohen's n0 + n, whose votes both g intervals read; h's
        percentile bounds)."""
        from drake_cert.certification.intervals import candidate_ranges
        from drake_cert.certification.statistics import percentile_bound_indices
        from drake_cert.errors import CertificationError
        from drake_cert.systems.perception_smoothing import check_decision_budget

        c = self.config
        pipeline, sigma, _, eps = cell
        if pipeline == "h":
            try:
                percentile_bound_indices(c.n, eps, sigma, c.alpha)
            except CertificationError:
                return "never"
        if pipeline in ("g", "g_conformal") and \
                max_certifiable_radius(sigma, c.n, c.alpha) <= eps:
            return "never"
        if c.decisions != "sequential" or radius_cell(c, cell):
            return "fixed"
        if pipeline == "h":  # its median decided over the designs' candidate intervals
            return "sequential" if self._median_candidates(preset, sigma) else "fixed"
        if pipeline not in ("g", "g_conformal"):
            return "fixed"
        labels = list(self.conditions.preset(preset).labels)
        try:
            check_decision_budget(c.n, c.alpha, eps, sigma,
                                  candidate_ranges(self.conditions, preset, labels))
        except ConfigError:  # never certifiable sequentially: the fixed-n certificate decides
            return "fixed"
        return "sequential"

    def _perception(self, preset: str, cell: tuple, seed: int, decision: str,
                    conformal=None):
        """The Diagram's perception block for one cell (the cells of one noise owner draw from
        the same streams: the seed of :func:`noise_cell`)."""
        from drake_cert.certification.intervals import candidate_ranges
        from drake_cert.systems.perception_smoothing import (
            ModelRuntime,
            PerceptionInputs,
            PerceptionSmoothing,
        )

        c = self.config
        pipeline, sigma, _, _ = cell
        task = task_of(pipeline)
        labels = list(self.conditions.preset(preset).labels)
        sequential = decision == "sequential"
        if sequential and pipeline == "h":
            ranges = self._median_candidates(preset, sigma)
        elif sequential:
            ranges = candidate_ranges(self.conditions, preset, labels)
        else:
            ranges = None
        return PerceptionSmoothing(
            self.evaluated(preset, task, sigma), cell_perception(c, preset, cell, decision),
            seed=seed, inputs=PerceptionInputs(label_names=labels, ranges=ranges,
                                               conformal=conformal if sequential else None),
            runtime=ModelRuntime(device=c.device))

    def _median_candidates(self, preset: str, sigma: float) -> list:
        """h's candidate intervals of the median at (preset, sigma), from the preset's designs
        and its beta (:func:`median_candidates`; none with an infinite beta)."""
        from drake_cert.certification.intervals import median_candidates
        from drake_cert.synthesis.selection import preset_designs

        return median_candidates(preset_designs(self.designs, self.conditions, preset),
                                 self.beta(preset, sigma), self.conditions.envelope(preset))

    @staticmethod
    def prediction(result, names):
        if result.certificate is not None:
            return names[result.certificate.top_label]
        if result.decision is not None:  # sequential: the label it certified through
            return names[result.decision.top_label]
        if result.conformal is not None and result.conformal.samples:
            # a sequential conformal set: the most votes (a set fixed before its first sample
            # has none: the base model's label, as for a cell that never certifies)
            return names[int(result.conformal.counts.argmax())]
        if result.base_label is not None and result.task == "classify":
            return names[result.base_label]
        if result.regression is not None:
            return float(result.regression[0])
        if result.median is not None:  # h decided sequentially: the median of its samples
            return result.median.sample_median
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


class NeverCertifies:
    """Perception for a cell whose budget its certificate can never reach (a radius beyond
    what n samples can certify at alpha): the result carries no certificate, so the interval is
    the envelope, as sampling would have made it; no sample is drawn. ``predicted`` is the
    base model's output on the frame."""

    def __init__(self, model, task: str, device: str = "cpu"):
        import torch

        self.model, self.task, self.device = model.eval(), task, torch.device(device)

    def perceive(self, frame, time_s: float):
        import torch

        from drake_cert.certification.regressor import point_value
        from drake_cert.systems.perception_smoothing import PerceptionResult

        with torch.inference_mode():
            out = self.model(frame.image.float()[None].to(self.device))
        classify = self.task == "classify"
        return PerceptionResult(
            time_s=float(time_s), tick=frame.tick, position_m=frame.position_m, frame_ok=True,
            error="", mode="certified", task=self.task,
            base_label=int(out.argmax(dim=1)[0]) if classify else None,
            base_value_n_per_rad=None if classify else float(point_value(out)[0]),
            label_index=frame.label_index, stiffness_n_per_rad=frame.stiffness_n_per_rad,
            friction_mu=frame.friction_mu, attack=frame.attack)


def tasks_for(config: ReproduceConfig) -> list[FrameTask]:
    """Every frame of the run, frame-major (all presets' frame 0, then frame 1, ...), so that a
    run stopped early holds about as many frames of each preset."""
    return [FrameTask(p, k) for k in range(config.frames) for p in config.presets]


@dataclasses.dataclass(frozen=True)
class RunReport:
    """What the caller of :func:`run_reproduction` watches: ``progress(desc, total)`` returns
    the update callable of one phase's progress bar; ``cpu``, a dict it fills with the CPU
    seconds its workers spent per stage."""

    progress: Callable[[str, int], Callable[[int], None]] | None = None
    cpu: dict | None = None


def run_reproduction(config: ReproduceConfig, executor=None, store: RunStore | None = None,
                     stop: Callable[[], bool] | None = None, designs: list | None = None,
                     report: RunReport | None = None) -> list[dict]:
    """Every per-frame row of the reproduction, in (preset, frame, cell) order.

    ``designs``: the design table of the shipped vehicle, conditions and settings (synthesized
    here when not given; a caller that also draws ``traces.png`` passes the one it drew with).
    ``report.progress(desc, total)`` returns the update callable of one phase's progress bar
    (:class:`RunReport`). With a ``store``, finished frames and betas are read back from it
    and new ones written to it as they arrive; once ``stop()`` is True no new frame starts
    and the rows of the frames finished so far come back (fewer than ``frames`` per preset:
    the tables count them).
    ``report.cpu``, when given, gets the CPU seconds its workers spent per stage
    (``calibration_h``, ``calibration_conformal``, ``frames``).
    """
    report = report or RunReport()
    progress, cpu = report.progress, report.cpu
    from drake_cert.experiments.executors import LocalExecutor, cpu_timed
    from drake_cert.synthesis.table import synthesize_table

    config.validate()
    executor = executor or LocalExecutor()
    bar = progress or (lambda desc, total: None)
    if designs is None:
        designs = synthesize_table(load_vehicle(), load_conditions(), load_settings())
    identity = store.identity(config, designs) if store is not None else ""
    tasks = tasks_for(config)
    done = {t: store.frame(identity, t) for t in tasks} if store is not None else {}
    todo = [t for t in tasks if done.get(t) is None]
    stored = len(tasks) - len(todo)
    if stop is not None and stop():
        todo = []  # nothing will run: no calibration either
    if todo and store is not None:
        store.check_arithmetic(identity, config.precision)  # no run finished in other digits
    betas, conformal = {}, {}
    spent: dict[str, list[float]] = {"calibration_h": [], "calibration_conformal": [],
                                     "frames": []}
    if todo:
        if config.regression:
            betas = calibration_betas(config, executor, store, identity, bar(
                "calibration (h)", len(config.presets) * len(config.sigmas)),
                spent["calibration_h"])
        if config.conformal:
            conformal = conformal_calibrations(config, executor, store, identity, bar(
                "calibration (conformal g)",
                len(config.presets) * len(conformal_sigmas(config))),
                spent["calibration_conformal"])

    def store_frame_rows(index: int, result) -> None:
        rows, cpu_s = result
        done[todo[index]] = rows
        spent["frames"].append(cpu_s)
        if store is not None:
            store.put_frame(identity, todo[index], rows, cpu_s)

    update = bar("frames", len(tasks))
    if update is not None:
        update(stored)
    executor.map(cpu_timed(lambda: FrameWorker(config, betas, designs, conformal)), todo,
                 update, on_result=store_frame_rows, stop=stop)
    if cpu is not None:
        cpu.update({stage: round(sum(v), 1) for stage, v in spent.items()})
    order = {p: i for i, p in enumerate(config.presets)}
    finished = sorted((t for t in tasks if done.get(t) is not None),
                      key=lambda t: (order[t.preset], t.position))
    return [row for t in finished for row in done[t]]


def recompute_frame(config: ReproduceConfig, preset: str, position: int) -> list[dict]:
    """The rows of one frame, computed alone (same numbers as in the full run)."""
    from drake_cert.threads import torch_threads

    config.validate()
    with torch_threads(1):  # one thread, as the executors run a worker; given back afterwards
        return FrameWorker(config)(FrameTask(preset, position))
