"""The certified closed loop: camera frame to steering in one Drake Diagram (DESIGN 6).

    longitudinal --arc length--> camera --frame--> attacker --frame--> perception smoothing
         ^  |                                                               | perception
         |  +--arc length--> route (curvature, true C, mu of the car's segment)
         |                                                                  v
         +--------------------------decision------------------------ certified interval
    longitudinal --speed, design in force--> switching L1 controller --> Saturation --> plant
    plant (Fiala) <-- true C, mu, curvature (route), speed (longitudinal); state --> controller

The controller gets the curvature under the car and, with
``settings.controller.preview_window_s > 0`` (default), the road preview (``RouteSource``
output ``curvature_preview_per_m``, fed ``speed_mps``) at which u_ff is taken (DESIGN 4.2).
Timing per camera tick k (period T): frame at kT, perception at kT + T/4, interval decision at
kT + T/2, speed/design profile update at kT + 3T/4 (DESIGN 6.1). The perception latency T/4 is
a requirement on the hardware (``n0 + n`` noisy samples within T/4, reported as
``samples_per_s_required``), not a measurement of the machine that simulates.

Where decisions apply (lead-in of ``look_ahead_m``, combined decisions, the frontier) is
:mod:`drake_cert.systems.longitudinal` (DESIGN 6.3-6.4); ``check_look_ahead`` refuses a camera
whose look-ahead cannot carry the table's top speed, and a route with an interior stretch
shorter than ``min_condition_length_m`` is refused. A wider (safer) design is never held back.
Each drive reports the switching certificates (DESIGN 5.6: ``switching_method``,
``loop_switching_decay_per_s``), whether its switching signal met them
(``switching_certificate_met``) and the chatter bound (``chatter_bound_n0``,
``lyapunov_growth_bound``). The non-robust baseline is the same Diagram with
``pipeline="base"``: the base model f's raw prediction, the predicted label's own interval and
design, attacked by PGD on f, each prediction standing alone (joined over the gap between
frames).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import numpy as np
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder, EventStatus
from pydrake.systems.primitives import LogVectorOutput, Saturation

from drake_cert.certification.alpha_spending import AlphaSpending, planned_decisions
from drake_cert.certification.backends import Int8Calibration, resolve_backend
from drake_cert.certification.intervals import candidate_ranges
from drake_cert.certification.pac_conformal import PacTargets
from drake_cert.certification.sampler import CalibrationSampling, resolve_precision
from drake_cert.certification.seeds import Purpose, child_seed
from drake_cert.config import ConditionsTable, Settings, VehicleParams
from drake_cert.errors import ConfigError
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.synthesis.selection import (
    design_label_spans,
    envelope_design_index,
    join_design_indices,
    preset_designs,
)
from drake_cert.systems.attacker import Attacker
from drake_cert.systems.camera import CameraSource
from drake_cert.systems.certified_interval import CertifiedInterval, IntervalInputs
from drake_cert.systems.longitudinal import (
    BRAKING_MARGIN_M,
    ENVELOPE_DECEL_FRACTION,
    BrakingLimits,
    LongitudinalMotion,
    ProfileDesigns,
    frontier_latency_s,
    look_ahead_needed_m,
    supported_speed_mps,
)
from drake_cert.systems.perception_smoothing import (
    PerceptionInputs,
    PerceptionSmoothing,
    check_decision_budget,
)
from drake_cert.systems.plants import NonlinearLateralPlant, body_state_from_error
from drake_cert.systems.route import Route, RouteSource
from drake_cert.systems.scenario import Scenario
from drake_cert.systems.switching_controller import SwitchingL1Controller, SwitchingOptions

OFF_ROAD_M = 5.0  # |e1| (m) at which a drive ends: the car has left its lane for good
REST_LIMIT_S = 5.0  # a drive ends after the car has rested this long (a stop for good)


@dataclasses.dataclass
class DriveTape:
    """Logged signals of one drive, sampled every tape period (SI units)."""

    times_s: np.ndarray  # (N,)
    states: np.ndarray  # (N, 4) s = [e1 (m), e1dot (m/s), e2 (rad), e2dot (rad/s)]
    steering_rad: np.ndarray  # (N,) applied (saturated) steering
    speed_mps: np.ndarray  # (N,) forward speed
    speed_command_mps: np.ndarray  # (N,) latest decision's speed command (look-ahead point)
    arc_length_m: np.ndarray  # (N,) distance along the route
    curvature_per_m: np.ndarray  # (N,) curvature at the car
    interval_n_per_rad: np.ndarray  # (N, 2) latest certified interval (look-ahead point)
    true_stiffness_n_per_rad: np.ndarray  # (N,) true C of the segment the car is on
    design_index: np.ndarray  # (N,) design the controller is running (the design in force)
    certified_radius: np.ndarray  # (N,) radius of the latest interval (0: none)
    status: np.ndarray  # (N,) 0 certified, 1 envelope, 2 stop, 3 base
    lane_margin_m: float
    design_interval_n_per_rad: np.ndarray  # (N, 2) stiffness interval of the design in force
    design_speed_mps: np.ndarray  # (N,) safe speed of the design in force (0: none)

    @property
    def lateral_offset_m(self) -> np.ndarray:
        return self.states[:, 0]


@dataclasses.dataclass
class TickLog:
    """One row per camera tick: the decision and the truth of the segment its frame showed."""

    times_s: np.ndarray
    interval_n_per_rad: np.ndarray  # (K, 2)
    seen_stiffness_n_per_rad: np.ndarray  # (K,)
    status: np.ndarray  # (K,)
    design_index: np.ndarray  # (K,) design the block chose for the look-ahead point
    samples: np.ndarray  # (K,) noisy samples perception drew for the frame (selection incl.)
    requested_design_index: np.ndarray  # (K,) design the tick asked for, before the dwell time


@dataclasses.dataclass
class DrivingDiagram:
    """The built Diagram and what :func:`drive` needs to run and read it."""

    diagram: Diagram
    scenario: Scenario
    route: Route
    designs: list[ControllerDesign]
    systems: dict  # name -> system
    loggers: dict  # name -> VectorLogSink (tape period)
    tick_loggers: dict  # name -> VectorLogSink (camera period)
    initial_speed_mps: float
    vehicle: VehicleParams
    seed_source: str = "scenario"  # "scenario" or "os-entropy" (the scenario's seed was null)
    switching: object = None  # the preset's drake_cert.synthesis.switching.SwitchingCertificate
    lead_in_m: float = 0.0  # the car starts this far before the route (m): the first frame
    # shows the route's start; the lead-in has the first segment's road and is driven under the
    # envelope design before any decision
    guarantee: dict = dataclasses.field(default_factory=dict)  # guarantee_summary()


@dataclasses.dataclass(frozen=True)
class BuildOptions:
    """How :func:`build_certified_driving_diagram` logs and reports its set-up."""

    tape_period_s: float = 0.05  # period of the continuous logs (s)
    calibration_progress: Callable | None = None  # wraps the calibration frames (a bar)


@dataclasses.dataclass(frozen=True)
class DriveProgress:
    """Progress callbacks of :func:`drive_scenario`."""

    drive: Callable[[float], None] | None = None  # called with the simulated seconds advanced
    calibration: Callable | None = None  # wraps the iterable of calibration frames (a bar)


@dataclasses.dataclass(frozen=True)
class DriveRun:
    """How one drive ran and what its Diagram was built with, for :func:`summarize_drive`."""

    simulated_s: float  # simulated time at the end (s)
    wall_s: float  # wall-clock time of the simulation (s)
    ending: str  # "time limit", "route end", "off road" or "stopped"
    seed_source: str = "scenario"  # "scenario" or "os-entropy"
    envelope_index: int | None = None  # index of the envelope design
    lead_in_m: float = 0.0  # driven before the route under the envelope design (m)
    alpha_spending: AlphaSpending | None = None  # the perception's alpha spending, if any
    guarantee: dict | None = None  # guarantee_summary(), merged into the summary


def entropy_seed() -> int:
    """A fresh 63-bit seed from the operating system's entropy (a deployment's noise: an
    attacker who knows the seed knows the certificate's noise and can defeat it)."""
    return int(np.random.SeedSequence().generate_state(2, np.uint64)[0] >> np.uint64(1))


