"""The L1 adaptive controller that switches designs and follows the speed at run time (DESIGN 5.6).

Inputs: ``state`` s = [e1, e1dot, e2, e2dot] (m, m/s, rad, rad/s), ``curvature_per_m`` kappa
(1/m), ``speed_mps`` V (m/s), ``design_index`` (into ``designs``; a float holding an integer);
with ``curvature_preview=True`` also ``curvature_preview_per_m`` kappa_p (1/m), at which u_ff is
taken in command and predictor while ``g_hat V kappa`` keeps kappa (DESIGN 4.2). Outputs:
``steering_rad`` u (rad, UNSATURATED), ``active_design_index``, ``scheduled_speed_mps`` (the grid
speed whose parameters are in use, m/s). Discrete state (period T_s =
``settings.controller.sample_period_s``, offset 0): ``[s_hat (4), u_ad, active design, speed
grid index, stopped (0/1), held steering (rad)]``.

``law="piecewise_constant"`` (default): the law of :mod:`drake_cert.systems.l1_law` (DESIGN 4),
its parameters moving. At each sample t_k, inputs read at t_k: (1) a requested design becomes
active (dwell is enforced upstream, in the certified-interval block) with the steering kept
and the estimate carried over (:func:`~drake_cert.systems.l1_law.piecewise_constant_hand_over`;
from a stop, s_hat restarts at the measured s); (2) V is clipped to [speed_min_mps, the design's
``gain_speed_max_mps``] and rounded to ``speed_step_mps``, the parameters of each (design, grid
point) computed once and cached; (3) ``piecewise_constant_update`` advances (s_hat, u_ad); the
output is ``steering_command`` with these parameters until the next sample. Below
``speed_min_mps`` (the stop speed) nothing adapts and the steering is held from that sample.

The gradient law (``law="gradient"``, :class:`SwitchingGradientL1Law`): the continuous law on
x = [q_hat (4), w_hat, theta_hat (4), sigma_hat, u_ad] (discrete slots 0-4 unused), same ports,
sample and stop rules; at a switch the steering is kept (bumpless) and the estimates go into the
new sets (:meth:`SwitchingGradientL1Law.hand_over`; why and measured: DESIGN 5.6). It DIVERGES
under fixed-step RK2 at 1 ms: simulate with Radau3, fixed 1 ms steps (``integration_scheme=
"radau3"``, ``max_step_size=0.001``, ``use_error_control=False``; DESIGN 4.4).

``fast=True`` (default): the law's exact affine rows, :func:`gradient_derivatives_fast`;
``fast=False``: the ``l1_law`` functions, the readable reference (tests: both agree).
"""

import dataclasses
import math

import numpy as np
import pydrake.symbolic as sym
from pydrake.systems.framework import BasicVector, Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import Multiplexer, SymbolicVectorSystem

from drake_cert.config import Settings, VehicleParams
from drake_cert.errors import ConfigError
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.systems import l1_law
from drake_cert.systems.l1_law import L1Parameters

S_HAT, U_AD, DESIGN, GRID, STOPPED, HELD = slice(0, 4), 4, 5, 6, 7, 8
STATE_SIZE = 9


@dataclasses.dataclass(frozen=True)
class ScheduledLaw:
    """The law at one (design, grid speed): parameters and their affine matrices.

    ``next = update @ [s_hat, u_ad, s, kappa, 1]`` gives (s_hat, u_ad) at the next sample,
    ``u = command @ [u_ad, s, kappa, 1]`` the steering; with the road preview ``kappa`` is
    the pair ``[kappa, kappa_p]`` in both (curvature under the car, preview).
    """

    parameters: L1Parameters
    update: np.ndarray  # (5, 11), (5, 12) with the preview
    command: np.ndarray  # (7,), (8,) with the preview


def _affine_rows(function, n_inputs: int) -> np.ndarray:
    """``[M | c]`` of an affine ``function(v) = M v + c`` from n + 1 evaluations."""
    c = np.asarray(function(np.zeros(n_inputs)), float)
    columns = [np.asarray(function(e), float) - c for e in np.eye(n_inputs)]
    return np.column_stack([*columns, c])


