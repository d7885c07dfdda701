"""Driving scenarios: typed YAML (DESIGN 6; the Drake hardware_sim pattern).

A scenario names everything a drive needs -- the route, the camera, the perception and its
certificate, the attack, the longitudinal motion, the controller law and dwell time, the
simulator -- and its random seed, so a drive is reproducible from its YAML alone. Files are
read with :func:`drake_cert.config.load_typed`: every key must be given, unknown keys raise
:class:`ConfigError` naming the key and the file, and non-physical values are rejected.
Shipped scenarios live in ``drake_cert/data/scenarios/<name>.yaml``.
"""


import dataclasses
import math
from importlib import resources
from pathlib import Path

from pydrake.systems.analysis import SimulatorConfig

from drake_cert.config import (
    SPEED_PLAUSIBLE,
    check_frame_size,
    check_plausible_fields,
    load_typed,
)
from drake_cert.errors import ConfigError
from drake_cert.systems.route import SegmentSpec

SHIPPED_SCENARIOS = ("dry_to_snow", "rain_route", "road_surface", "sunny_into_snow",
                     "weather_change_in_curve", "sunny_straight_to_snow", "curve_entry_changes")
PIPELINES = ("certified", "base")
TASKS = ("classify", "regress")
ALPHA_SCOPES = ("decision", "drive")  # what perception.alpha bounds: each decision, or all
ATTACK_KINDS = ("none", "sa", "ea", "nan", "misshaped")
ATTACK_TARGETS = ("base", "smoothed")
LAWS = ("piecewise_constant", "gradient")
IMPLICIT_SCHEMES = ("radau3", "radau1", "implicit_euler")  # what the gradient law needs


def _positive(value, key: str, where: str) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{where}: {key} = {value!r} must be a positive finite number")


def _non_negative(value, key: str, where: str) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
        raise ConfigError(f"{where}: {key} = {value!r} must be a finite number >= 0")


def _one_of(value, choices, key: str, where: str) -> None:
    if value not in choices:
        raise ConfigError(f"{where}: {key} = {value!r}; expected one of {', '.join(choices)}")


@dataclasses.dataclass
class CameraSettings:
    """The forward camera."""

    rate_hz: float = 10.0  # frames per second; the perception period is 1 / rate_hz (s)
    look_ahead_m: float = 40.0  # the frame shows the road this far ahead of the car (m)
    frame_size: int = 64  # frames are frame_size x frame_size RGB pixels (16 to 1024)
    frames_dir: str = ""  # "" renders frames; else a class-per-folder image directory

    def validate(self, where: str) -> None:
        _positive(self.rate_hz, "camera.rate_hz", where)
        _non_negative(self.look_ahead_m, "camera.look_ahead_m", where)
        if self.frame_size < 16:
            raise ConfigError(f"{where}: camera.frame_size = {self.frame_size} must be >= 16")