def with_overrides(scenario: Scenario, *, pipeline: str | None = None, attack: str | None = None,
                   eps: float | None = None, seed: int | None = None) -> Scenario:
    """A copy of ``scenario`` with the command line's choices; validated."""
    perception, attack_cfg = scenario.perception, scenario.attack
    if pipeline is not None:
        perception = dataclasses.replace(perception, pipeline=pipeline)
    if attack is not None:
        attack_cfg = dataclasses.replace(attack_cfg, kind=attack)
    if eps is not None:
        attack_cfg = dataclasses.replace(attack_cfg, eps=float(eps))
    out = dataclasses.replace(scenario, perception=perception, attack=attack_cfg,
                              seed=scenario.seed if seed is None else int(seed))
    out.validate("scenario")
    return out


def _regression_beta(model, scenario: Scenario, conditions: ConditionsTable) -> float:
    """Run-time conformal beta of the median-smoothed regressor (DESIGN 3), largest over labels;
    ``model``: the module perception evaluates (the calibration is that of the model as
    evaluated: ONNX Runtime, int8, bf16)."""
    from drake_cert.certification.regressor import MedianSmoothedRegressor, calibrate_conformal
    from drake_cert.perception.datasets import load_split

    p = scenario.perception
    cal = load_split(p.preset, "calibration", conditions=conditions).per_class(
        p.calibration_frames_per_class)
    sampling = CalibrationSampling(n=p.calibration_n,
                                   batch_size=min(p.batch_size, p.calibration_n),
                                   seed=child_seed(scenario.seed, Purpose.REGRESSION_CALIBRATION))
    calib = calibrate_conformal(
        MedianSmoothedRegressor(model, p.sigma), cal.images, cal.stiffness_n_per_rad.tolist(),
        cal.labels.tolist(), sampling=sampling, alpha_m=p.alpha_m, alpha_c=p.alpha_c)
    return calib.beta


CONFORMAL_CALIBRATION_SEED = 0  # noise root of the robust conformal calibration of every drive


def conformal_votes_spec(scenario: Scenario, conditions: ConditionsTable):
    """The :class:`~drake_cert.certification.shipped_calibration.VotesSpec` of the scenario's
    robust conformal calibration: the model file's digest, the backend and precision as
    resolved on this machine, the scenario's calibration frames and samples, and the noise root
    :data:`CONFORMAL_CALIBRATION_SEED` (the calibration is the model's, not the drive's)."""
    from drake_cert.certification.shipped_calibration import VotesSpec
    from drake_cert.perception.models import file_sha256, model_path

    p = scenario.perception
    precision = resolve_precision(p.precision)
    return VotesSpec(
        preset=p.preset, sigma=float(p.sigma),
        model_sha256=file_sha256(model_path(p.preset, p.task, p.sigma)),
        backend=resolve_backend(p.backend, precision), precision=precision,
        quantization=p.quantization, frames_per_label=int(p.conformal_frames_per_class),
        n=int(p.conformal_calibration_n),
        root_seed=child_seed(CONFORMAL_CALIBRATION_SEED, Purpose.CONFORMAL_CALIBRATION),
        batch_size=int(p.batch_size),
        conditions=tuple((c.name, float(c.interval[0]), float(c.interval[1]))
                         for c in conditions.preset_conditions(p.preset)))


def conformal_votes(model, scenario: Scenario, conditions: ConditionsTable,
                    progress: Callable | None = None, *, refresh: bool = False):
    """The calibration frames' true-label votes for the scenario's robust conformal
    calibration: shipped beside the model when the spec matches, else cached, else drawn
    (``progress`` wraps the frames; ``refresh``: always drawn); ``model``: the module
    perception evaluates (calibrated as evaluated: ONNX Runtime, int8, bf16)."""
    from drake_cert.certification import conformal as rc
    from drake_cert.certification.classifier import SmoothedClassifier
    from drake_cert.certification.shipped_calibration import CalibrationVotes, calibration_votes
    from drake_cert.perception.datasets import load_split
    from drake_cert.perception.models import model_path

    p = scenario.perception
    spec = conformal_votes_spec(scenario, conditions)

    def compute(progress_of):
        cal = load_split(p.preset, "calibration", conditions=conditions,
                         frames_per_class=spec.frames_per_label)
        classifier = SmoothedClassifier(model, len(spec.conditions), p.sigma)
        sampling = CalibrationSampling(n=spec.n, batch_size=spec.batch_size,
                                       seed=spec.root_seed, progress=progress_of)
        counts = rc.true_label_counts(classifier, cal.images, cal.labels.tolist(),
                                      sampling=sampling)
        return CalibrationVotes(spec, cal.labels.numpy().astype(np.int64),
                                cal.stiffness_n_per_rad.numpy().astype(np.float64), counts)

    return calibration_votes(spec, model_path(p.preset, p.task, p.sigma), compute, progress,
                             refresh=refresh)


def drive_conformal_calibration(model, scenario: Scenario, conditions: ConditionsTable,
                                progress: Callable | None = None):
    """The robust conformal calibration of the certified classifier (docs/design.md 3.6):
    calibration-conditional (``perception.conformal_delta_cal``) and bounded in each of
    ``perception.conformal_bins_per_label`` stiffness bins of every label at
    ``perception.conformal_alpha_c``, from :func:`conformal_votes` (shipped with the model).
    Every drive shares it, whatever its seed (a drive with fresh noise too: the attacker may
    know the calibration, only the test noise must be fresh); the drive's guarantee holds for
    every calibration outside an event of probability delta_cal."""
    from drake_cert.certification import conformal as rc

    p = scenario.perception
    votes = conformal_votes(model, scenario, conditions, progress)
    intervals = [(c[1], c[2]) for c in votes.spec.conditions]
    targets = PacTargets(bins=p.conformal_bins_per_label, miss_target=p.conformal_alpha_c,
                         delta_cal=p.conformal_delta_cal)
    return rc.pac_calibration_from_counts(
        rc.TrueLabelVotes(votes.true_counts, votes.labels, votes.stiffness_n_per_rad,
                          votes.spec.n), intervals,
        sigma=p.sigma, targets=targets, label_names=[c[0] for c in votes.spec.conditions])


def _calibration_warnings(scenario: Scenario, regression_beta: float) -> list[str]:
    """What the summary must say about a calibration that makes every interval the envelope
    (a regression beta that is infinite: too few calibration frames for alpha_c)."""
    p = scenario.perception
    if p.pipeline != "certified" or p.task != "regress" or math.isfinite(regression_beta):
        return []
    needed = math.ceil((1.0 - p.alpha_c) / p.alpha_c)
    return [f"the regression's conformal beta is infinite ({p.calibration_frames_per_class} "
            f"calibration frames per label; alpha_c = {p.alpha_c:g} needs at least {needed}): "
            "every interval is the envelope; raise perception.calibration_frames_per_class to "
            f"{needed} or more"]