def scheduled_law(parameters: L1Parameters, curvature_preview: bool = False) -> ScheduledLaw:
    """The :class:`ScheduledLaw` of the piecewise-constant law at these parameters
    (``curvature_preview``: u_ff at a second curvature input, the road preview)."""
    p = parameters
    n = 2 if curvature_preview else 1  # curvature inputs: kappa (, kappa_p)

    def preview(v, i):
        return v[i + 1] if curvature_preview else None

    def update(v):
        s_hat, u_ad = l1_law.piecewise_constant_update(p, v[0:4], v[4], v[5:9], v[9],
                                                       preview(v, 9))
        return np.append(s_hat, u_ad)

    def command(v):
        return [l1_law.steering_command(p, v[1:5], v[0], v[5], preview(v, 5))]

    return ScheduledLaw(p, _affine_rows(update, 9 + n), _affine_rows(command, 5 + n)[0])


@dataclasses.dataclass(frozen=True)
class SwitchingOptions:
    """How the switching controller runs (module docstring); the vehicle, designs and
    settings are given beside it."""

    law: str | None = None  # "piecewise_constant" or "gradient"; None: the leaf's own law
    initial_design_index: int = 0  # active design before the first sample (into designs)
    initial_speed_mps: float | None = None  # speed for the first schedule (None: the design's)
    speed_step_mps: float = 0.1  # grid step of the speed schedule (m/s)
    fast: bool = True  # steering from the cached row in C++ / the affine-row derivative
    curvature_preview: bool = False  # the input curvature_preview_per_m (u_ff at kappa_p)


def check_switching_options(designs: list[ControllerDesign], options: SwitchingOptions,
                            leaf_law: str) -> SwitchingOptions:
    """``options`` with ``law`` resolved (None: ``leaf_law``), checked for the leaf that runs
    ``leaf_law``: ConfigError for an unknown law or one the leaf does not run, no designs, an
    initial design out of range or a speed step that is not positive."""
    law = leaf_law if options.law is None else options.law
    if law not in l1_law.LAWS:
        raise ConfigError(f"switching controller: law {law!r} is not supported; expected "
                          f"one of {l1_law.LAWS}")
    if law != leaf_law:
        leaf = "SwitchingGradientL1Law" if leaf_law == "gradient" else "SwitchingL1Law"
        raise ConfigError(f"switching controller: {leaf} runs the "
                          f"{leaf_law!r} law, not {law!r}; SwitchingL1Controller(law="
                          f"{law!r}) builds the leaf that runs it")
    if not designs:
        raise ConfigError("switching controller: designs is empty")
    index, step = options.initial_design_index, options.speed_step_mps
    if not 0 <= index < len(designs):
        raise ConfigError(f"switching controller: initial_design_index = "
                          f"{index!r} not in [0, {len(designs)})")
    if not (math.isfinite(step) and step > 0):
        raise ConfigError(f"switching controller: speed_step_mps = {step!r} "
                          "must be positive")
    return dataclasses.replace(options, law=law)