@dataclasses.dataclass
class PerceptionSettings:
    """The perception model and its certificate (DESIGN 3)."""

    preset: str = "robotcar-like"  # perception preset: its labels, models and frames
    task: str = "classify"  # "classify" (label certificate) or "regress" (median smoothing)
    sigma: float = 0.25  # smoothing noise level (pixel units in [0, 1]) of the certified model
    base_sigma: float = 0.0  # noise level of the model the base pipeline runs (0: plain f)
    eps: float = 0.5  # L2 budget (pixel units) the run-time interval is certified against
    n0: int = 100  # selection samples per certificate (sequential: 0 = test every range at once)
    n: int = 1000  # estimation samples per certificate
    alpha: float = 0.001  # failure probability of each decision, or of the whole drive
    alpha_scope: str = "decision"  # "decision": alpha each; "drive": alpha for all together
    batch_size: int = 500  # noisy copies per model evaluation
    pipeline: str = "certified"  # "certified" (smoothed g) or "base" (raw f, non-robust)
    calibration_frames_per_class: int = 20  # regression: conformal calibration frames per label
    calibration_n: int = 500  # regression: samples per calibration frame
    alpha_c: float = 0.01  # regression: conformal miscoverage
    alpha_m: float = 0.001  # regression: level of the calibration median interval
    precision: str = "auto"  # "auto" (fp32 with ONNX Runtime if installed; DESIGN 3.8), fp32, bf16
    decision: str = "auto"  # "sequential" (n: the most samples), "fixed"; auto: sequential if apt
    backend: str = "auto"  # "torch", "onnxruntime"; auto: onnxruntime if installed and fp32
    quantization: str = "none"  # "none" or "int8" (onnxruntime; the certificate is the int8 one)
    interval: str = "conformal"  # classification interval: "conformal" (DESIGN 3.6) or "safe_set"
    # "conformal" (docs/design.md 3.6): calibration frames per label, split over the bins
    conformal_frames_per_class: int = 2000
    # "conformal": the bound on the conformal step's miss rate in every stiffness bin, for all
    # calibrations outside an event of probability conformal_delta_cal (alpha_total adds
    # beta_cal + beta_test = 0.002)
    conformal_alpha_c: float = 0.25
    conformal_bins_per_label: int = 4  # "conformal": equal-width stiffness bins of each label
    conformal_delta_cal: float = 0.001  # "conformal": probability the calibration is a bad one
    conformal_calibration_n: int = 500  # "conformal": samples per calibration frame

    @property
    def resolved_decision(self) -> str:
        """"sequential" or "fixed": what ``decision`` means for this task and interval."""
        if self.decision != "auto":
            return self.decision
        return "sequential" if self.task == "classify" else "fixed"

    def validate(self, where: str) -> None:
        _one_of(self.task, TASKS, "perception.task", where)
        _one_of(self.precision, ("auto", "fp32", "bf16"), "perception.precision", where)
        _one_of(self.interval, ("safe_set", "conformal"), "perception.interval", where)
        _one_of(self.alpha_scope, ALPHA_SCOPES, "perception.alpha_scope", where)
        _one_of(self.decision, ("auto", "sequential", "fixed"), "perception.decision", where)
        _one_of(self.backend, ("auto", "torch", "onnxruntime"), "perception.backend", where)
        _one_of(self.quantization, ("none", "int8"), "perception.quantization", where)
        if self.quantization == "int8" and self.backend != "onnxruntime":
            raise ConfigError(f"{where}: perception.quantization = int8 needs backend "
                              "onnxruntime")
        if self.decision == "sequential" and self.task != "classify":
            raise ConfigError(f"{where}: perception.decision = sequential needs task classify "
                              "(a drive's regression interval uses the fixed-n certificate); "
                              "use fixed or auto")
        _one_of(self.pipeline, PIPELINES, "perception.pipeline", where)
        _positive(self.sigma, "perception.sigma", where)
        _non_negative(self.base_sigma, "perception.base_sigma", where)
        _non_negative(self.eps, "perception.eps", where)
        if self.resolved_decision == "sequential" and self.n0 < 0:
            raise ConfigError(f"{where}: perception.n0 = {self.n0} must be >= 0 (0: no "
                              "selection, every label range is tested at once)")
        keys = ("n", "batch_size", "calibration_frames_per_class", "calibration_n",
                "conformal_frames_per_class", "conformal_bins_per_label",
                "conformal_calibration_n")
        for key in keys if self.resolved_decision == "sequential" else ("n0", *keys):
            if getattr(self, key) <= 0:
                raise ConfigError(f"{where}: perception.{key} = {getattr(self, key)} must be a "
                                  "positive integer")
        for key in ("alpha", "alpha_c", "alpha_m", "conformal_alpha_c", "conformal_delta_cal"):
            if not 0 < getattr(self, key) < 1:
                raise ConfigError(f"{where}: perception.{key} = {getattr(self, key)!r} must be "
                                  "in (0, 1)")
        if self.task == "classify" and self.interval == "conformal" and \
                self.pipeline == "certified":
            from drake_cert.certification.pac_conformal import min_frames_per_bin

            # a necessary check before the conditions are read (every preset has 3 labels);
            # the calibration names any bin that is still short
            bins = self.conformal_bins_per_label
            need = min_frames_per_bin(self.conformal_alpha_c,
                                      self.conformal_delta_cal / (3 * bins))
            if self.conformal_frames_per_class < bins * need:
                raise ConfigError(
                    f"{where}: perception.conformal_frames_per_class = "
                    f"{self.conformal_frames_per_class} gives fewer than the {need} calibration "
                    f"frames a stiffness bin (of {bins}) that conformal_alpha_c = "
                    f"{self.conformal_alpha_c:g} at conformal_delta_cal = "
                    f"{self.conformal_delta_cal:g} needs for any threshold (with fewer, a label "
                    "never leaves the set); raise it to at least "
                    f"{bins * need} or conformal_alpha_c")