def moving_envelope(designs: list[ControllerDesign], conditions: ConditionsTable,
                    preset: str) -> tuple[list[ControllerDesign], int]:
    """The preset's designs and the index of its envelope design; :class:`ConfigError` when the
    envelope has no safe speed (the car would stand still wherever it abstains)."""
    table = preset_designs(designs, conditions, preset)
    envelope = envelope_design_index(table, conditions, preset)
    if not table[envelope].has_safe_speed:
        raise ConfigError(
            f"the design table has no safe speed for the envelope of preset {preset!r} "
            f"(labels {list(table[envelope].labels)}; failed: "
            f"{table[envelope].failed_condition or 'unknown'}): the certified car would "
            f"stand still wherever it abstains; {drivable_scenarios_note(designs, conditions)}")
    return table, envelope


def drivable_scenarios_note(designs: list[ControllerDesign],
                            conditions: ConditionsTable) -> str:
    """Which shipped scenarios this table can drive (their preset's envelope has a safe speed),
    and what to change for the others: one phrase for an error message."""
    from drake_cert.systems.scenario import SHIPPED_SCENARIOS, load_scenario

    presets = set()
    for p in conditions.presets:
        try:
            table = preset_designs(designs, conditions, p.name)
        except ConfigError:
            continue
        if table[envelope_design_index(table, conditions, p.name)].has_safe_speed:
            presets.add(p.name)
    ok = [s for s in SHIPPED_SCENARIOS if load_scenario(s).perception.preset in presets]
    can = (f"this table can drive the shipped scenarios {', '.join(ok)}" if ok
           else "this table can drive none of the shipped scenarios")
    return (f"{can}; for the others give the vehicle's tires per axle if they differ "
            "(docs/usage.md, \"Your vehicle's tires\"), or synthesize with a shorter "
            "controller.sample_period_s, which lets the filter gain rise further "
            "(docs/design.md 5.3a)")


def _speeds(table: list[ControllerDesign]) -> list[float]:
    return [float(d.speed_mps) if d.has_safe_speed else 0.0 for d in table]


def slowest_command_mps(table: list[ControllerDesign], stop_speed_mps: float) -> float:
    """The slowest speed command (m/s) a decision can give with these designs (0: stop; a
    design speed below the stop speed means stop): the speed the car brakes for at the
    frontier of the road it has decisions for."""
    slowest = min(_speeds(table))
    return slowest if slowest >= stop_speed_mps else 0.0


def check_route_is_seen(scenario: Scenario, table: list[ControllerDesign]) -> None:
    """:class:`ConfigError` when the route breaks the car's assumption that no stretch of one
    road condition (consecutive segments with the same condition) is as short as
    ``min_condition_length_m`` (the first and the last stretch excepted: they extend before the
    route's start and past its end), or when that length is not longer than the road the car
    can cover between two frames at the table's top speed: the join of the designs on either
    side of a gap between frames, and the bridge over abstentions, hold only when at most one
    boundary lies between their look points."""
    top = max(_speeds(table))
    gap = top / scenario.camera.rate_hz
    shortest = scenario.min_condition_length_m
    if shortest <= gap:
        raise ConfigError(
            f"min_condition_length_m = {shortest:g} m is not longer than the {gap:.2f} m the car "
            f"can drive between two frames ({top:.2f} m/s at {scenario.camera.rate_hz:g} Hz): "
            "raise it or camera.rate_hz")
    runs: list[list] = []  # [condition, length, index of the first segment]
    for i, seg in enumerate(scenario.route):
        if runs and runs[-1][0] == seg.condition:
            runs[-1][1] += seg.length_m
        else:
            runs.append([seg.condition, seg.length_m, i])
    for condition, length, first in runs[1:-1]:
        if length < shortest:
            raise ConfigError(
                f"route segment {first} ({condition}, {length:g} m of that condition) is shorter "
                f"than min_condition_length_m = {shortest:g} m, the shortest stretch of one "
                "condition the car assumes (it bridges abstentions over shorter spans); "
                "lengthen it, or lower min_condition_length_m (it must stay above the "
                f"{gap:.2f} m between two frames)")


def decision_lag_ticks(scenario: Scenario) -> int:
    """Camera ticks by which the decided road trails the newest look point: the combined
    decisions of the certified pipeline narrow a stretch only once ``tolerated_wrong_frames``
    later frames have bounded it (DESIGN 6.3); the base pipeline's decisions stand alone."""
    return scenario.tolerated_wrong_frames if scenario.perception.pipeline == "certified" else 0


def check_look_ahead(scenario: Scenario, table: list[ControllerDesign]) -> None:
    """:class:`ConfigError` when the camera's look-ahead cannot carry the table's top speed:
    the car must be able to brake to the slowest command before the end of the road it has a
    decision for (:func:`drake_cert.systems.longitudinal.supported_speed_mps`); names the largest
    speed the look-ahead supports and the look-ahead the top speed needs."""
    cam, motion = scenario.camera, scenario.motion
    decel = ENVELOPE_DECEL_FRACTION * motion.max_decel_mps2
    floor = slowest_command_mps(table, motion.stop_speed_mps)
    top_index = max(range(len(table)), key=lambda i: _speeds(table)[i])
    top = _speeds(table)[top_index]
    lag = decision_lag_ticks(scenario)
    kw = dict(braking=BrakingLimits(decel_mps2=decel, margin_m=BRAKING_MARGIN_M,
                                    floor_speed_mps=floor), lag_ticks=lag)
    supported = supported_speed_mps(cam.look_ahead_m, cam.rate_hz, **kw)
    if supported < top - 1e-9:
        needed = look_ahead_needed_m(top, cam.rate_hz, **kw)
        raise ConfigError(
            f"camera.look_ahead_m = {cam.look_ahead_m:g} m supports at most {supported:.2f} m/s "
            f"at {cam.rate_hz:g} Hz (braking at {decel:.2f} m/s^2 to the slowest command, "
            f"{floor:.2f} m/s, {BRAKING_MARGIN_M:g} m before the end of the decided road, "
            "which stays put for up to "
            f"{frontier_latency_s(cam.rate_hz, lag_ticks=lag):.2f} s), below the design "
            f"table's top speed {top:.2f} m/s (labels "
            f"{list(table[top_index].labels)}); raise look_ahead_m to at least {needed:.1f} m "
            "or raise camera.rate_hz")


def planned_ticks(scenario: Scenario, table: list[ControllerDesign]) -> int:
    """Camera ticks the drive plans for: the route and the lead-in at the slowest moving design
    speed, at most the ticks of ``t_final_s`` (DESIGN 6.2)."""
    moving = [v for v in _speeds(table) if v >= scenario.motion.stop_speed_mps]
    slowest = min(moving, default=scenario.motion.stop_speed_mps)  # every design stops: stop speed
    return planned_decisions(scenario.route_length_m + scenario.camera.look_ahead_m,
                             slowest, scenario.camera.rate_hz, scenario.t_final_s)


def alpha_spending(scenario: Scenario, table: list[ControllerDesign]) -> AlphaSpending | None:
    """How the drive spends ``perception.alpha`` (DESIGN 6.2): with ``alpha_scope: drive``, an
    :class:`AlphaSpending` of that total over the :func:`planned_ticks`; None with
    ``alpha_scope: decision`` (``alpha`` per decision) or for the base pipeline."""
    p = scenario.perception
    if p.alpha_scope != "drive" or p.pipeline != "certified":
        return None
    return AlphaSpending(p.alpha, planned_ticks(scenario, table))


def certificate_failure_bound(scenario: Scenario, spending: AlphaSpending | None,
                              ticks: int) -> float:
    """The union bound on the probability that some certificate of a drive of ``ticks``
    decisions failed: the alpha spent (drive scope) or ``ticks * alpha`` (decision scope,
    capped at 1); 0 for the base pipeline, which certifies nothing. It counts the realised
    ticks and the certificates only: not the conformal miscoverage of a frame, not the
    standing assumption of the safe-set interval, not the tolerance of the combined
    decisions; :func:`guarantee_failure_bound` is the bound on the drive's guarantee."""
    if scenario.perception.pipeline != "certified":
        return 0.0
    if spending is not None:
        return spending.spent(ticks)
    return min(1.0, ticks * scenario.perception.alpha)


