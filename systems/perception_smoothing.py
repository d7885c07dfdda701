"""Perception with its certificate, once per camera tick (DESIGN 3 and 6).

A periodic unrestricted update at ``camera.rate_hz``, at :data:`OFFSET_FRACTION` (1/4) of the
period after the camera's tick, reads the ``frame`` input and holds a :class:`PerceptionResult`
(abstract state, output ``perception``); output ``samples`` (1): the noisy samples drawn for it.
It reads the scenario's ``perception`` block (:class:`PerceptionSettings`: ``pipeline`` as the
mode, ``task``, ``sigma``, ``eps``, ``n0``, ``n``, ``alpha``, ``batch_size`` and
``resolved_decision``) and ``camera`` block (``rate_hz``, ``frame_size``):

- certified classification, ``sequential``: the decision at budget eps
  (:meth:`SmoothedClassifier.decide`) over the candidate label ``ranges`` (those holding the
  top label of n0 selection samples; all at once when n0 = 0), up to n samples; with a robust
  ``conformal`` calibration, the conformal label set at eps, sampled until its range is decided
  (:func:`~drake_cert.certification.conformal.sequential_label_set`).
- certified classification, ``fixed``: CERTIFY at the observed frame (n0 selection, n
  estimation samples, joint Clopper-Pearson bounds at ``alpha``), from which the run-time
  interval of any label range is read off (``drake_cert.systems.certified_interval``).
- certified regression: median smoothing's ``(median, lower, upper)`` at budget eps
  (:meth:`MedianSmoothedRegressor.certify_interval`), or, sequential over given candidate
  intervals (``ranges``, N/rad), the median's interval decided.
- ``pipeline: base``: the raw prediction of the model f (label, or stiffness in N/rad).

A frame that is not a finite float [3, H, W] image in [0, 1] of ``frame_size`` gives
``frame_ok = False`` and the reason in ``error`` (never an exception, never a prediction).
The certificate of tick k draws its selection samples from the stream ``selection`` (k) of the
seed and its estimation samples from ``estimation`` (k) (:mod:`drake_cert.certification.seeds`).
Cost per tick: n0 + n forward passes with a fixed-n certificate; a sequential decision draws
between a few dozen and n (``PerceptionResult.samples``).
"""

import dataclasses
import math

import torch
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import EventStatus, LeafSystem
from scipy.stats import norm

from drake_cert.certification.alpha_spending import AlphaSpending
from drake_cert.certification.classifier import (
    ClassCertificate,
    SequentialDecision,
    SmoothedClassifier,
    check_enough_samples,
)
from drake_cert.certification.conformal import (
    ConformalDecision,
    LabelSetStopping,
    RobustConformalCalibration,
    look_batches,
    sequential_label_set,
)
from drake_cert.certification.regressor import (
    MedianDecision,
    MedianSmoothedRegressor,
    point_value,
)
from drake_cert.certification.sampler import check_frame
from drake_cert.certification.seeds import Purpose, child_seed
from drake_cert.certification.statistics import (
    SequentialOptions,
    look_plan,
    percentile_bound_indices,
)
from drake_cert.errors import CertificationError, ConfigError
from drake_cert.systems.camera import CameraFrame
from drake_cert.systems.scenario import CameraSettings, PerceptionSettings
from drake_cert.threads import available_cores

MODES = ("certified", "base")
TASKS = ("classify", "regress")
DECISIONS = ("sequential", "fixed")
OFFSET_FRACTION = 0.25  # the update comes this share of a camera period after the frame
# Samples of the next tick's conformal set whose noise is drawn ahead (its looks up to here:
# 64 + 64 + 128 at the default looks, enough for about 9 frames in 10 without attack).
DRAW_AHEAD_SAMPLES = 256


@dataclasses.dataclass(frozen=True)
class ModelRuntime:
    """Where and how the perception model runs: the machine's choice, not the scenario's."""

    device: str = "cpu"  # "cpu" or a CUDA device (the frames come from the CPU)
    compile: bool = False  # compile the model for the smoothing (see SmoothedClassifier)