@dataclasses.dataclass
class AttackSettingsYaml:
    """The attacker between the camera and perception (DESIGN 3, attacks)."""

    kind: str = "none"  # "none", "sa" (stability), "ea" (efficiency), or faults "nan", "misshaped"
    eps: float = 0.0  # L2 budget of sa/ea (pixel units in [0, 1])
    target: str = "smoothed"  # "smoothed": SmoothAdv on g; "base": PGD on f without noise
    steps: int = 20  # PGD iterations per frame
    noise_draws: int = 8  # noise draws per PGD step against the smoothed model

    def validate(self, where: str) -> None:
        _one_of(self.kind, ATTACK_KINDS, "attack.kind", where)
        _one_of(self.target, ATTACK_TARGETS, "attack.target", where)
        _non_negative(self.eps, "attack.eps", where)
        if self.steps < 0:
            raise ConfigError(f"{where}: attack.steps = {self.steps} must be >= 0")
        if self.noise_draws < 1:
            raise ConfigError(f"{where}: attack.noise_draws = {self.noise_draws} must be >= 1")


@dataclasses.dataclass
class MotionSettings:
    """Longitudinal motion (speed along the route)."""

    max_decel_mps2: float = 4.0  # largest braking deceleration (m/s^2)
    max_accel_mps2: float = 2.0  # largest acceleration (m/s^2)
    # speed at t = 0 (m/s); 0: the envelope design's speed
    initial_speed_mps: float = dataclasses.field(default=0.0,
                                                 metadata={"plausible": SPEED_PLAUSIBLE})
    # a command below this brakes the car to rest (m/s)
    stop_speed_mps: float = dataclasses.field(default=5.0, metadata={"plausible": SPEED_PLAUSIBLE})

    def validate(self, where: str) -> None:
        _positive(self.max_decel_mps2, "motion.max_decel_mps2", where)
        _positive(self.max_accel_mps2, "motion.max_accel_mps2", where)
        _non_negative(self.initial_speed_mps, "motion.initial_speed_mps", where)
        _non_negative(self.stop_speed_mps, "motion.stop_speed_mps", where)
        check_plausible_fields(self, "motion.", where)


@dataclasses.dataclass
class ControllerScenario:
    """The switching L1 controller's law and the design dwell time."""

    law: str = "piecewise_constant"  # L1 adaptation law: "piecewise_constant" or "gradient"
    dwell_time_s: float = 0.3  # least time between two design switches (s)

    def validate(self, where: str) -> None:
        _one_of(self.law, LAWS, "controller.law", where)
        _non_negative(self.dwell_time_s, "controller.dwell_time_s", where)