def frame_miscoverage(scenario: Scenario, conformal=None) -> float:
    """Probability (per frame, marginal) that a frame's interval misses the true condition
    although every certificate held: the robust conformal set's ``alpha_total`` (``conformal``:
    its calibration), the regression interval's ``alpha_c + alpha_m``; 0 for the safe-set
    interval, which instead rests on the standing assumption (DESIGN 3.4)."""
    p = scenario.perception
    if p.task == "regress":
        return p.alpha_c + p.alpha_m
    if p.interval == "conformal":
        return float(conformal.alpha_total) if conformal is not None else 1.0
    return 0.0


def guarantee_failure_bound(scenario: Scenario, planned: int, miscoverage: float,
                            conformal=None) -> float | None:
    """Bound, computed before the drive from its ``planned`` ticks, on the probability that
    somewhere on the route the design in force misses the stiffness under the car or the car
    is faster than its safe speed (docs/design.md 6.2). None for the base pipeline.

    Robust conformal interval with a calibration-conditional ``conformal`` calibration
    (``delta_cal`` > 0): ``delta_cal + R P(Bin(m, p) > j)``, p = ``miscoverage`` the per-tick
    miss bound that holds in every stiffness bin given a good calibration, m =
    ``looks_per_side``, j = ``tolerated_wrong_frames``, R = max(1, planned - m + 1) runs of m
    consecutive ticks: the counting rule keeps the truth unless some side, a run of at most m
    consecutive ticks, holds more than j wrong looks (6.3), and given the calibration each
    tick is wrong with probability at most p whatever came before (6.2).

    Otherwise (the safe-set interval, under its standing assumption; the regression interval;
    a marginal calibration), Markov's inequality on the expected number of wrong frames,
    ``min(1, (A + planned miscoverage) / (j + 1))``, A the certificates' alpha."""
    from drake_cert.systems.decision_combination import run_failure_bound

    p = scenario.perception
    if p.pipeline != "certified":
        return None
    m, j = scenario.looks_per_side, scenario.tolerated_wrong_frames
    if conformal is not None and getattr(conformal, "delta_cal", 0.0) > 0.0 \
            and p.task == "classify" and p.interval == "conformal":
        runs = max(1, planned - m + 1)
        return min(1.0, conformal.delta_cal + runs * run_failure_bound(miscoverage, m, j))
    certificates = p.alpha if p.alpha_scope == "drive" else planned * p.alpha
    expected_wrong = certificates + planned * miscoverage
    return min(1.0, expected_wrong / (j + 1))


def guarantee_summary(scenario: Scenario, table: list[ControllerDesign],
                      conformal=None) -> dict:
    """The drive summary's account of what its guarantee rests on: ``interval``,
    ``standing_assumption`` (true where the guarantee assumes the smoothed classifier right on
    the clean frame: the safe-set interval), ``tolerated_wrong_frames``, ``looks_per_side``,
    ``planned_ticks``, ``frame_miscoverage`` (per tick, in every stiffness bin given the
    calibration), ``calibration_failure_bound`` (delta_cal) and ``guarantee_failure_bound``."""
    p = scenario.perception
    certified = p.pipeline == "certified"
    planned = planned_ticks(scenario, table)
    miss = frame_miscoverage(scenario, conformal) if certified else None
    return {
        "interval": (("median_conformal" if p.task == "regress" else p.interval)
                     if certified else "base"),
        "standing_assumption": certified and p.task == "classify" and p.interval == "safe_set",
        "tolerated_wrong_frames": scenario.tolerated_wrong_frames if certified else 0,
        "looks_per_side": scenario.looks_per_side if certified else 0,
        "planned_ticks": planned,
        "frame_miscoverage": miss,
        "calibration_failure_bound": (float(getattr(conformal, "delta_cal", 0.0))
                                      if certified and conformal is not None else None),
        "guarantee_failure_bound": (guarantee_failure_bound(scenario, planned, miss, conformal)
                                    if certified else None),
    }


def check_perception_budget(scenario: Scenario, conditions: ConditionsTable,
                            table: list[ControllerDesign] | None = None) -> None:
    """:class:`ConfigError` when the scenario's sequential decisions could never certify its
    eps with its n at the alpha of a decision (with ``alpha_scope: drive``, the planned ticks'
    share of the drive's alpha; needs the design ``table``), checked before any model is
    loaded or any drive starts."""
    p = scenario.perception
    if p.pipeline == "certified" and p.resolved_decision == "sequential" \
            and p.interval == "safe_set":
        labels = list(conditions.preset(p.preset).labels)
        spending = alpha_spending(scenario, table) if table is not None else None
        alpha = spending.planned_alpha if spending is not None else p.alpha
        check_decision_budget(p.n, alpha, p.eps, p.sigma,
                              candidate_ranges(conditions, p.preset, labels))


def _evaluated_model(model, scenario: Scenario, conditions: ConditionsTable, sigma: float):
    """The module perception evaluates: ``model`` itself (torch) or its ONNX Runtime session
    (fp32 or int8, the latter calibrated on noisy copies of calibration frames) with one
    intra-op thread per available core, while the rest of the Diagram keeps torch on one
    thread (DESIGN 3.8: at camera 10 Hz on 2 cores this is what reaches real time)."""
    from drake_cert.certification.backends import evaluated_model
    from drake_cert.threads import available_cores

    p = scenario.perception
    frames = None
    if p.quantization == "int8":
        from drake_cert.perception.datasets import load_split

        frames = load_split(p.preset, "calibration", conditions=conditions,
                            frames_per_class=8).images
    calibration = Int8Calibration(
        frames, sigma=max(sigma, 1e-3),  # base f (sigma 0): near-clean frames
        seed=child_seed(scenario.seed, Purpose.QUANTIZATION_CALIBRATION))
    return evaluated_model(model, backend=p.backend, quantization=p.quantization,
                           precision=resolve_precision(p.precision), calibration=calibration,
                           threads=available_cores())


@dataclasses.dataclass
class _PreparedDrive:
    """What the builder's steps share: the checked scenario and the objects built from it."""

    scenario: Scenario
    vehicle: VehicleParams
    settings: Settings
    tires: ConditionsTable  # the conditions table as this vehicle's tires feel it
    table: list[ControllerDesign]  # the preset's designs
    envelope: int  # index of the preset's envelope design in ``table``
    route: Route
    model: object  # the torch model (the attacker's gradients)
    evaluated: object  # what perception evaluates (torch or ONNX Runtime)
    sigma: float
    labels: list[str]
    period_s: float  # camera period
    initial_speed_mps: float
    regression_beta: float
    conformal: object
    seed_source: str

    @property
    def certified(self) -> bool:
        return self.scenario.perception.pipeline == "certified"