class SwitchingL1Law(LeafSystem):
    """Piecewise-constant L1 law over a list of designs, switched and speed-scheduled at run
    time without rebuilding the Diagram (module docstring); the Python leaf of
    :class:`SwitchingL1Controller`, with its own (Python) ``steering_rad`` output and the
    ``command_row`` r = [gains on s (4), gain on kappa, offset] with u = r . [s, kappa, 1],
    a function of the discrete state only (cached between samples); with
    ``curvature_preview`` the input ``curvature_preview_per_m`` and r = [gains on s (4), on
    kappa, on kappa_p, offset] with u = r . [s, kappa, kappa_p, 1].

    ``options`` (:class:`SwitchingOptions`, checked by :func:`check_switching_options`):
    law, initial design and speed, speed grid step, fast path and road preview."""

    def __init__(self, *, vehicle: VehicleParams, designs: list[ControllerDesign],
                 settings: Settings, options: SwitchingOptions | None = None):
        super().__init__()
        o = check_switching_options(designs, options or SwitchingOptions(), self.LAW)
        self.vehicle, self.designs, self.settings = vehicle, list(designs), settings
        self.speed_min_mps = float(settings.synthesis.speed_min_mps)
        self.speed_step_mps = float(o.speed_step_mps)
        self.sample_period_s = float(settings.controller.sample_period_s)
        self.fast, self.curvature_preview = bool(o.fast), bool(o.curvature_preview)
        self._cache: dict[tuple[int, int], ScheduledLaw] = {}

        self._s = self.DeclareVectorInputPort("state", 4)
        self._kappa = self.DeclareVectorInputPort("curvature_per_m", 1)
        self._speed = self.DeclareVectorInputPort("speed_mps", 1)
        self._design = self.DeclareVectorInputPort("design_index", 1)
        self._kappa_p = (self.DeclareVectorInputPort("curvature_preview_per_m", 1)
                         if self.curvature_preview else None)
        self._z = self.DeclareDiscreteState(BasicVector(self._initial_discrete_state(o)))
        self._declare_sampling()
        self.DeclareVectorOutputPort("steering_rad", 1, self._command)
        xd = {self.xd_ticket()}
        self.DeclareVectorOutputPort(
            "active_design_index", 1,
            lambda c, o: o.SetAtIndex(0, c.get_discrete_state(self._z).GetAtIndex(DESIGN)),
            prerequisites_of_calc=xd)
        self.DeclareVectorOutputPort("scheduled_speed_mps", 1, self._calc_scheduled_speed,
                                     prerequisites_of_calc=xd)
        self.DeclareVectorOutputPort("command_row", self.command_row_size,
                                     self._calc_command_row,
                                     prerequisites_of_calc=self._command_row_tickets())

    LAW = "piecewise_constant"  # the law this leaf runs (SwitchingGradientL1Law: "gradient")

    def _initial_discrete_state(self, options: SwitchingOptions) -> np.ndarray:
        """The discrete state before the first sample: the initial design, the grid point of
        the initial speed (the design's safe speed by default) and stopped below the stop
        speed."""
        d0 = int(options.initial_design_index)
        v0 = (self.designs[d0].speed_mps if options.initial_speed_mps is None
              else options.initial_speed_mps)
        z0 = np.zeros(STATE_SIZE)
        z0[DESIGN] = d0
        z0[GRID] = self.grid_index(d0, v0 if v0 > 0 else self.speed_min_mps)
        z0[STOPPED] = 0.0 if v0 >= self.speed_min_mps else 1.0
        return z0

    def _declare_sampling(self) -> None:
        """The sample every T_s: a periodic discrete update (the law is all discrete state)."""
        self.DeclarePeriodicDiscreteUpdateEvent(period_sec=self.sample_period_s,
                                                offset_sec=0.0, update=self._sample)

    def _command_row_tickets(self) -> set:
        """``command_row`` depends on the discrete state only (cached between samples)."""
        return {self.xd_ticket()}

    @property
    def command_row_size(self) -> int:
        """Length of ``command_row``: 6, or 7 with the road preview."""
        return 7 if self.curvature_preview else 6

    # ---------------------------------------------------------------- scheduling

    def grid_index(self, design_index: int, speed_mps: float) -> int:
        """Grid point of V clipped to [speed_min, the design's gain_speed_max_mps]."""
        top = max(self.designs[design_index].gain_speed_max_mps, self.speed_min_mps)
        v = min(max(float(speed_mps), self.speed_min_mps), top)
        return int(round((v - self.speed_min_mps) / self.speed_step_mps))

    def grid_speed(self, index: int) -> float:
        """Speed (m/s) of a grid point, rounded to 1e-9 so 12.0 is 12.0 exactly."""
        return round(self.speed_min_mps + index * self.speed_step_mps, 9)

    def law_at(self, design_index: int, grid_index: int) -> ScheduledLaw:
        """The cached :class:`ScheduledLaw` of a design at a grid point (computed once)."""
        key = (int(design_index), int(grid_index))
        if key not in self._cache:
            p = l1_law.l1_parameters(self.vehicle, self.designs[key[0]], self.settings,
                                     self.grid_speed(key[1]),
                                     curvature_preview=self.curvature_preview)
            self._cache[key] = scheduled_law(p, self.curvature_preview)
        return self._cache[key]

    def _requested_design(self, context) -> int:
        value = float(self._design.Eval(context)[0])
        index = int(round(value))
        if index != value or not 0 <= index < len(self.designs):
            raise ConfigError(f"switching controller: design_index input = {value!r} is not "
                              f"an index into {len(self.designs)} designs")
        return index

    # ---------------------------------------------------------------- the law

    def _curvatures(self, context) -> np.ndarray:
        """[kappa] or, with the road preview, [kappa, kappa_p] (1/m) at this context."""
        kappa = self._kappa.Eval(context)
        if self._kappa_p is None:
            return np.array([kappa[0]])
        return np.array([kappa[0], self._kappa_p.Eval(context)[0]])

    def _steering(self, law: ScheduledLaw, u_ad: float, s, curvatures: np.ndarray) -> float:
        if self.fast:
            c = law.command
            return float(c[0] * u_ad + c[1:5] @ s + c[5:-1] @ curvatures + c[-1])
        preview = curvatures[1] if self.curvature_preview else None
        return float(l1_law.steering_command(law.parameters, s, u_ad, curvatures[0], preview))

    def _sample(self, context, discrete_state) -> None:
        z = context.get_discrete_state(self._z).CopyToVector()
        s = self._s.Eval(context)
        curvatures = self._curvatures(context)
        kappa = float(curvatures[0])
        speed = float(self._speed.Eval(context)[0])
        requested = self._requested_design(context)
        old = (int(z[DESIGN]), int(z[GRID]))
        switched = requested != old[0]
        z[DESIGN] = requested
        design = int(z[DESIGN])
        if speed < self.speed_min_mps:  # stopped: no adaptation, steering held
            if switched:  # nothing adapts while stopped: the predictor restarts at s
                z[S_HAT] = l1_law.predictor_memory(self.law_at(design, int(z[GRID])).parameters,
                                                   s, kappa)
            if not z[STOPPED]:
                law = self.law_at(design, int(z[GRID]))
                z[HELD] = self._steering(law, z[U_AD], s, curvatures)
                z[STOPPED] = 1.0
        else:
            was_stopped = bool(z[STOPPED])
            z[STOPPED] = 0.0
            z[GRID] = self.grid_index(design, speed)
            law = self.law_at(design, int(z[GRID]))
            if switched and not was_stopped:  # bumpless, the estimate carried (l1_law)
                preview = curvatures[1] if self.curvature_preview else None
                z[S_HAT], z[U_AD] = l1_law.piecewise_constant_hand_over(
                    self.law_at(*old).parameters, law.parameters, z[S_HAT], z[U_AD],
                    l1_law.SwitchSample(s, kappa, preview))
            elif switched:  # resuming from a stop: the predictor at s
                z[S_HAT] = l1_law.predictor_memory(law.parameters, s, kappa)
            if self.fast:
                z[0:5] = law.update @ np.concatenate([z[0:5], s, curvatures, [1.0]])
            else:
                preview = curvatures[1] if self.curvature_preview else None
                s_hat, u_ad = l1_law.piecewise_constant_update(law.parameters, z[S_HAT],
                                                               z[U_AD], s, kappa, preview)
                z[S_HAT], z[U_AD] = s_hat, u_ad
        discrete_state.get_mutable_vector(self._z).SetFromVector(z)

    def _command(self, context, output) -> None:
        z = context.get_discrete_state(self._z).get_value()
        if z[STOPPED]:
            output.SetAtIndex(0, z[HELD])
            return
        law = self.law_at(int(z[DESIGN]), int(z[GRID]))
        output.SetAtIndex(0, self._steering(law, z[U_AD], self._s.Eval(context),
                                            self._curvatures(context)))

    def _u_ad(self, context, z) -> float:
        """The adaptive steering u_ad (rad): a discrete state entry of this law."""
        return z[U_AD]

    def _calc_command_row(self, context, output) -> None:
        z = context.get_discrete_state(self._z).get_value()
        row = np.zeros(self.command_row_size)
        if z[STOPPED]:
            row[-1] = z[HELD]
        else:
            c = self.law_at(int(z[DESIGN]), int(z[GRID])).command
            row[:-1] = c[1:-1]
            row[-1] = c[0] * self._u_ad(context, z) + c[-1]
        output.SetFromVector(row)

    def _calc_scheduled_speed(self, context, output) -> None:
        output.SetAtIndex(0, self.grid_speed(int(context.get_discrete_state(self._z)
                                                 .GetAtIndex(GRID))))

    # ---------------------------------------------------------------- initial state

    def initial_state(self, context, s0, curvature: float = 0.0) -> np.ndarray:
        """Discrete state with the predictor at s0 (at curvature kappa) and u_ad = 0 (as the
        fixed controller)."""
        z = self.GetMyContextFromRoot(context).get_discrete_state(self._z).CopyToVector()
        p = self.law_at(int(z[DESIGN]), int(z[GRID])).parameters
        z[0:5] = l1_law.piecewise_constant_initial_state(s0, p, curvature)
        return z

    def set_initial_state(self, context, s0, curvature: float = 0.0) -> None:
        """Write :meth:`initial_state` into this system's context within the root ``context``."""
        mine = self.GetMyMutableContextFromRoot(context)
        mine.SetDiscreteState(self.initial_state(context, s0, curvature))