@dataclasses.dataclass
class Scenario:
    """One drive, reproducible from this file alone."""

    name: str = ""  # short name of the scenario
    seed: int | None = 0  # seed of every random stream; null: OS entropy (deployment)
    transition_m: float = 10.0  # curvature ramps over this length at segment boundaries (m)
    # the shortest stretch of one road condition the car assumes (m): decisions bridge
    # abstentions over shorter spans; a route with a shorter stretch (first and last
    # excepted) is refused (drake_cert.systems.driving.check_route_is_seen)
    min_condition_length_m: float = 60.0
    # the combined decisions' counting rule (docs/design.md 6.3): each side of a stretch holds
    # its nearest looks_per_side camera ticks (abstentions included) within the window, and
    # keeps the labels that all but tolerated_wrong_frames of them support; each tolerated
    # frame costs a camera period of look-ahead
    tolerated_wrong_frames: int = 14
    looks_per_side: int = 20
    route: list[SegmentSpec] = dataclasses.field(default_factory=list)  # segments, in order
    camera: CameraSettings = dataclasses.field(default_factory=CameraSettings)
    perception: PerceptionSettings = dataclasses.field(default_factory=PerceptionSettings)
    attack: AttackSettingsYaml = dataclasses.field(default_factory=AttackSettingsYaml)
    motion: MotionSettings = dataclasses.field(default_factory=MotionSettings)
    controller: ControllerScenario = dataclasses.field(default_factory=ControllerScenario)
    simulator: SimulatorConfig = dataclasses.field(default_factory=SimulatorConfig)
    t_final_s: float = 0.0  # simulated time (s); 0: until the car reaches the route's end

    def validate(self, where: str = "scenario") -> None:
        if not self.name:
            raise ConfigError(f"{where}: name must not be empty")
        if self.seed is not None and self.seed < 0:
            raise ConfigError(f"{where}: seed = {self.seed} must be >= 0 (or null)")
        _positive(self.transition_m, "transition_m", where)
        _positive(self.min_condition_length_m, "min_condition_length_m", where)
        if isinstance(self.looks_per_side, bool) or not isinstance(self.looks_per_side, int) \
                or not 1 <= self.looks_per_side <= 64:
            raise ConfigError(f"{where}: looks_per_side = {self.looks_per_side!r} must be an "
                              "integer in 1..64")
        if isinstance(self.tolerated_wrong_frames, bool) or not isinstance(
                self.tolerated_wrong_frames, int) or \
                not 0 <= self.tolerated_wrong_frames < self.looks_per_side:
            raise ConfigError(f"{where}: tolerated_wrong_frames = "
                              f"{self.tolerated_wrong_frames!r} must be an integer in "
                              f"0..{self.looks_per_side - 1} (below looks_per_side)")
        _non_negative(self.t_final_s, "t_final_s", where)
        if not self.route:
            raise ConfigError(f"{where}: route must list at least one segment")
        for i, seg in enumerate(self.route):
            _positive(seg.length_m, f"route[{i}].length_m", where)
            if not (math.isfinite(seg.curvature_per_m) and abs(seg.curvature_per_m) <= 0.02):
                raise ConfigError(f"{where}: route[{i}].curvature_per_m = {seg.curvature_per_m!r}"
                                  ": the radius must be at least 50 m (|kappa| <= 0.02 1/m)")
            if not seg.condition:
                raise ConfigError(f"{where}: route[{i}].condition must not be empty")
        # before anything allocates a frame (the camera's placeholder is one)
        check_frame_size(self.camera.frame_size, f"{where}: camera.frame_size",
                         self.perception.batch_size)
        for part in (self.camera, self.perception, self.attack, self.motion, self.controller):
            part.validate(where)
        if self.controller.law == "gradient" and self.simulator.integration_scheme not in \
                IMPLICIT_SCHEMES:
            raise ConfigError(
                f"{where}: controller.law = gradient needs an implicit integrator (simulator."
                f"integration_scheme {' or '.join(IMPLICIT_SCHEMES)}; radau3 with max_step_size "
                "0.001 and use_error_control false recommended): the gradient law's adaptation "
                "is stiff and explicit fixed 1 ms steps diverge; "
                f"got {self.simulator.integration_scheme!r}")

    @property
    def route_length_m(self) -> float:
        return float(sum(seg.length_m for seg in self.route))


def scenarios_dir() -> Path:
    """Folder of the shipped scenarios: ``drake_cert/data/scenarios``."""
    return Path(str(resources.files("drake_cert.data"))) / "scenarios"


def scenario_path(name_or_path: str | Path) -> Path:
    """The file of a shipped scenario's name, or the given path."""
    text = str(name_or_path)
    if text in SHIPPED_SCENARIOS:
        return scenarios_dir() / f"{text}.yaml"
    path = Path(text)
    if not path.exists():
        raise ConfigError(f"scenario {text!r} is neither a file nor a shipped scenario "
                          f"({', '.join(SHIPPED_SCENARIOS)})")
    return path


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a shipped scenario by name or a scenario file; :class:`ConfigError` on any problem."""
    return load_typed(Scenario, scenario_path(name_or_path))