def build_certified_driving_diagram(scenario: Scenario, *, vehicle: VehicleParams,
                                    settings: Settings, conditions: ConditionsTable,
                                    designs: list[ControllerDesign],
                                    options: BuildOptions | None = None) -> DrivingDiagram:
    """Wire route, camera, attacker, perception, certified interval, longitudinal motion,
    switching L1 controller, Saturation and the Fiala plant into one Diagram, with logs.

    ``designs``: a synthesized design table (every contiguous label range of the scenario's
    preset must be in it). The certified pipeline runs the smoothed model at
    ``perception.sigma``; the base pipeline runs the model at ``perception.base_sigma``
    (0: the plain f) and is attacked by PGD on that model. Ports and timing: DESIGN 6.1.
    ``options`` (:class:`BuildOptions`): the tape period (s, default 0.05) and a wrapper of
    the calibration frames (a progress bar).
    """
    options = options or BuildOptions()
    prepared = _prepare_drive(scenario, vehicle, settings, conditions, designs,
                           options.calibration_progress)
    builder = DiagramBuilder()
    # added in the order motion, perception, control: the order their events were always in
    blocks = {**_add_motion(builder, prepared), **_add_perception(builder, prepared),
              **_add_control(builder, prepared)}
    _connect(builder, blocks, preview=settings.controller.preview_window_s > 0)
    loggers, tick_loggers = _add_loggers(builder, blocks, options.tape_period_s, prepared.period_s)
    diagram = builder.Build()
    diagram.set_name(f"certified_driving_{prepared.scenario.perception.pipeline}")
    switching = preset_switching_certificate(vehicle, prepared.table, settings,
                                             prepared.scenario.perception.preset)
    return DrivingDiagram(diagram, prepared.scenario, prepared.route, prepared.table, blocks,
                          loggers, tick_loggers, prepared.initial_speed_mps, vehicle,
                          prepared.seed_source,
                          switching=switching, lead_in_m=float(scenario.camera.look_ahead_m),
                          guarantee={**guarantee_summary(prepared.scenario, prepared.table,
                                                         prepared.conformal),
                                     "warnings": _calibration_warnings(prepared.scenario,
                                                                       prepared.regression_beta)})


def _prepare_drive(scenario: Scenario, vehicle: VehicleParams, settings: Settings,
                   conditions: ConditionsTable, designs: list[ControllerDesign],
                   calibration_progress: Callable | None) -> _PreparedDrive:
    """Check the scenario against the table, build the route and load and calibrate the model."""
    from drake_cert.certification.sampler import with_precision
    from drake_cert.perception.models import load_model

    scenario.validate("scenario")
    seed_source = "scenario"
    if scenario.seed is None:  # deployment: fresh noise, recorded so the drive can be replayed
        scenario, seed_source = dataclasses.replace(scenario, seed=entropy_seed()), "os-entropy"
    p = scenario.perception
    certified = p.pipeline == "certified"
    # The road's stiffness as this vehicle's tires feel it: the conditions table's intervals
    # times vehicle.tire_stiffness_scale (the front tires; the designs were synthesized on
    # these). The truth under the car, the labels' hulls and the designs' intervals use it;
    # the perception models (trained on the table's reference stiffness) and their calibration
    # keep the table.
    tires = conditions.with_stiffness_scale(vehicle.tire_stiffness_scale)
    table, envelope = moving_envelope(designs, tires, p.preset)
    check_route_is_seen(scenario, table)
    check_look_ahead(scenario, table)
    check_initial_speed(scenario, table)
    route = Route.build(scenario.route, tires, p.preset, scenario.seed,
                        transition_m=scenario.transition_m)
    sigma = p.sigma if certified else p.base_sigma
    # The attack and the certificate see the same model as evaluated (fp32 or bf16; ONNX
    # Runtime fp32 agrees with torch fp32 to float rounding; int8 is attacked through the fp32
    # model's gradients and judged by the int8 model's outputs).
    model = with_precision(load_model(p.preset, p.task, sigma), p.precision)
    evaluated = _evaluated_model(model, scenario, conditions, sigma)
    beta = _regression_beta(evaluated, scenario, conditions) \
        if certified and p.task == "regress" else math.inf
    conformal = drive_conformal_calibration(evaluated, scenario, conditions,
                                            calibration_progress) \
        if certified and p.task == "classify" and p.interval == "conformal" else None
    return _PreparedDrive(
        scenario=scenario, vehicle=vehicle, settings=settings, tires=tires, table=table,
        envelope=envelope, route=route, model=model, evaluated=evaluated, sigma=sigma,
        labels=list(conditions.preset(p.preset).labels), period_s=1.0 / scenario.camera.rate_hz,
        initial_speed_mps=scenario.motion.initial_speed_mps or float(table[envelope].speed_mps),
        regression_beta=beta, conformal=conformal, seed_source=seed_source)


def _add_perception(builder: DiagramBuilder, prepared: _PreparedDrive) -> dict:
    """Camera, attacker, perception smoothing and certified interval (DESIGN 6.1)."""
    scenario, tires, table = prepared.scenario, prepared.tires, prepared.table
    p, cam, att = scenario.perception, scenario.camera, scenario.attack
    add = builder.AddNamedSystem
    camera = add("camera", CameraSource(prepared.route, tires, p.preset, cam, seed=scenario.seed))
    # The attacker attacks the pipeline's own model: SmoothAdv on g at perception.sigma
    # (certified), PGD on f without noise (base), whatever the scenario's attack.target.
    attacker = add("attacker", Attacker(
        dataclasses.replace(att, target="smoothed" if prepared.certified else "base"), p, cam,
        model=prepared.model, seed=scenario.seed))
    perception = add("perception_smoothing", PerceptionSmoothing(
        prepared.evaluated, p, cam, seed=scenario.seed, inputs=PerceptionInputs(
            label_names=prepared.labels, ranges=candidate_ranges(tires, p.preset, prepared.labels),
            alpha_spending=alpha_spending(scenario, table), conformal=prepared.conformal)))
    interval = add("certified_interval", CertifiedInterval(
        table, tires, p, scenario.controller, cam, IntervalInputs(
            regression_beta=prepared.regression_beta, conformal=prepared.conformal,
            stiffness_scale=prepared.vehicle.tire_stiffness_scale, label_names=prepared.labels)))
    return dict(camera=camera, attacker=attacker, perception=perception, interval=interval)


def _add_motion(builder: DiagramBuilder, prepared: _PreparedDrive) -> dict:
    """Longitudinal motion and the route's road (DESIGN 6.1, 6.3)."""
    scenario, table, tires = prepared.scenario, prepared.table, prepared.tires
    p, cam, ctl = scenario.perception, scenario.camera, prepared.settings.controller
    add = builder.AddNamedSystem
    motion = add("longitudinal_motion", LongitudinalMotion(
        # the scenario's initial speed 0 means the envelope design's speed
        dataclasses.replace(scenario.motion, initial_speed_mps=prepared.initial_speed_mps), cam,
        designs=ProfileDesigns(
            join=join_design_indices(table, tires, p.preset), design_speeds_mps=_speeds(table),
            frontier_speed_mps=slowest_command_mps(table, scenario.motion.stop_speed_mps),
            # the certified pipeline combines its certified decisions over the shortest
            # stretch of one condition; the base pipeline's raw predictions each stand alone
            spans=design_label_spans(table, tires, p.preset) if prepared.certified else None,
            window_m=scenario.min_condition_length_m if prepared.certified else 0.0,
            tolerance=scenario.tolerated_wrong_frames, looks_per_side=scenario.looks_per_side,
            envelope_index=prepared.envelope),
        initial_design_index=prepared.envelope, initial_arc_length_m=-cam.look_ahead_m))
    road = add("route", RouteSource(prepared.route, preview_ahead_s=ctl.preview_ahead_s,
                                    preview_window_s=ctl.preview_window_s))
    return dict(motion=motion, route=road)


def _add_control(builder: DiagramBuilder, prepared: _PreparedDrive) -> dict:
    """The switching L1 controller, the steering Saturation and the Fiala plant (DESIGN 6.1)."""
    scenario, ctl, add = prepared.scenario, prepared.settings.controller, builder.AddNamedSystem
    controller = add("switching_l1_controller", SwitchingL1Controller(
        vehicle=prepared.vehicle, designs=prepared.table, settings=prepared.settings,
        options=SwitchingOptions(
            law=scenario.controller.law, initial_design_index=prepared.envelope,
            initial_speed_mps=prepared.initial_speed_mps,
            curvature_preview=ctl.preview_window_s > 0)))
    limit = prepared.vehicle.steering_limit_rad
    saturation = add("steering_saturation", Saturation([-limit], [limit]))
    plant = add("plant", NonlinearLateralPlant(prepared.vehicle,
                                               stop_speed_mps=scenario.motion.stop_speed_mps))
    return dict(controller=controller, saturation=saturation, plant=plant)


