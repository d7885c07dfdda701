"""From perception to a stiffness interval, a controller design and a speed command (DESIGN 3, 6).

Once per camera tick (``camera.rate_hz``, at :data:`OFFSET_FRACTION` (1/2) of the period, after
perception at 1/4) the block turns the latest :class:`PerceptionResult` into a :class:`Decision`.
It reads the scenario's ``perception`` block (``preset``, ``eps``, ``pipeline`` as the mode,
``task``), ``controller.dwell_time_s`` and ``camera.rate_hz``; the Diagram builder gives the
designs, the conditions table, the calibrations, the vehicle's stiffness scale and the labels.

- certified classification: the run-time interval at budget eps at the observed frame
  (:func:`runtime_classification_interval`: the narrowest contiguous label range T holding
  the top label with ``R_T > eps``; from a sequential decision,
  :func:`runtime_decision_interval`: the range it certified); its design is the table's for T.
- certified regression: ``[lower - beta, upper + beta]`` clipped to the envelope
  (:func:`runtime_interval`); its design is the narrowest design holding it whose friction
  bound is at most the least friction a stiffness in it can mean
  (:func:`drake_cert.synthesis.table.friction_lower_bound`); ties: the slower design.
- base mode (non-robust baseline): the raw label's own interval and design (regression: the
  narrowest design holding the raw point prediction, under the same friction rule).
- Abstain, a bad frame, a failed certificate or nothing certified: the family envelope and its
  design, never a nominal value. The state before the first tick is the envelope too.

The speed command is the design's safe speed, or 0 (stop) when the design has none.
Dwell time: a request for a design that holds every stiffness the current one holds (a wider
label range) applies at once. Any other change waits until ``dwell_time_s`` has passed since the
last switch; meanwhile the join of the two designs (the design of the hull of both ranges: a
widening, so at once) is in force with the speed ``min(join speed, requested speed)``; the
request applies at the first tick after the dwell if still requested, from the look point of
the tick that first requested it. A request that changes while held back restarts the hold's
look point; one no longer requested is dropped.
"""

import dataclasses
import math
from collections.abc import Sequence

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem

from drake_cert.certification.conformal import conformal_interval
from drake_cert.certification.intervals import (
    runtime_classification_interval,
    runtime_decision_interval,
    runtime_interval,
)
from drake_cert.config import ConditionsTable
from drake_cert.errors import ConfigError
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.synthesis.design_io import DesignTable
from drake_cert.synthesis.selection import join_design_indices
from drake_cert.synthesis.table import friction_lower_bound
from drake_cert.systems.perception_smoothing import PerceptionResult
from drake_cert.systems.scenario import CameraSettings, ControllerScenario, PerceptionSettings

STATUS_CODES = {"certified": 0, "envelope": 1, "stop": 2, "base": 3}
OFFSET_FRACTION = 0.5  # the update comes this share of a camera period after the frame


@dataclasses.dataclass(frozen=True)
class Decision:
    """The interval, design and speed command in force from the look point ``position_m``."""

    time_s: float  # time of the decision (s)
    position_m: float  # look point from which it applies (m); held requests: first request's
    interval: tuple[float, float]  # stiffness interval (N/rad) of the design in force
    c_hat: float  # the design's nominal stiffness (interval midpoint, N/rad)
    design_index: int  # index into the block's designs list
    speed_command_mps: float  # speed for the look point on (m/s); 0 = stop
    status: str  # "certified", "envelope" or "base"
    radius: float  # certified L2 radius of the interval (0 if none; regression: eps)
    labels: tuple[str, ...]  # label names of the design in force
    true_stiffness_n_per_rad: float  # truth of the seen segment (N/rad), for logs
    true_label_index: int = -1  # truth: condition of the seen segment
    tick: int = -1  # camera tick of the frame behind it
    requested_design_index: int = -1  # what this tick asked for (differs when held back)
    held: bool = False  # a request for another design is held back by the dwell time
    frame_ok: bool = False  # perception had a good frame
    error: str = ""  # perception's reason for a bad frame
    look_m: float = math.nan  # look point of the frame behind it (m); nan: none yet

    @property
    def status_code(self) -> int:
        """0 certified, 1 envelope, 2 stop (speed command 0), 3 base."""
        if self.speed_command_mps <= 0.0:
            return STATUS_CODES["stop"]
        return STATUS_CODES[self.status]

    @property
    def covers_truth(self) -> bool:
        """The interval holds the true stiffness of the seen segment."""
        lo, hi = self.interval
        return lo <= self.true_stiffness_n_per_rad <= hi