@dataclasses.dataclass(frozen=True)
class GradientConstants:
    """The gradient law at one (design, grid speed) as plain floats, for
    :func:`gradient_derivatives_fast` (every entry from :class:`L1Parameters`).

    The predictor's derivative is affine: ``q_hat' = predictor_rows . [q_hat, kappa, kappa_ff]
    + b_m eta`` (``s_hat = q_hat - V kappa e4``, ``g_hat V kappa``, ``b_m k_ff V kappa_ff``
    folded into the rows), and ``s_tilde' P b_m = p_b . (q_hat - s) - p_b[3] V kappa``.
    """

    predictor_rows: tuple  # 4 rows of 6: [A_m | -V A_m e4 + g_hat V | b_m k_ff V]
    b_m: tuple  # (4,)
    p_b: tuple  # (4,) P b_m
    p_b_curvature: float  # p_b[3] V (the jump-free coordinates' term of s_tilde' P b_m)
    gamma: float
    filter_gain: float
    w_centre: float
    w_radius: float
    theta_max: float
    sigma_max: float
    epsilon: float

    @classmethod
    def of(cls, p: L1Parameters) -> "GradientConstants":
        a_m, b_m = np.asarray(p.a_m, float), np.asarray(p.b_m, float)
        v = float(p.measured_curvature_gain)
        rows = np.column_stack([a_m, -v * a_m[:, 3] + np.asarray(p.g_hat, float) * p.speed_mps,
                                b_m * p.k_ff * p.speed_mps])
        p_b = np.asarray(p.p_ad, float) @ b_m
        return cls(predictor_rows=tuple(tuple(r) for r in rows.tolist()),
                   b_m=tuple(b_m.tolist()), p_b=tuple(p_b.tolist()),
                   p_b_curvature=float(p_b[3] * v), gamma=float(p.adaptation_gain),
                   filter_gain=float(p.filter_gain), w_centre=float(p.w_centre),
                   w_radius=float(p.w_radius), theta_max=float(p.theta_max),
                   sigma_max=float(p.sigma_max), epsilon=float(p.projection_epsilon))