def _connect(builder: DiagramBuilder, blocks: dict, preview: bool) -> None:
    """The Diagram's wiring (DESIGN 6.1), in one fixed order."""
    motion, road, camera = blocks["motion"], blocks["route"], blocks["camera"]
    plant, controller = blocks["plant"], blocks["controller"]
    interval, perception = blocks["interval"], blocks["perception"]
    builder.Connect(motion.GetOutputPort("arc_length_m"), road.GetInputPort("arc_length_m"))
    builder.Connect(motion.GetOutputPort("arc_length_m"), camera.GetInputPort("arc_length_m"))
    builder.Connect(camera.GetOutputPort("frame"), blocks["attacker"].GetInputPort("frame"))
    builder.Connect(blocks["attacker"].GetOutputPort("frame"), perception.GetInputPort("frame"))
    builder.Connect(perception.GetOutputPort("perception"), interval.GetInputPort("perception"))
    builder.Connect(interval.GetOutputPort("decision"), motion.GetInputPort("decision"))
    builder.Connect(plant.GetOutputPort("state"), controller.GetInputPort("state"))
    builder.Connect(road.GetOutputPort("curvature_per_m"),
                    controller.GetInputPort("curvature_per_m"))
    if preview:
        builder.Connect(motion.GetOutputPort("speed_mps"), road.GetInputPort("speed_mps"))
        builder.Connect(road.GetOutputPort("curvature_preview_per_m"),
                  controller.GetInputPort("curvature_preview_per_m"))
    builder.Connect(motion.GetOutputPort("speed_mps"), controller.GetInputPort("speed_mps"))
    builder.Connect(motion.GetOutputPort("design_index"), controller.GetInputPort("design_index"))
    builder.Connect(controller.GetOutputPort("steering_rad"), blocks["saturation"].get_input_port())
    builder.Connect(blocks["saturation"].get_output_port(), plant.GetInputPort("steering_rad"))
    for port in ("stiffness_n_per_rad", "friction_mu", "curvature_per_m"):
        builder.Connect(road.GetOutputPort(port), plant.GetInputPort(port))
    builder.Connect(motion.GetOutputPort("speed_mps"), plant.GetInputPort("speed_mps"))


def _add_loggers(builder: DiagramBuilder, blocks: dict, tape_period_s: float,
                 period_s: float) -> tuple[dict, dict]:
    """The tape's loggers (every ``tape_period_s``) and the camera-period loggers."""
    def log(port, every=tape_period_s):
        return LogVectorOutput(port, builder, every)

    motion, road, interval = blocks["motion"], blocks["route"], blocks["interval"]
    loggers = {
        "state": log(blocks["plant"].GetOutputPort("state")),
        "steering": log(blocks["saturation"].get_output_port()),
        "speed": log(motion.GetOutputPort("speed_mps")),
        "arc_length": log(motion.GetOutputPort("arc_length_m")),
        "curvature": log(road.GetOutputPort("curvature_per_m")),
        "true_stiffness": log(road.GetOutputPort("stiffness_n_per_rad")),
        "design": log(blocks["controller"].GetOutputPort("active_design_index")),
        "interval": log(interval.GetOutputPort("interval_n_per_rad")),
        "speed_command": log(interval.GetOutputPort("speed_command_mps")),
        "radius": log(interval.GetOutputPort("certified_radius")),
        "status": log(interval.GetOutputPort("status")),
    }
    # Camera-period logs publish at t_k, before that tick's updates: each sample holds the
    # decision of tick k-1 and the truth of the frame it came from.
    tick_loggers = {
        "interval": log(interval.GetOutputPort("interval_n_per_rad"), period_s),
        "seen_stiffness": log(blocks["camera"].GetOutputPort("seen_stiffness_n_per_rad"), period_s),
        "status": log(interval.GetOutputPort("status"), period_s),
        "design": log(interval.GetOutputPort("design_index"), period_s),
        "samples": log(blocks["perception"].GetOutputPort("samples"), period_s),
        "requested": log(interval.GetOutputPort("requested_design_index"), period_s),
    }
    return loggers, tick_loggers


_CERTIFICATES: dict[str, object] = {}  # memo of preset_switching_certificate, by value
_CERTIFICATES_KEPT = 16


def preset_switching_certificate(vehicle: VehicleParams, table: list[ControllerDesign],
                                 settings: Settings, preset: str):
    """The switching certificate of a preset's designs
    (:func:`drake_cert.synthesis.switching.common_lyapunov_certificate`, DESIGN 5.6), memoised on
    the values of its inputs: drives that share vehicle, designs and settings (every drive of a
    sweep or a test session) solve its LMIs once."""
    from drake_cert.synthesis.switching import common_lyapunov_certificate

    key = repr((dataclasses.asdict(vehicle), [dataclasses.asdict(d) for d in table],
                dataclasses.asdict(settings), preset))
    if key not in _CERTIFICATES:
        if len(_CERTIFICATES) >= _CERTIFICATES_KEPT:
            _CERTIFICATES.clear()
        _CERTIFICATES[key] = common_lyapunov_certificate(vehicle, table, settings,
                                                         family=preset)
    return _CERTIFICATES[key]


@dataclasses.dataclass
class DriveResult:
    """What a drive returns (plain data: it crosses process boundaries)."""

    tape: DriveTape
    ticks: TickLog
    summary: dict
    route: Route
    lane_width_m: float


def drive_warnings(summary: dict) -> list[str]:
    """What a drive's summary must warn about beyond the calibration: an attack above the
    certified budget (no certificate covers it) and switching the certificate does not cover
    (``switching_note``)."""
    out = []
    if not summary.get("attack_within_certified_budget", True):
        out.append(f"attack budget {summary['attack_eps']:g} exceeds the certified eps "
                   f"{summary['certified_eps']:g}: no certificate covers it")
    if summary.get("switching_note"):
        out.append(summary["switching_note"])
    return out


def _read(logger, context) -> tuple[np.ndarray, np.ndarray]:
    log = logger.FindLog(context)
    return log.sample_times().copy(), log.data().T.copy()