@dataclasses.dataclass(frozen=True)
class PerceptionResult:
    """What perception saw at one tick; truth fields are copied from the frame for logs."""

    time_s: float  # time of the perception update (s)
    tick: int  # camera tick of the frame (-1: no frame yet)
    position_m: float  # look-ahead point of the frame (m)
    frame_ok: bool  # False: bad frame (NaN, wrong shape, outside [0, 1]) or failed certificate
    error: str  # why frame_ok is False ("" otherwise)
    mode: str  # "certified" or "base"
    task: str  # "classify" or "regress"
    certificate: ClassCertificate | None = None  # certified classification (fixed n)
    decision: SequentialDecision | None = None  # certified classification (sequential)
    conformal: ConformalDecision | None = None  # robust conformal label set (sequential)
    median: MedianDecision | None = None  # certified regression (sequential)
    samples: int = 0  # noisy samples drawn at this tick (selection included)
    base_label: int | None = None  # raw label of f (classification, both modes)
    regression: tuple[float, float, float] | None = None  # certified (median, lower, upper)
    base_value_n_per_rad: float | None = None  # raw stiffness prediction of f (base regress)
    label_index: int = -1  # truth: condition of the seen segment
    stiffness_n_per_rad: float = math.nan  # truth: stiffness of the seen segment (N/rad)
    friction_mu: float = math.nan  # truth: friction of the seen segment
    attack: str = "none"  # what the attacker did to the frame

    @staticmethod
    def no_frame(mode: str, task: str) -> "PerceptionResult":
        """The state before the first tick: no frame, handled like a bad frame."""
        return PerceptionResult(time_s=0.0, tick=-1, position_m=0.0, frame_ok=False,
                                error="no frame yet", mode=mode, task=task)


def check_decision_budget(n: int, alpha: float, eps: float, sigma: float, ranges) -> None:
    """:class:`ConfigError` when n samples can never certify radius eps in a sequential
    decision over these candidate ranges (None: one label), so that such a setting fails at
    once instead of abstaining on every tick."""
    listed = list(ranges) if ranges is not None else [(0,)]
    tests = len({t for c in listed for t in c}) + sum(len(c) > 1 for c in listed)
    try:
        look_plan(int(n), float(alpha), tests, threshold=float(norm.cdf(eps / sigma)))
    except CertificationError as e:
        raise ConfigError(f"perception: {e}") from None


def _holding(ranges):
    """The ranges that hold a label, as a function of the label."""
    return lambda label: [c for c in ranges if label in c]


@dataclasses.dataclass(frozen=True)
class PerceptionInputs:
    """What the Diagram builder gives :class:`PerceptionSmoothing` beyond the scenario's
    blocks: the labels, the candidate ranges, the alpha spending and the conformal
    calibration (see the block's Args)."""

    label_names: list[str] | tuple[str, ...] = ()  # the classifier's labels, grippiest first
    ranges: object = None  # candidate label ranges / median intervals (N/rad), or None
    alpha_spending: AlphaSpending | None = None  # None: alpha per decision
    conformal: RobustConformalCalibration | None = None


@dataclasses.dataclass(frozen=True)
class SmoothingSetup:
    """:class:`PerceptionSmoothing`'s checked settings and its smoothed model
    (:func:`smoothing_setup`); the block's attributes of the same names."""

    model: torch.nn.Module  # in eval mode
    device: torch.device
    mode: str
    task: str
    decision: str  # "sequential" or "fixed" (regression without ranges: fixed)
    ranges: object
    n0: int
    n: int
    alpha_spending: AlphaSpending | None
    conformal: RobustConformalCalibration | None
    alpha: float  # the largest alpha a decision gets
    batch_size: int
    seed: int
    eps: float  # L2 budget (pixel units)
    label_names: tuple[str, ...]
    frame_shape: tuple[int, int, int]
    period_s: float  # camera period (s)
    smooth: object  # SmoothedClassifier / MedianSmoothedRegressor, or None in base mode
    # samples of the next tick's noise drawn ahead after a conformal set (0: none)
    draw_ahead_samples: int = 0


def _check_perception_modes(p: PerceptionSettings, rate_hz: float) -> None:
    """ConfigError for a mode, task, decision or camera rate out of range."""
    mode, task, decision = p.pipeline, p.task, p.resolved_decision
    if mode not in MODES:
        raise ConfigError(f"perception mode {mode!r}; expected one of {', '.join(MODES)}")
    if task not in TASKS:
        raise ConfigError(f"perception task {task!r}; expected one of {', '.join(TASKS)}")
    if decision not in DECISIONS:
        raise ConfigError(f"perception decision {decision!r}; expected one of "
                          f"{', '.join(DECISIONS)}")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ConfigError(f"perception: rate_hz = {rate_hz!r} must be positive")