def _projection_factor(norm2: float, theta_y: float, bound: float, eps: float) -> float:
    """``f / |theta|^2`` where :func:`l1_law.projection_operator` is active (0 elsewhere):
    the projected update is ``y - theta (theta' y) factor``."""
    f = ((eps + 1.0) * norm2 - bound * bound) / (eps * bound * bound)
    return f / norm2 if (f > 0.0 and theta_y > 0.0) else 0.0


def gradient_derivatives_fast(c: GradientConstants, x, s, curvature: float,
                              feedforward_curvature: float) -> np.ndarray:
    """:func:`l1_law.gradient_controller_derivatives` in plain floats: the same equations,
    5 us a call against 62 us (tests check both agree). ``x`` = [q_hat, w_hat, theta_hat,
    sigma_hat, u_ad]; ``feedforward_curvature`` is kappa without the preview."""
    q0, q1, q2, q3, w, t0, t1, t2, t3, sigma, u_ad = x.tolist()
    s0, s1, s2, s3 = s.tolist()
    eta = w * u_ad + t0 * s0 + t1 * s1 + t2 * s2 + t3 * s3 + sigma  # adaptive_signal
    v = (q0, q1, q2, q3, curvature, feedforward_curvature)
    q_dot = [sum(r_i * v_i for r_i, v_i in zip(row, v, strict=True)) + b * eta
             for row, b in zip(c.predictor_rows, c.b_m, strict=True)]
    p0, p1, p2, p3 = c.p_b
    pb = (p0 * (q0 - s0) + p1 * (q1 - s1) + p2 * (q2 - s2) + p3 * (q3 - s3)
          - c.p_b_curvature * curvature)  # s_tilde' P b_m
    g, eps = c.gamma, c.epsilon
    y = -pb * u_ad  # w_hat, about its set's centre
    dw = w - c.w_centre
    w_dot = g * (y - dw * dw * y * _projection_factor(dw * dw, dw * y, c.w_radius, eps))
    y0, y1, y2, y3 = -pb * s0, -pb * s1, -pb * s2, -pb * s3  # theta_hat
    theta_y = t0 * y0 + t1 * y1 + t2 * y2 + t3 * y3
    k = theta_y * _projection_factor(t0 * t0 + t1 * t1 + t2 * t2 + t3 * t3, theta_y,
                                     c.theta_max, eps)
    theta_dot = [g * (y0 - t0 * k), g * (y1 - t1 * k), g * (y2 - t2 * k), g * (y3 - t3 * k)]
    sigma_dot = g * (-pb + sigma * sigma * pb * _projection_factor(sigma * sigma, -sigma * pb,
                                                                    c.sigma_max, eps))
    return np.array([*q_dot, w_dot, *theta_dot, sigma_dot, -c.filter_gain * eta])