def drive(built: DrivingDiagram, *, progress: Callable[[float], None] | None = None,
          t_final_s: float | None = None) -> DriveResult:
    """Simulate the Diagram to the route's end (or ``t_final_s``); returns tape and summary.

    A drive ends when the car passes the end of the route, leaves the road (|e1| > 5 m, the
    Frenet frame stops making sense), has rested for 5 s (a stop for good), or at the time
    limit (the scenario's ``t_final_s``, else the route at 5 m/s plus 10 s). ``progress``
    receives simulated seconds as they pass.
    """
    scenario, route = built.scenario, built.route
    plant = built.systems["plant"]
    motion = built.systems["motion"]
    limit = t_final_s or scenario.t_final_s or route.total_length_m / 5.0 + 10.0
    simulator = Simulator(built.diagram)
    ApplySimulatorConfig(scenario.simulator, simulator)
    context = simulator.get_mutable_context()
    kappa0 = float(route.curvature_at(-built.lead_in_m))
    s0 = np.zeros(4)
    plant.body_state_subsystem().GetMyMutableContextFromRoot(context).SetContinuousState(
        np.asarray(body_state_from_error(s0, built.initial_speed_mps, kappa0), float))
    built.systems["controller"].set_initial_state(context, s0, kappa0)
    plant_context = plant.GetMyContextFromRoot(context)
    motion_context = motion.GetMyContextFromRoot(context)
    state_port, arc_port = plant.GetOutputPort("state"), motion.GetOutputPort("arc_length_m")
    speed_port = motion.GetOutputPort("speed_mps")
    ending = {"reason": "time limit", "rest_since": None}

    def monitor(root):
        t = root.get_time()
        e1 = state_port.Eval(plant_context)[0]
        if not abs(e1) <= OFF_ROAD_M:  # NaN too: a diverged simulation is not in its lane
            ending["reason"] = "off road"
            return EventStatus.ReachedTermination(built.diagram, "off road")
        if arc_port.Eval(motion_context)[0] >= route.total_length_m:
            ending["reason"] = "route end"
            return EventStatus.ReachedTermination(built.diagram, "route end")
        if speed_port.Eval(motion_context)[0] <= 1e-6:
            ending["rest_since"] = ending["rest_since"] if ending["rest_since"] is not None else t
            if t - ending["rest_since"] >= REST_LIMIT_S:
                ending["reason"] = "stopped"
                return EventStatus.ReachedTermination(built.diagram, "stopped")
        else:
            ending["rest_since"] = None
        return EventStatus.Succeeded()

    simulator.set_monitor(monitor)
    start = time.perf_counter()
    simulator.Initialize()
    t = 0.0
    while t < limit and ending["reason"] == "time limit":
        t_next = min(t + 1.0, limit)
        simulator.AdvanceTo(t_next)
        if progress is not None:
            progress(context.get_time() - t)
        t = context.get_time()
        if t < t_next - 1e-9:  # the monitor ended the drive
            break
    wall = time.perf_counter() - start
    tape, ticks = _tapes(built, context)
    run = DriveRun(simulated_s=context.get_time(), wall_s=wall, ending=ending["reason"],
                   seed_source=built.seed_source,
                   envelope_index=built.systems["interval"].envelope_index,
                   lead_in_m=built.lead_in_m,
                   alpha_spending=built.systems["perception"].alpha_spending,
                   guarantee=built.guarantee)
    summary = summarize_drive(tape, ticks, scenario=scenario, route=route, run=run)
    if built.switching is not None:
        from drake_cert.synthesis.switching import drive_switching_report

        switches = tape.times_s[1:][np.diff(tape.design_index) != 0]
        summary.update(drive_switching_report(built.switching, switches))
    summary["warnings"] = list(summary.get("warnings") or []) + drive_warnings(summary)
    summary["vehicle"] = dataclasses.asdict(built.vehicle)  # the vehicle that drove (SI units)
    return DriveResult(tape, ticks, summary, route, built.vehicle.lane_width_m)


def drive_scenario(scenario: Scenario, *, vehicle: VehicleParams, settings: Settings,
                   conditions: ConditionsTable, designs: list[ControllerDesign],
                   progress: DriveProgress | None = None) -> DriveResult:
    """Build the Diagram for ``scenario`` and drive it (one call; usable in a worker process);
    ``progress`` (:class:`DriveProgress`): ``drive`` is called with the simulated seconds
    advanced, ``calibration`` wraps the iterable of calibration frames (a progress bar)."""
    from drake_cert.threads import torch_threads

    progress = progress or DriveProgress()
    with torch_threads(1):
        built = build_certified_driving_diagram(
            scenario, vehicle=vehicle, settings=settings, conditions=conditions,
            designs=designs, options=BuildOptions(calibration_progress=progress.calibration))
        return drive(built, progress=progress.drive)


def _in_force(designs: list[ControllerDesign], index: np.ndarray) -> dict:
    """The interval (N/rad) and safe speed (m/s, 0 if none) of the design in force per sample."""
    lo = np.array([d.stiffness_lo_n_per_rad for d in designs])
    hi = np.array([d.stiffness_hi_n_per_rad for d in designs])
    speed = np.array([float(d.speed_mps) if d.has_safe_speed else 0.0 for d in designs])
    return dict(design_interval_n_per_rad=np.column_stack([lo[index], hi[index]]),
                design_speed_mps=speed[index])


def protection(tape: DriveTape, speed_slack_mps: float = 0.1) -> tuple[float | None, float]:
    """``(design_covers_true_fraction, time_unprotected_s)`` of a drive (DESIGN 6).

    Over the tape's samples (each standing for the time to the next one): the share of time in
    which the design in force holds the true stiffness under the car, and the time (s) in which
    it does not, or the car is faster than that design's safe speed plus ``speed_slack_mps``.
    The tape's period (50 ms by default) is the resolution of both.
    """
    if len(tape.times_s) < 2:
        return None, 0.0
    dt = np.diff(tape.times_s)
    c = tape.true_stiffness_n_per_rad[:-1]
    lo, hi = tape.design_interval_n_per_rad[:-1, 0], tape.design_interval_n_per_rad[:-1, 1]
    covered = (lo <= c) & (c <= hi)
    too_fast = tape.speed_mps[:-1] > tape.design_speed_mps[:-1] + speed_slack_mps
    return (float(np.sum(dt * covered) / np.sum(dt)),
            float(np.sum(dt * (~covered | too_fast))))


def _tapes(built: DrivingDiagram, context) -> tuple[DriveTape, TickLog]:
    logs = {k: _read(v, context) for k, v in built.loggers.items()}
    n = min(len(t) for t, _ in logs.values())
    col = {k: d[:n] for k, (_, d) in logs.items()}
    tape = DriveTape(
        times_s=logs["state"][0][:n], states=col["state"], steering_rad=col["steering"][:, 0],
        speed_mps=col["speed"][:, 0], speed_command_mps=col["speed_command"][:, 0],
        arc_length_m=col["arc_length"][:, 0], curvature_per_m=col["curvature"][:, 0],
        interval_n_per_rad=col["interval"], true_stiffness_n_per_rad=col["true_stiffness"][:, 0],
        design_index=col["design"][:, 0].astype(int), certified_radius=col["radius"][:, 0],
        status=col["status"][:, 0].astype(int), lane_margin_m=built.vehicle.lane_margin_m,
        **_in_force(built.designs, col["design"][:, 0].astype(int)))
    ticks_raw = {k: _read(v, context) for k, v in built.tick_loggers.items()}
    m = min(len(t) for t, _ in ticks_raw.values())
    seen = ticks_raw["seen_stiffness"][1][:m, 0]
    framed = np.isfinite(seen)  # ticks after a frame (the first sample precedes any)
    ticks = TickLog(times_s=ticks_raw["interval"][0][:m][framed],
                    interval_n_per_rad=ticks_raw["interval"][1][:m][framed],
                    seen_stiffness_n_per_rad=seen[framed],
                    status=ticks_raw["status"][1][:m, 0][framed].astype(int),
                    design_index=ticks_raw["design"][1][:m, 0][framed].astype(int),
                    samples=ticks_raw["samples"][1][:m, 0][framed].astype(int),
                    requested_design_index=ticks_raw["requested"][1][:m, 0][framed].astype(int))
    return tape, ticks


def check_initial_speed(scenario: Scenario, table: list) -> None:
    """ConfigError when the scenario starts the car faster than the fastest safe speed of its
    preset's designs: it would start outside every certificate (a speed in km/h, say)."""
    v0 = scenario.motion.initial_speed_mps
    fastest = max((d.speed_mps for d in table), default=0.0)
    if v0 > fastest:
        raise ConfigError(
            f"{scenario.name}: motion.initial_speed_mps = {v0:g} m/s is above the fastest safe "
            f"speed of the {scenario.perception.preset} designs ({fastest:.2f} m/s): the car "
            f"would start outside every certificate (km/h? {v0:g} km/h is {v0 / 3.6:.2f} m/s; "
            "0 starts at the envelope design's speed)")