def _smoothed_model(model, p: PerceptionSettings, s: dict, runtime: ModelRuntime):
    """The certified mode's smoothed model, after the checks that n can certify (``s``: the
    setup's fields so far); None in base mode."""
    if p.pipeline != "certified":
        return None
    sigma, device = p.sigma, runtime.device
    if p.task == "classify":
        if len(s["label_names"]) < 2:
            raise ConfigError("perception: classification needs label_names (>= 2)")
        if s["decision"] == "fixed":
            check_enough_samples(s["n"], s["alpha"], len(s["label_names"]))
        elif s["conformal"] is None:
            check_decision_budget(s["n"], s["alpha"], s["eps"], sigma, s["ranges"])
        return SmoothedClassifier(model, len(s["label_names"]), sigma,
                                  compile=runtime.compile, device=device)
    if s["decision"] == "fixed":
        percentile_bound_indices(s["n"], s["eps"], sigma, s["alpha"])
    return MedianSmoothedRegressor(model, sigma, compile=runtime.compile, device=device)


def smoothing_setup(model: torch.nn.Module, perception: PerceptionSettings | None = None,
                    camera: CameraSettings | None = None, seed: int = 0,
                    inputs: PerceptionInputs | None = None,
                    runtime: ModelRuntime | None = None) -> SmoothingSetup:
    """Check :class:`PerceptionSmoothing`'s arguments (ConfigError naming the first bad one,
    including an n that can never certify) and build its smoothed model."""
    p = perception if perception is not None else PerceptionSettings()
    camera = camera if camera is not None else CameraSettings()
    runtime = runtime if runtime is not None else ModelRuntime()
    inputs = inputs if inputs is not None else PerceptionInputs()
    _check_perception_modes(p, camera.rate_hz)
    model = model.eval()
    spending, ranges = inputs.alpha_spending, inputs.ranges
    s = dict(
        model=model, device=torch.device(runtime.device), mode=p.pipeline, task=p.task,
        # regression decides sequentially only over given candidate intervals (``ranges``)
        decision=(p.resolved_decision if p.task == "classify" or ranges is not None
                  else "fixed"),
        ranges=ranges, n0=int(p.n0), n=int(p.n), alpha_spending=spending,
        conformal=inputs.conformal,
        # the largest alpha a decision gets (the checks: n must reach it)
        alpha=float(p.alpha) if spending is None else spending.planned_alpha,
        batch_size=int(p.batch_size), seed=int(seed), eps=float(p.eps),
        label_names=tuple(inputs.label_names),
        frame_shape=(3, int(camera.frame_size), int(camera.frame_size)),
        period_s=1.0 / float(camera.rate_hz))
    return SmoothingSetup(**s, smooth=_smoothed_model(model, p, s, runtime),
                          draw_ahead_samples=_draw_ahead_samples(p, s))


def _draw_ahead_samples(p: PerceptionSettings, s: dict) -> int:
    """How many of a tick's samples to draw the noise of ahead, while the simulation runs:
    :data:`DRAW_AHEAD_SAMPLES` for a conformal set on a second core, else 0 (on one core the
    work would only compete with the simulation)."""
    conformal_set = p.pipeline == "certified" and p.task == "classify" \
        and s["decision"] == "sequential" and s["conformal"] is not None
    return DRAW_AHEAD_SAMPLES if conformal_set and available_cores() >= 2 else 0