def _into_ball(v: np.ndarray, radius: float) -> np.ndarray:
    """``v`` scaled radially into the ball ``|v| <= radius`` (unchanged inside it)."""
    norm = float(np.linalg.norm(v))
    return v if norm <= radius else v * (radius / norm)


class SwitchingGradientL1Law(SwitchingL1Law):
    """The gradient law over a list of designs, switched and speed-scheduled at run time
    (module docstring, "The gradient law"); the Python leaf of
    ``SwitchingL1Controller(law="gradient")``, with the ports of :class:`SwitchingL1Law`.

    Continuous state x = [q_hat (4), w_hat, theta_hat (4), sigma_hat, u_ad]
    (``l1_law.GRADIENT_STATE``), moving with the parameters of the active (design, grid
    point); discrete state as :class:`SwitchingL1Law`'s with slots 0-4 unused (zero). The
    sample every T_s is a periodic unrestricted update: it switches, schedules and hands x
    over (:meth:`hand_over`). ``fast=True`` evaluates the derivative with
    :func:`gradient_derivatives_fast`, ``fast=False`` with
    :func:`l1_law.gradient_controller_derivatives` (the readable reference).
    """

    LAW = "gradient"
    STATE_SIZE = sum(size for _, size in l1_law.GRADIENT_STATE)  # 11

    def __init__(self, *, vehicle: VehicleParams, designs: list[ControllerDesign],
                 settings: Settings, options: SwitchingOptions | None = None):
        super().__init__(vehicle=vehicle, designs=designs, settings=settings, options=options)
        self._gradient: dict[tuple[int, int], GradientConstants] = {}

    def _declare_sampling(self) -> None:
        self.DeclareContinuousState(self.STATE_SIZE)
        self.DeclarePeriodicUnrestrictedUpdateEvent(period_sec=self.sample_period_s,
                                                    offset_sec=0.0,
                                                    update=self._sample_gradient)

    def _command_row_tickets(self) -> set:
        return {self.xd_ticket(), self.xc_ticket()}  # u_ad is continuous state here

    def constants_at(self, design_index: int, grid_index: int) -> GradientConstants:
        """The cached :class:`GradientConstants` of a design at a grid point."""
        key = (int(design_index), int(grid_index))
        if key not in self._gradient:
            self._gradient[key] = GradientConstants.of(self.law_at(*key).parameters)
        return self._gradient[key]

    def _kappas(self, context) -> tuple[float, float | None]:
        """(kappa, kappa_p): kappa_p None without the road preview (u_ff at kappa)."""
        kappa = float(self._kappa.Eval(context)[0])
        return kappa, None if self._kappa_p is None else float(self._kappa_p.Eval(context)[0])

    # ---------------------------------------------------------------- the law

    def DoCalcTimeDerivatives(self, context, derivatives):
        z = context.get_discrete_state(self._z).get_value()
        if z[STOPPED]:  # stopped: no adaptation, nothing moves
            derivatives.get_mutable_vector().SetFromVector(np.zeros(self.STATE_SIZE))
            return
        x = context.get_continuous_state_vector().CopyToVector()
        s = self._s.Eval(context)
        kappa, preview = self._kappas(context)
        if self.fast:
            dx = gradient_derivatives_fast(self.constants_at(z[DESIGN], z[GRID]), x, s, kappa,
                                           kappa if preview is None else preview)
        else:
            dx = l1_law.gradient_controller_derivatives(
                self.law_at(int(z[DESIGN]), int(z[GRID])).parameters, x, s, kappa,
                preview).astype(float)
        derivatives.get_mutable_vector().SetFromVector(dx)

    def hand_over(self, old: tuple[int, int], new: tuple[int, int], x, s, curvatures,
                  bumpless: bool = True) -> np.ndarray:
        """The state x for the law at ``new`` = (design, grid index) when the law at ``old``
        was running, at the measurement s and ``curvatures`` ([kappa] or [kappa, kappa_p]);
        module docstring, "The gradient law".

        Design switch: q_hat at s (the new predictor starts at the plant), w_hat the same
        stiffness C = w_hat C_hat in the new C_hat, u_ad such that the steering command is
        unchanged (``bumpless``; False, when stopped: u_ad kept). Grid change (same design):
        q_hat such that s_hat is unchanged, u_ad kept (gain scheduling). Both: w_hat,
        theta_hat, sigma_hat put into the new design's sets (clipped, radially)."""
        law_old, law_new = self.law_at(*old), self.law_at(*new)
        p_old, p_new = law_old.parameters, law_new.parameters
        q, w, theta, sigma, u_ad = l1_law.unpack_gradient_state(np.asarray(x, float))
        s = np.asarray(s, float)
        kappa = float(curvatures[0])
        if new[0] != old[0]:  # design switch
            q = l1_law.predictor_memory(p_new, s, kappa)
            w = w * (self.designs[old[0]].nominal_stiffness_n_per_rad
                     / self.designs[new[0]].nominal_stiffness_n_per_rad)
            if bumpless:
                u_ad = (self._steering(law_old, u_ad, s, curvatures)
                        - self._steering(law_new, 0.0, s, curvatures))
        else:  # gain scheduling: the same prediction in the new jump-free coordinates
            q = l1_law.predictor_memory(p_new, l1_law.predicted_measurement(p_old, q, kappa),
                                        kappa)
        w = min(max(float(w), p_new.w_centre - p_new.w_radius), p_new.w_centre + p_new.w_radius)
        sigma = min(max(float(sigma), -p_new.sigma_max), p_new.sigma_max)
        return np.concatenate([q, [w], _into_ball(theta, p_new.theta_max), [sigma],
                               [float(u_ad)]])

    def _sample_gradient(self, context, state) -> None:
        z = context.get_discrete_state(self._z).CopyToVector()
        x = context.get_continuous_state_vector().CopyToVector()
        s = self._s.Eval(context)
        curvatures = self._curvatures(context)
        speed = float(self._speed.Eval(context)[0])
        old = (int(z[DESIGN]), int(z[GRID]))
        z[DESIGN] = self._requested_design(context)
        if speed < self.speed_min_mps:  # stopped: no adaptation, steering held
            new = (int(z[DESIGN]), old[1])
            if new != old:  # the steering is held: nothing to keep continuous
                x = self.hand_over(old, new, x, s, curvatures, bumpless=False)
            if not z[STOPPED]:
                z[HELD] = self._steering(self.law_at(*new), x[-1], s, curvatures)
                z[STOPPED] = 1.0
        else:
            z[STOPPED] = 0.0
            z[GRID] = self.grid_index(int(z[DESIGN]), speed)
            new = (int(z[DESIGN]), int(z[GRID]))
            if new != old:
                x = self.hand_over(old, new, x, s, curvatures)
        state.get_mutable_discrete_state(self._z).SetFromVector(z)
        state.get_mutable_continuous_state().SetFromVector(x)

    def _command(self, context, output) -> None:
        z = context.get_discrete_state(self._z).get_value()
        if z[STOPPED]:
            output.SetAtIndex(0, z[HELD])
            return
        law = self.law_at(int(z[DESIGN]), int(z[GRID]))
        u_ad = context.get_continuous_state_vector().GetAtIndex(self.STATE_SIZE - 1)
        if not self.fast:
            output.SetAtIndex(0, self._steering(law, u_ad, self._s.Eval(context),
                                                self._curvatures(context)))
            return
        c = law.command
        kappa, preview = self._kappas(context)
        u = c[0] * u_ad + float(c[1:5] @ self._s.Eval(context)) + c[5] * kappa + c[-1]
        output.SetAtIndex(0, float(u if preview is None else u + c[6] * preview))

    def _u_ad(self, context, z) -> float:
        """u_ad lives in the continuous state (its last entry)."""
        return context.get_continuous_state_vector().GetAtIndex(self.STATE_SIZE - 1)

    # ---------------------------------------------------------------- initial state

    def initial_state(self, context, s0, curvature: float = 0.0) -> np.ndarray:
        """Continuous state with the predictor at s0 (at curvature kappa), w_hat at its set's
        centre, theta = sigma = u_ad = 0 (``l1_law.gradient_initial_state``, as the fixed
        controller)."""
        z = self.GetMyContextFromRoot(context).get_discrete_state(self._z).get_value()
        p = self.law_at(int(z[DESIGN]), int(z[GRID])).parameters
        return l1_law.gradient_initial_state(p, s0, curvature)

    def set_initial_state(self, context, s0, curvature: float = 0.0) -> None:
        """Write :meth:`initial_state` into this system's context within the root ``context``."""
        mine = self.GetMyMutableContextFromRoot(context)
        mine.SetContinuousState(self.initial_state(context, s0, curvature))