@dataclasses.dataclass(frozen=True)
class _DwellState:
    decision: Decision
    switched_at_s: float  # time of the last design switch (s)
    pending: tuple[int, float] | None  # held request: (design index, first look point)


def designs_for_preset(table: DesignTable, conditions: ConditionsTable,
                       preset: str) -> list[ControllerDesign]:
    """The table's designs of the preset's contiguous label ranges (envelope included), in
    :meth:`ConditionsTable.contiguous_ranges` order; :class:`ConfigError` if one is missing."""
    by_labels = {tuple(d.labels): d for d in table.designs}
    out = []
    for rng in conditions.contiguous_ranges(preset):
        if tuple(rng) not in by_labels:
            raise ConfigError(f"design table has no design for the label range {rng} of preset "
                              f"{preset!r}; synthesize it (drake-cert synthesize)")
        out.append(by_labels[tuple(rng)])
    return out


def _speed(design: ControllerDesign) -> float:
    return float(design.speed_mps) if design.has_safe_speed else 0.0


@dataclasses.dataclass(frozen=True)
class IntervalInputs:
    """What the Diagram builder gives :class:`CertifiedInterval` beyond the scenario's blocks:
    the calibrations, the vehicle's stiffness scale and the classifier's labels (see the
    block's Args)."""

    regression_beta: float = 0.0  # conformal beta of the regression interval (N/rad)
    conformal: object = None  # a RobustConformalCalibration, or None (safe-set interval)
    stiffness_scale: float = 1.0  # the vehicle's tire_stiffness_scale (dimensionless)
    label_names: Sequence[str] | None = None  # default: the preset's


@dataclasses.dataclass(frozen=True)
class IntervalSetup:
    """:class:`CertifiedInterval`'s checked settings and precomputed design lookups
    (:func:`interval_setup`); the block's attributes of the same names."""

    designs: list
    conditions: ConditionsTable
    preset: str
    eps: float  # L2 budget of the run-time interval
    mode: str  # "certified" or "base"
    task: str  # "classify" or "regress"
    beta: float  # regression beta (N/rad)
    conformal: object
    dwell_time_s: float  # least time between design switches (s)
    stiffness_scale: float
    family: tuple  # the preset's labels
    label_names: tuple
    envelope: tuple  # the family envelope (N/rad)
    by_labels: dict  # label range -> index of its (first) design
    envelope_index: int
    join: dict | None  # (i, j) -> the design of the hull of both label ranges
    period_s: float  # camera period (s)


def _check_interval_settings(p: PerceptionSettings, dwell_time_s: float,
                             inputs: IntervalInputs) -> None:
    """ConfigError for a mode, task, eps, dwell time, beta or stiffness scale out of range."""
    eps, mode, task = p.eps, p.pipeline, p.task
    stiffness_scale, regression_beta = inputs.stiffness_scale, inputs.regression_beta
    if mode not in ("certified", "base") or task not in ("classify", "regress"):
        raise ConfigError(f"mode {mode!r} / task {task!r}: expected certified|base and "
                          "classify|regress")
    if not (math.isfinite(eps) and eps >= 0):
        raise ConfigError(f"eps = {eps!r} must be a finite number >= 0")
    if not (math.isfinite(dwell_time_s) and dwell_time_s >= 0):
        raise ConfigError(f"dwell_time_s = {dwell_time_s!r} must be a finite number >= 0")
    if not regression_beta >= 0:
        raise ConfigError(f"regression_beta = {regression_beta!r} must be >= 0")
    if not (math.isfinite(stiffness_scale) and stiffness_scale > 0):
        raise ConfigError(f"stiffness_scale = {stiffness_scale!r} must be a positive number")