class PerceptionSmoothing(LeafSystem):
    """Input ``frame`` (abstract :class:`CameraFrame`); abstract state and output
    ``perception`` (:class:`PerceptionResult`); output ``samples`` (1): noisy samples drawn
    for the latest frame.

    Args:
        model: classifier (logits over ``label_names``) or stiffness regressor, eval mode.
        perception: the scenario's perception block; reads ``pipeline`` ("certified":
            smoothed, certificate; "base": raw f), ``task``, ``sigma`` (pixel units; unused in
            base mode), ``eps`` (L2 budget of the decision and the median bounds), CERTIFY's
            ``n0``, ``n``, ``alpha``, ``batch_size`` (n0 unused for regression) and
            ``resolved_decision`` ("sequential" or "fixed"; regression: sequential only with
            ``ranges``).
        camera: the scenario's camera block; reads ``rate_hz`` (the update's rate) and
            ``frame_size`` (expected frames are [3, frame_size, frame_size]).
        seed: scenario seed (streams ``selection`` and ``estimation`` per tick).
        label_names: the classifier's labels (grippiest first); their count is K.
        ranges: sequential only: the candidate label ranges, most preferred first
            (:func:`drake_cert.certification.intervals.candidate_ranges`); n0 > 0 keeps those
            holding the selection's top label; None: the top label alone. Regression: the
            candidate intervals of the median (N/rad,
            :func:`drake_cert.certification.intervals.median_candidates`), required.
        alpha_spending: an :class:`~drake_cert.certification.alpha_spending.AlphaSpending`:
            the decision of camera tick k is taken at ``alpha_spending.alpha(k)`` (every
            decision of the drive holds at once with probability >= 1 - its total) instead of
            ``alpha`` each; None: ``alpha`` per decision.
        conformal: a robust conformal calibration: with ``decision="sequential"`` the tick's
            result is the conformal label set at budget ``eps``, decided sequentially
            (:func:`~drake_cert.certification.conformal.sequential_label_set`, at most n
            samples); with ``"fixed"`` the certificate's votes give it downstream.
        runtime: where ``model`` runs and whether it is compiled (:class:`ModelRuntime`).

    ``label_names``, ``ranges``, ``alpha_spending`` and ``conformal`` come in one
    :class:`PerceptionInputs`; :func:`smoothing_setup` checks everything and builds the
    smoothed model. Two attributes may be changed before a drive, neither changing what is
    certified: ``label_set_stopping`` (when a conformal set stops sampling,
    :class:`~drake_cert.certification.conformal.LabelSetStopping`) and ``draw_ahead_samples``
    (the next tick's samples whose noise is drawn while the simulation runs; 0: none).
    """

    def __init__(self, model: torch.nn.Module, perception: PerceptionSettings | None = None,
                 camera: CameraSettings | None = None, *, seed: int = 0,
                 inputs: PerceptionInputs | None = None, runtime: ModelRuntime | None = None):
        super().__init__()
        s = smoothing_setup(model, perception, camera, seed, inputs, runtime)
        self.model, self.device, self.mode, self.task = s.model, s.device, s.mode, s.task
        self.decision, self.ranges, self.n0, self.n = s.decision, s.ranges, s.n0, s.n
        self.alpha_spending, self.conformal, self.alpha = s.alpha_spending, s.conformal, s.alpha
        self.batch_size, self.seed, self.eps = s.batch_size, s.seed, s.eps
        self.label_names, self.frame_shape = s.label_names, s.frame_shape
        self.period_s = s.period_s
        self.offset_s = OFFSET_FRACTION * self.period_s
        self._smooth, self.draw_ahead_samples = s.smooth, s.draw_ahead_samples  # 0: none
        self.label_set_stopping = LabelSetStopping()  # when a conformal set stops sampling
        initial = PerceptionResult.no_frame(s.mode, s.task)
        self._in = self.DeclareAbstractInputPort(
            "frame", AbstractValue.Make(CameraFrame.placeholder(s.frame_shape[1])))
        state_index = self.DeclareAbstractState(AbstractValue.Make(initial))
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.period_s, self.offset_s, self._update)
        state = {self.abstract_state_ticket(state_index)}
        self.DeclareAbstractOutputPort("perception", lambda: AbstractValue.Make(initial),
                                       self._calc_perception, prerequisites_of_calc=state)
        self.DeclareVectorOutputPort("samples", 1, self._calc_samples,
                                     prerequisites_of_calc=state)

    def frame_problem(self, image) -> str:
        """Why a frame cannot be perceived ("" when it can)."""
        if not isinstance(image, torch.Tensor):
            return f"frame is a {type(image).__name__}, not a tensor"
        if tuple(image.shape) != self.frame_shape:
            return f"frame has shape {list(image.shape)}; expected {list(self.frame_shape)}"
        try:
            check_frame(image)
        except CertificationError as e:
            return str(e)
        return ""

    def perceive(self, frame: CameraFrame, time_s: float) -> PerceptionResult:
        """The result for one frame (pure: same frame and tick, same result)."""
        base = PerceptionResult(time_s=float(time_s), tick=frame.tick,
                                position_m=frame.position_m, frame_ok=True, error="",
                                mode=self.mode, task=self.task, label_index=frame.label_index,
                                stiffness_n_per_rad=frame.stiffness_n_per_rad,
                                friction_mu=frame.friction_mu, attack=frame.attack)
        problem = self.frame_problem(frame.image)
        if problem:
            return dataclasses.replace(base, frame_ok=False, error=problem)
        x = frame.image.float()
        alpha = self.alpha_of(frame.tick)
        seed = child_seed(self.seed, Purpose.ESTIMATION, frame.tick)
        selection_seed = child_seed(self.seed, Purpose.SELECTION, frame.tick)
        try:
            if self.task == "classify":
                with torch.inference_mode():
                    base_label = int(self.model(x[None].to(self.device)).argmax(dim=1)[0])
                if self.mode == "base":
                    return dataclasses.replace(base, base_label=base_label)
                if self.decision == "sequential" and self.conformal is not None:
                    c = sequential_label_set(self._smooth, x, self.conformal, self.eps, self.n,
                                             self.batch_size, seed=seed,
                                             stopping=self.label_set_stopping)
                    self._draw_ahead(frame.tick + 1)
                    return dataclasses.replace(base, base_label=base_label, conformal=c,
                                               samples=c.samples)
                if self.decision == "sequential":
                    ranges = self.ranges
                    if self.n0 and ranges is not None:  # those holding the selected label
                        ranges = _holding(ranges)
                    d = self._smooth.decide(
                        x, self.eps, alpha, self.n, self.batch_size, ranges,
                        seed=seed, options=SequentialOptions(selection_n=self.n0,
                                                             selection_seed=selection_seed))
                    return dataclasses.replace(base, base_label=base_label, decision=d,
                                               samples=d.samples)
                cert = self._smooth.certify(x, self.n0, self.n, alpha, self.batch_size,
                                            seed=seed, selection_seed=selection_seed)
                return dataclasses.replace(base, base_label=base_label, certificate=cert,
                                           samples=self.n0 + self.n)
            if self.mode == "base":
                with torch.inference_mode():
                    value = float(point_value(self.model(x[None].to(self.device)))[0])
                if not math.isfinite(value):
                    raise CertificationError("regressor returned a non-finite stiffness")
                return dataclasses.replace(base, base_value_n_per_rad=value)
            if self.decision == "sequential":
                ranges = list(self.ranges)
                m = self._smooth.decide(x, self.eps, alpha, self.n, self.batch_size,
                                        lambda v: ranges, seed=seed)
                return dataclasses.replace(base, median=m, samples=m.samples)
            median, lower, upper = self._smooth.certify_interval(x, self.eps, self.n, alpha,
                                                                 self.batch_size, seed=seed)
            return dataclasses.replace(base, regression=(median, lower, upper), samples=self.n)
        except CertificationError as e:
            return dataclasses.replace(base, frame_ok=False, error=str(e))

    def _draw_ahead(self, tick: int) -> None:
        """Start drawing the noise of camera tick ``tick``'s looks up to
        ``draw_ahead_samples`` on a worker thread, while the simulation runs on one core until
        that tick (the same numbers, earlier: DESIGN 3.8)."""
        if self.draw_ahead_samples:
            batches = look_batches(self.n, self.batch_size, self.draw_ahead_samples,
                                   self.label_set_stopping.first_look)
            self._smooth.draw_ahead(child_seed(self.seed, Purpose.ESTIMATION, tick),
                                    self.frame_shape, batches)

    def alpha_of(self, tick: int) -> float:
        """The failure probability of the decision on camera tick ``tick``."""
        if self.alpha_spending is None:
            return self.alpha
        return self.alpha_spending.alpha(max(0, int(tick)))

    def _update(self, context, state) -> EventStatus:
        result = self.perceive(self._in.Eval(context), context.get_time())
        state.get_mutable_abstract_state(0).set_value(result)
        return EventStatus.Succeeded()

    def _calc_perception(self, context, output: AbstractValue) -> None:
        output.set_value(context.get_abstract_state(0).get_value())

    def _calc_samples(self, context, output) -> None:
        output.SetAtIndex(0, float(context.get_abstract_state(0).get_value().samples))