def _row_product_system(n_curvatures: int = 1) -> SymbolicVectorSystem:
    """``u = r[0:4] . s + r[4:-1] . kappas + r[-1]`` for inputs [r (5 + n), s (4), kappas (n)]
    in C++; kappas = [kappa] or, with the road preview, [kappa, kappa_p] (n = 2).

    Drake 1.51's SymbolicVectorSystem needs a state in a continuous diagram: one constant
    dummy state (derivative 0), as in :mod:`drake_cert.systems.plants`.
    """
    r = sym.MakeVectorVariable(5 + n_curvatures, "r")
    s = sym.MakeVectorVariable(4, "s")
    kappas = sym.MakeVectorVariable(n_curvatures, "kappa")
    dummy = sym.Variable("unused")
    u = sum((r[i] * s[i] for i in range(4)), sym.Expression(0.0)) + r[-1]
    u = u + sum((r[4 + i] * kappas[i] for i in range(n_curvatures)), sym.Expression(0.0))
    return SymbolicVectorSystem(state=[dummy], input=np.concatenate([r, s, kappas]),
                                dynamics=[sym.Expression(0.0)], output=[u])


def _export_row_steering(builder: DiagramBuilder, law, curvature_ports: list[str]) -> None:
    """The fast path's steering: the law's ``command_row`` times [s, curvatures, 1] in C++
    (:func:`_row_product_system`), exported as ``steering_rad``."""
    n = len(curvature_ports)
    product = builder.AddNamedSystem("steering_from_row", _row_product_system(n))
    mux = builder.AddSystem(Multiplexer([5 + n, 4] + [1] * n))
    builder.Connect(law.GetOutputPort("command_row"), mux.get_input_port(0))
    builder.ConnectInput("state", mux.get_input_port(1))
    for i, name in enumerate(curvature_ports):
        builder.ConnectInput(name, mux.get_input_port(2 + i))
    builder.Connect(mux.get_output_port(0), product.get_input_port(0))
    builder.ExportOutput(product.get_output_port(0), "steering_rad")