def interval_setup(designs: Sequence[ControllerDesign], conditions: ConditionsTable,
                   perception: PerceptionSettings | None = None,
                   controller: ControllerScenario | None = None,
                   camera: CameraSettings | None = None,
                   inputs: IntervalInputs | None = None) -> IntervalSetup:
    """Check :class:`CertifiedInterval`'s arguments and precompute its design lookups;
    ConfigError for a setting out of range or a missing envelope (or, for classification,
    label range) design."""
    p = perception if perception is not None else PerceptionSettings()
    controller = controller if controller is not None else ControllerScenario()
    camera = camera if camera is not None else CameraSettings()
    inputs = inputs if inputs is not None else IntervalInputs()
    _check_interval_settings(p, controller.dwell_time_s, inputs)
    preset, task, designs = p.preset, p.task, list(designs)
    family = tuple(conditions.preset(preset).labels)
    by_labels = {}
    for i, d in enumerate(designs):
        by_labels.setdefault(tuple(d.labels), i)
    if family not in by_labels:
        raise ConfigError(f"designs hold no envelope design (labels {list(family)})")
    if task == "classify":
        for rng in conditions.contiguous_ranges(preset):
            if tuple(rng) not in by_labels:
                raise ConfigError(f"designs hold no design for the label range {rng}")
    complete = all(tuple(rng) in by_labels for rng in conditions.contiguous_ranges(preset))
    # join[(i, j)]: the design of the hull of both label ranges (holds both); without
    # every range's design (a partial regression table) held requests keep the old design.
    join = (join_design_indices(designs, conditions, preset)
            if complete and all(d.labels for d in designs) else None)
    names = inputs.label_names
    return IntervalSetup(
        designs, conditions, preset, float(p.eps), p.pipeline, task,
        float(inputs.regression_beta), inputs.conformal, float(controller.dwell_time_s),
        float(inputs.stiffness_scale), family,
        tuple(names) if names is not None else family, conditions.envelope(preset), by_labels,
        by_labels[family], join, 1.0 / float(camera.rate_hz))