def time_left_lane(tape: DriveTape) -> float | None:
    """First logged time (s) at which |e1| exceeded the lane margin; None if never."""
    out = np.nonzero(~(np.abs(tape.lateral_offset_m) <= tape.lane_margin_m))[0]  # NaN: out
    return float(tape.times_s[out[0]]) if len(out) else None


def summarize_drive(tape: DriveTape, ticks: TickLog, *, scenario: Scenario, route: Route,
                    run: DriveRun) -> dict:
    """The ``drive --json`` object (DESIGN 7 metrics of one drive); ``run``
    (:class:`DriveRun`): how the drive ran and what its Diagram was built with.

    ``mean_speed_mps`` is over the route (arc length >= 0, from the first point a frame
    showed); the lead-in before it (``lead_in_m``, driven under the envelope design before any
    decision) counts in every other figure. ``abstention_fraction``: share of camera ticks
    whose own decision is the envelope (perception abstained, or the frame was bad);
    ``certified_wrong_fraction``: share of camera ticks whose own decision is certified (not
    the envelope) and whose interval misses the true stiffness of the frame's road;
    ``envelope_fraction``: share of camera ticks whose decision for the look point is the
    envelope after the dwell time (the abstentions, and the ticks after one whose narrower
    design the dwell time holds back); ``envelope_time_fraction``: share of simulated time the
    envelope design is in force on the route (what the car drives under: the combined
    decisions give an abstaining tick's stretch the join of its certified neighbours).
    ``certificate_failure_bound``: the union bound on the probability that some certificate of
    the drive failed (:func:`certificate_failure_bound`, over the at most
    ``ceil(simulated_s * rate_hz)`` decisions taken); where none failed, the design in force
    held the stiffness under the car up to the standing assumption (DESIGN 6.2).
    ``guarantee``: :func:`guarantee_summary` (``interval``, ``standing_assumption``,
    ``guarantee_failure_bound`` and what it is computed from), merged in.
    """
    simulated_s, wall_s, ending = run.simulated_s, run.wall_s, run.ending
    seed_source, envelope_index, lead_in_m = run.seed_source, run.envelope_index, run.lead_in_m
    alpha_spending, guarantee = run.alpha_spending, run.guarantee
    left = time_left_lane(tape)
    covers = (ticks.interval_n_per_rad[:, 0] <= ticks.seen_stiffness_n_per_rad) & \
        (ticks.seen_stiffness_n_per_rad <= ticks.interval_n_per_rad[:, 1])
    mean_speed, envelope_time = _route_speed_figures(tape, envelope_index)
    peak = float(np.max(np.abs(tape.lateral_offset_m))) if len(tape.times_s) else 0.0
    design_covers, unprotected = protection(tape)
    attacked = scenario.attack.kind in ("sa", "ea")
    return {
        "scenario": scenario.name,
        "pipeline": scenario.perception.pipeline,
        "task": scenario.perception.task,
        "attack": scenario.attack.kind,
        "attack_eps": scenario.attack.eps,
        "certified_eps": scenario.perception.eps,
        "left_lane": left is not None,
        "peak_abs_e1_m": peak,
        "time_left_lane_s": left,
        "mean_speed_mps": mean_speed,
        "min_speed_mps": float(np.min(tape.speed_mps)) if len(tape.speed_mps) else 0.0,
        "distance_m": float(tape.arc_length_m[-1]) if len(tape.arc_length_m) else 0.0,
        "route_length_m": route.total_length_m,
        "ending": ending,
        "simulated_s": float(simulated_s),
        "wall_s": float(wall_s),
        "real_time_factor": float(simulated_s / wall_s) if wall_s > 0 else None,
        "camera_ticks": int(len(ticks.times_s)),
        "interval_covers_true_fraction": float(np.mean(covers)) if len(covers) else None,
        "design_covers_true_fraction": design_covers,
        "time_unprotected_s": unprotected,
        "alpha_scope": scenario.perception.alpha_scope,
        "certificate_failure_bound": certificate_failure_bound(
            scenario, alpha_spending, math.ceil(simulated_s * scenario.camera.rate_hz - 1e-9)),
        "attack_within_certified_budget": (not attacked
                                           or scenario.attack.eps <= scenario.perception.eps),
        **_tick_decision_fractions(ticks, covers, envelope_index),
        "envelope_time_fraction": envelope_time,
        "lead_in_m": float(lead_in_m),
        "design_switches": int(np.count_nonzero(np.diff(tape.design_index))),
        "design_intervals_n_per_rad": designs_in_force(tape),
        "mean_samples_per_tick": float(np.mean(ticks.samples)) if len(ticks.samples) else None,
        "max_samples_per_tick": int(np.max(ticks.samples)) if len(ticks.samples) else 0,
        **_perception_settings(scenario, seed_source),
        **(guarantee or {}),
    }


def designs_in_force(tape: DriveTape) -> list[list[float]]:
    """The stiffness intervals (N/rad, the front tire's C) of the designs that were in force,
    in the order they first took over."""
    rows = np.asarray(tape.design_interval_n_per_rad, dtype=float).reshape(-1, 2)
    rows = rows[np.all(np.isfinite(rows), axis=1)]
    if not len(rows):
        return []
    unique, first = np.unique(rows, axis=0, return_index=True)
    return [[float(lo), float(hi)] for lo, hi in unique[np.argsort(first)]]


def _route_speed_figures(tape: DriveTape, envelope_index: int | None
                         ) -> tuple[float, float | None]:
    """:func:`summarize_drive`'s mean speed over the route (from the first point a frame
    showed) and share of the route's time the envelope design is in force (None without an
    envelope or a route)."""
    dt = np.diff(tape.times_s)
    on_route = tape.arc_length_m[:-1] >= 0.0 if len(dt) else np.zeros(0, bool)
    mean_speed = float(np.sum((tape.speed_mps[:-1] * dt)[on_route]) / np.sum(dt[on_route])) \
        if np.any(on_route) else float(tape.speed_mps[0]) if len(tape.speed_mps) else 0.0
    envelope_time = (float(np.sum(dt[on_route & (tape.design_index[:-1] == envelope_index)])
                           / np.sum(dt[on_route]))
                     if envelope_index is not None and np.any(on_route) else None)
    return mean_speed, envelope_time


def _tick_decision_fractions(ticks: TickLog, covers: np.ndarray,
                             envelope_index: int | None) -> dict:
    """:func:`summarize_drive`'s shares of camera ticks: abstentions, certified but wrong, and
    the envelope in force after the dwell time."""
    return {
        "abstention_fraction": (float(np.mean(ticks.requested_design_index == envelope_index))
                                if envelope_index is not None and len(ticks.status) else None),
        "certified_wrong_fraction": (
            float(np.mean((ticks.requested_design_index != envelope_index) & ~covers))
            if envelope_index is not None and len(ticks.status) else None),
        "envelope_fraction": float(np.mean(ticks.status == 1)) if len(ticks.status) else None,
    }


def _perception_settings(scenario: Scenario, seed_source: str) -> dict:
    """:func:`summarize_drive`'s figures of the perception's settings: sample rate needed,
    seed, precision, decision rule, backend and quantization."""
    return {
        # the modelled perception latency T/4 holds on hardware that draws the most samples a
        # tick may take (n0 + n) in T/4
        "samples_per_s_required": (
            (scenario.perception.n0 + scenario.perception.n) * 4.0 * scenario.camera.rate_hz
            if scenario.perception.pipeline == "certified" else 0.0),
        "seed": scenario.seed,
        "seed_source": seed_source,
        "precision": resolve_precision(scenario.perception.precision),
        "decision": scenario.perception.resolved_decision
        if scenario.perception.pipeline == "certified" else "none (base f)",
        "backend": resolve_backend(scenario.perception.backend,
                                   resolve_precision(scenario.perception.precision)),
        "quantization": scenario.perception.quantization,
    }