class SwitchingL1Controller(Diagram):
    """The switching, speed-scheduled L1 controller (module docstring) as one block.

    :class:`SwitchingL1Law` (Python: the sample every T_s, switching and scheduling) and, for
    ``fast=True``, the steering ``u = r . [s, kappa, 1]`` evaluated in C++ from the law's
    cached ``command_row`` (the output is needed at every integrator stage; the row changes
    only at samples). ``fast=False`` exports the law's Python output, which calls
    ``l1_law.steering_command`` directly (the readable reference). Same ports as the leaf
    (``curvature_preview=True``: also ``curvature_preview_per_m``, the road preview).

    ``law="gradient"``: the leaf is :class:`SwitchingGradientL1Law` and its Python steering
    output is exported (u_ad is continuous state, so the row would change at every
    integrator stage as well); simulate it with an implicit integrator (module docstring,
    "Numerics of the gradient law").
    """

    def __init__(self, *, vehicle: VehicleParams, designs: list[ControllerDesign],
                 settings: Settings, options: SwitchingOptions | None = None):
        super().__init__()
        options = options or SwitchingOptions()
        law = options.law or "piecewise_constant"
        builder = DiagramBuilder()
        leaf = SwitchingGradientL1Law if law == "gradient" else SwitchingL1Law
        self._law = builder.AddNamedSystem("switching_l1_law", leaf(
            vehicle=vehicle, designs=designs, settings=settings,
            options=dataclasses.replace(options, law=law)))
        curvature_ports = ["curvature_per_m"] + \
            (["curvature_preview_per_m"] if options.curvature_preview else [])
        for name in ("state", *curvature_ports, "speed_mps", "design_index"):
            builder.ExportInput(self._law.GetInputPort(name), name)
        if options.fast and law != "gradient":
            _export_row_steering(builder, self._law, curvature_ports)
        else:
            builder.ExportOutput(self._law.GetOutputPort("steering_rad"), "steering_rad")
        for name in ("active_design_index", "scheduled_speed_mps"):
            builder.ExportOutput(self._law.GetOutputPort(name), name)
        builder.BuildInto(self)
        self.set_name("switching_l1_controller")

    def law_system(self) -> SwitchingL1Law:
        """The leaf holding the discrete state (for contexts and tests)."""
        return self._law

    def set_initial_state(self, context, s0, curvature: float = 0.0) -> None:
        """Predictor at s0, u_ad = 0 (as the fixed controller), in the root ``context``."""
        self._law.set_initial_state(context, s0, curvature)