class CertifiedInterval(LeafSystem):
    """Input ``perception`` (abstract :class:`PerceptionResult`); abstract state and output
    ``decision`` (:class:`Decision`); vector outputs ``interval_n_per_rad`` (2, N/rad),
    ``design_index`` (1), ``speed_command_mps`` (1, m/s), ``certified_radius`` (1, L2 pixel
    units), ``status`` (1: 0 certified, 1 envelope, 2 stop / no safe speed, 3 base) and
    ``requested_design_index`` (1: the design the latest tick asked for, before the dwell time;
    the envelope's index where perception abstained or the frame was bad).

    Args:
        designs: the designs to choose from (e.g. :func:`designs_for_preset`); must hold the
            envelope design (labels = the preset's whole family) and, for classification,
            one design per contiguous label range.
        conditions: the conditions table (as scaled for the vehicle: the designs' intervals).
        perception: the scenario's perception block; reads ``preset``, ``eps`` (the L2 budget
            the run-time interval is certified against), ``pipeline`` ("certified" or "base")
            and ``task`` ("classify" or "regress").
        controller: the scenario's controller block; reads ``dwell_time_s`` (s), the least
            time between design switches.
        camera: the scenario's camera block; reads ``rate_hz``, the update's rate.
        regression_beta: conformal beta (N/rad) of the regression interval.
        conformal: a robust conformal calibration
            (:func:`drake_cert.certification.conformal.calibrate_robust_conformal`): when given,
            a certified classification interval is the robust conformal one (it holds the true
            stiffness with probability >= 1 - alpha_total without assuming g is right on the
            clean frame; DESIGN 3) instead of the safe-set interval; the design is that of its
            contiguous label range.
        stiffness_scale: the vehicle's ``tire_stiffness_scale`` (dimensionless): a regressor
            estimates the road's stiffness for the conditions table's reference tire, so its
            values (and beta) are multiplied by it before a design is chosen; ``conditions``
            must then be the table as scaled for this vehicle (the designs' intervals).
            Classification reads label ranges, which need no scaling.
        label_names: the classifier's label names (default: the preset's).

    ``regression_beta``, ``conformal``, ``stiffness_scale`` and ``label_names`` come in one
    :class:`IntervalInputs`; :func:`interval_setup` checks everything and precomputes the
    design lookups.
    """

    def __init__(self, designs: Sequence[ControllerDesign], conditions: ConditionsTable,
                 perception: PerceptionSettings | None = None,
                 controller: ControllerScenario | None = None,
                 camera: CameraSettings | None = None, inputs: IntervalInputs | None = None):
        super().__init__()
        s = interval_setup(designs, conditions, perception, controller, camera, inputs)
        self.designs, self.conditions, self.preset = s.designs, s.conditions, s.preset
        self.eps, self.mode, self.task, self.beta = s.eps, s.mode, s.task, s.beta
        self.conformal, self.dwell_time_s = s.conformal, s.dwell_time_s
        self.stiffness_scale, self.family, self.label_names = (s.stiffness_scale, s.family,
                                                               s.label_names)
        self.envelope, self.envelope_index = s.envelope, s.envelope_index
        self._by_labels, self._join = s.by_labels, s.join
        self.offset_s = OFFSET_FRACTION * s.period_s
        initial = self.initial_state()
        self.DeclareAbstractInputPort("perception", AbstractValue.Make(
            PerceptionResult.no_frame(s.mode, s.task)))
        state_index = self.DeclareAbstractState(AbstractValue.Make(initial))
        self.DeclarePeriodicUnrestrictedUpdateEvent(s.period_s, self.offset_s, self._update)
        state = {self.abstract_state_ticket(state_index)}
        self.DeclareAbstractOutputPort("decision", lambda: AbstractValue.Make(initial.decision),
                                       self._calc_decision, prerequisites_of_calc=state)
        for name, size, calc in (("interval_n_per_rad", 2, self._calc_interval),
                                 ("design_index", 1, self._calc_index),
                                 ("speed_command_mps", 1, self._calc_speed),
                                 ("certified_radius", 1, self._calc_radius),
                                 ("status", 1, self._calc_status),
                                 ("requested_design_index", 1, self._calc_requested)):
            self.DeclareVectorOutputPort(name, size, calc, prerequisites_of_calc=state)

    # ------------------------------------------------------------------ the decision
    def _decision(self, p: PerceptionResult, index: int, status: str, radius: float,
                  interval: tuple[float, float] | None = None) -> Decision:
        d = self.designs[index]
        return Decision(time_s=float(p.time_s), position_m=float(p.position_m),
                        interval=tuple(interval) if interval is not None else tuple(d.interval),
                        c_hat=float(d.nominal_stiffness_n_per_rad), design_index=index,
                        speed_command_mps=_speed(d), status=status, radius=float(radius),
                        labels=tuple(d.labels), true_stiffness_n_per_rad=p.stiffness_n_per_rad,
                        true_label_index=p.label_index, tick=p.tick,
                        requested_design_index=index, frame_ok=p.frame_ok, error=p.error,
                        look_m=float(p.position_m))

    def envelope_decision(self, p: PerceptionResult) -> Decision:
        """The family envelope and its design (abstain, bad frame, nothing certified)."""
        return self._decision(p, self.envelope_index, "envelope", 0.0, self.envelope)

    def request(self, p: PerceptionResult) -> Decision:
        """What this perception result asks for, before the dwell time (pure)."""
        if not p.frame_ok:
            return self.envelope_decision(p)
        if self.task == "classify":
            if self.mode == "base":
                if p.base_label is None or not 0 <= p.base_label < len(self.label_names):
                    return self.envelope_decision(p)
                index = self._by_labels.get((self.label_names[p.base_label],))
                return (self.envelope_decision(p) if index is None
                        else self._decision(p, index, "base", 0.0))
            if self.conformal is not None and (p.conformal is not None
                                               or p.certificate is not None):
                return self._conformal_decision(p)
            if p.decision is not None:  # sequential
                rt = runtime_decision_interval(p.decision, self.conditions, self.preset,
                                               self.label_names)
                if not rt.certified or tuple(rt.labels) not in self._by_labels:
                    return self.envelope_decision(p)
                return self._decision(p, self._by_labels[tuple(rt.labels)], "certified",
                                      rt.radius, rt.interval)
            if p.certificate is None or p.certificate.abstained:
                return self.envelope_decision(p)
            rt = runtime_classification_interval(p.certificate, self.conditions, self.preset,
                                                 self.eps, self.label_names)
            if not rt.certified:
                return self.envelope_decision(p)
            return self._decision(p, self._by_labels[tuple(rt.labels)], "certified", rt.radius,
                                  rt.interval)
        if self.mode == "base":
            v = p.base_value_n_per_rad
            if v is None or not math.isfinite(v):
                return self.envelope_decision(p)
            v *= self.stiffness_scale  # the reference tire's stiffness -> this vehicle's
            index = self._narrowest_holding((v, v))
            return (self.envelope_decision(p) if index is None
                    else self._decision(p, index, "base", 0.0))
        if p.median is not None:  # sequential: the candidate's ends bound the median
            if not p.median.certified:
                return self.envelope_decision(p)
            lower, upper = p.median.interval  # an open end: the design reaches the envelope's
            lower = lower if math.isfinite(lower) else self.envelope[0] / self.stiffness_scale
            upper = upper if math.isfinite(upper) else self.envelope[1] / self.stiffness_scale
        elif p.regression is None:
            return self.envelope_decision(p)
        else:
            _, lower, upper = p.regression
        k = self.stiffness_scale  # the reference tire's stiffness -> this vehicle's
        interval = runtime_interval(k * lower, k * upper, k * self.beta, self.envelope)
        if interval == tuple(float(x) for x in self.envelope):
            return self.envelope_decision(p)
        index = self._narrowest_holding(interval)
        if index is None or index == self.envelope_index:
            return self.envelope_decision(p)
        return self._decision(p, index, "certified", self.eps, interval)

    def _conformal_decision(self, p: PerceptionResult) -> Decision:
        """The robust conformal interval at budget eps from the certificate's own votes."""
        votes = p.conformal if p.conformal is not None else p.certificate
        ci = conformal_interval(votes, self.conformal, self.conditions, self.preset,
                                self.eps, self.label_names)
        if tuple(ci.labels) == self.family:
            return self.envelope_decision(p)
        return self._decision(p, self._by_labels[tuple(ci.labels)], "certified", self.eps,
                              ci.interval)

    def _narrowest_holding(self, interval: tuple[float, float]) -> int | None:
        """Narrowest design holding ``interval`` whose friction bound is sound for it."""
        lo, hi = interval
        mu = friction_lower_bound(self.conditions, self.preset, (lo, hi))
        best, key = None, None
        for i, d in enumerate(self.designs):
            if not (d.stiffness_lo_n_per_rad <= lo and hi <= d.stiffness_hi_n_per_rad):
                continue
            if d.friction_mu_lo > mu + 1e-12:
                continue
            k = (d.stiffness_hi_n_per_rad - d.stiffness_lo_n_per_rad, _speed(d), i)
            if key is None or k < key:
                best, key = i, k
        return best

    # ------------------------------------------------------------------ the dwell time
    def initial_state(self) -> _DwellState:
        """The envelope decision, no switch yet (the first switch is free)."""
        p = PerceptionResult.no_frame(self.mode, self.task)
        return _DwellState(self.envelope_decision(p), -math.inf, None)

    def step(self, state: _DwellState, p: PerceptionResult, time_s: float) -> _DwellState:
        """Apply the request of ``p`` at time ``time_s`` (s) under the dwell time (pure)."""
        t = float(time_s)
        req = dataclasses.replace(self.request(p), time_s=t)
        cur = state.decision
        if req.design_index == cur.design_index:
            return _DwellState(req, state.switched_at_s, None)
        join = (self._join[(cur.design_index, req.design_index)] if self._join is not None
                else cur.design_index)
        if join == req.design_index:  # req holds every stiffness cur holds: at once
            return _DwellState(req, t, None)
        if t - state.switched_at_s >= self.dwell_time_s - 1e-9:
            position = (state.pending[1] if state.pending is not None
                        and state.pending[0] == req.design_index else req.position_m)
            return _DwellState(dataclasses.replace(req, position_m=position), t, None)
        pending = (state.pending if state.pending is not None
                   and state.pending[0] == req.design_index
                   else (req.design_index, req.position_m))
        in_force = cur if join == cur.design_index else self._decision(p, join, req.status,
                                                                         req.radius)
        held = dataclasses.replace(
            in_force, time_s=t, position_m=pending[1],
            speed_command_mps=min(_speed(self.designs[join]), req.speed_command_mps),
            true_stiffness_n_per_rad=req.true_stiffness_n_per_rad,
            true_label_index=req.true_label_index, tick=req.tick,
            requested_design_index=req.design_index, held=True, frame_ok=req.frame_ok,
            error=req.error, look_m=req.look_m)
        switched = state.switched_at_s if join == cur.design_index else t
        return _DwellState(held, switched, pending)

    # ------------------------------------------------------------------ Drake plumbing
    def _update(self, context, state) -> EventStatus:
        p = self.get_input_port(0).Eval(context)
        new = self.step(context.get_abstract_state(0).get_value(), p, context.get_time())
        state.get_mutable_abstract_state(0).set_value(new)
        return EventStatus.Succeeded()

    def _now(self, context) -> Decision:
        return context.get_abstract_state(0).get_value().decision

    def _calc_decision(self, context, output: AbstractValue) -> None:
        output.set_value(self._now(context))

    def _calc_interval(self, context, output: BasicVector) -> None:
        output.SetFromVector(list(self._now(context).interval))

    def _calc_index(self, context, output: BasicVector) -> None:
        output.SetAtIndex(0, float(self._now(context).design_index))

    def _calc_speed(self, context, output: BasicVector) -> None:
        output.SetAtIndex(0, self._now(context).speed_command_mps)

    def _calc_radius(self, context, output: BasicVector) -> None:
        output.SetAtIndex(0, self._now(context).radius)

    def _calc_status(self, context, output: BasicVector) -> None:
        output.SetAtIndex(0, float(self._now(context).status_code))

    def _calc_requested(self, context, output: BasicVector) -> None:
        output.SetAtIndex(0, float(self._now(context).requested_design_index))
