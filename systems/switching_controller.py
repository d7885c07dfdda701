"""The L1 adaptive controller that switches designs and follows the speed at run time (issue 7).

Input ports:  ``state`` s = [e1, e1dot, e2, e2dot] (m, m/s, rad, rad/s),
              ``curvature_per_m`` kappa (1/m), ``speed_mps`` V (m/s),
              ``design_index`` (index into ``designs``; a float holding an integer);
              with ``curvature_preview=True`` also ``curvature_preview_per_m`` kappa_p (1/m),
              the road preview (``systems.route.RouteSource``): the feedforward u_ff, in the
              command and in the predictor, is taken at kappa_p instead of kappa, while the
              predictor's ``g_hat V kappa`` and its jump-free coordinates keep the curvature
              under the car (``systems.l1_law``, "Road preview").
Output ports: ``steering_rad`` u (rad, UNSATURATED, as :mod:`systems.l1_controller`),
              ``active_design_index`` the design in use, ``scheduled_speed_mps`` the grid
              speed whose parameters are in use (m/s).
Discrete state (period T_s = settings.controller.sample_period_s, offset 0):
  ``[s_hat (4), u_ad, active design, speed grid index, stopped (0/1), held steering (rad)]``.

The law is the piecewise-constant one of :mod:`systems.l1_law` (DESIGN 4), unchanged; only its
parameters move. At each sample t_k, with the inputs read at t_k:
1. if ``design_index`` differs from the active design, the requested one becomes active at
   this sample (a request made in (t_{k-1}, t_k] acts at t_k; the dwell time is enforced
   upstream, in the certified-interval block);
2. the speed is clipped to [speed_min_mps, the design's ``gain_speed_max_mps``] (where its k_m
   is certified) and rounded to a grid of ``speed_step_mps``; the parameters
   ``l1_law.l1_parameters(vehicle, design, settings, V_grid)`` are computed once per
   (design, grid point) and cached;
3. ``l1_law.piecewise_constant_update`` advances (s_hat, u_ad); the output is
   ``l1_law.steering_command`` with the same parameters until the next sample.
Below ``speed_min_mps`` (the stop speed, DESIGN 2: the plant's lateral dynamics are frozen,
and the law's 1/V model is meaningless) the controller is stopped: (s_hat, u_ad) are not
updated (no adaptation) and the steering is held at its value at the stopping sample.

Adaptive state at a switch: u_ad is HANDED OVER and s_hat is RESET to the measured s.
u_ad is the filtered adaptive steering correction, in rad on the same input channel for every
design: keeping it keeps the steering continuous except for the change of -k_m s and u_ff,
and keeps the compensation the car currently needs on this road (resetting it to 0 would drop
e.g. the correction for a stiffness at the edge of the old interval, a steering step of that
size). s_hat is the state of the old design's predictor (its A_m, b_m); the new predictor
starts where the predictor starts at t = 0, at the plant's state, so the first estimate
of the new design is not the old model's prediction error. The piecewise-constant law has no
other memory (its estimate is recomputed from s_hat - s at every sample). A change of the
speed grid point within a design changes the parameters only (gain scheduling).

Speed: ``fast=True`` (default) evaluates the law through its affine matrices: for each
(design, grid point) ``piecewise_constant_update`` and ``steering_command`` are evaluated at
the unit vectors of [s_hat, u_ad, s, kappa (, kappa_p)] (both are affine in them, exactly),
giving one matrix-vector product per sample. ``fast=False`` calls the law's functions at
each sample, the readable reference; tests check both agree. Both are Python (a few tens of
us per call): the parameters are scheduled at run time, which Drake's C++ ``AffineSystem``
cannot do.
"""

import dataclasses
import math

import numpy as np
import pydrake.symbolic as sym
from pydrake.systems.framework import BasicVector, Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import Multiplexer, SymbolicVectorSystem

from drake_cert.config import Settings, VehicleParams
from drake_cert.errors import ConfigError
from synthesis.design import ControllerDesign
from systems import l1_law
from systems.l1_law import L1Parameters

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


class SwitchingL1Law(LeafSystem):
    """Piecewise-constant L1 law over a list of designs, switched and speed-scheduled at run
    time without rebuilding the Diagram (module docstring); the Python leaf of
    :class:`SwitchingL1Controller`, with its own (Python) ``steering_rad`` output and the
    ``command_row`` r = [gains on s (4), gain on kappa, offset] with u = r . [s, kappa, 1],
    a function of the discrete state only (cached between samples); with
    ``curvature_preview`` the input ``curvature_preview_per_m`` and r = [gains on s (4), on
    kappa, on kappa_p, offset] with u = r . [s, kappa, kappa_p, 1]."""

    def __init__(self, *, vehicle: VehicleParams, designs: list[ControllerDesign],
                 settings: Settings, law: str = "piecewise_constant",
                 initial_design_index: int = 0, initial_speed_mps: float | None = None,
                 speed_step_mps: float = 0.1, fast: bool = True,
                 curvature_preview: bool = False):
        super().__init__()
        if law != "piecewise_constant":
            raise ConfigError(f"switching controller: law {law!r} is not supported; only "
                              "'piecewise_constant' (the law run on vehicles, DESIGN 4)")
        if not designs:
            raise ConfigError("switching controller: designs is empty")
        if not 0 <= initial_design_index < len(designs):
            raise ConfigError(f"switching controller: initial_design_index = "
                              f"{initial_design_index!r} not in [0, {len(designs)})")
        if not (math.isfinite(speed_step_mps) and speed_step_mps > 0):
            raise ConfigError(f"switching controller: speed_step_mps = {speed_step_mps!r} "
                              "must be positive")
        self.vehicle, self.designs, self.settings = vehicle, list(designs), settings
        self.speed_min_mps = float(settings.synthesis.speed_min_mps)
        self.speed_step_mps = float(speed_step_mps)
        self.sample_period_s = float(settings.controller.sample_period_s)
        self.fast = bool(fast)
        self.curvature_preview = bool(curvature_preview)
        self._cache: dict[tuple[int, int], ScheduledLaw] = {}

        self._s = self.DeclareVectorInputPort("state", 4)
        self._kappa = self.DeclareVectorInputPort("curvature_per_m", 1)
        self._speed = self.DeclareVectorInputPort("speed_mps", 1)
        self._design = self.DeclareVectorInputPort("design_index", 1)
        self._kappa_p = (self.DeclareVectorInputPort("curvature_preview_per_m", 1)
                         if self.curvature_preview else None)
        d0 = int(initial_design_index)
        v0 = designs[d0].speed_mps if initial_speed_mps is None else initial_speed_mps
        z0 = np.zeros(STATE_SIZE)
        z0[DESIGN] = d0
        z0[GRID] = self.grid_index(d0, v0 if v0 > 0 else self.speed_min_mps)
        z0[STOPPED] = 0.0 if v0 >= self.speed_min_mps else 1.0
        self._z = self.DeclareDiscreteState(BasicVector(z0))
        self.DeclarePeriodicDiscreteUpdateEvent(period_sec=self.sample_period_s,
                                                offset_sec=0.0, update=self._sample)
        self.DeclareVectorOutputPort("steering_rad", 1, self._command)
        xd = {self.xd_ticket()}
        self.DeclareVectorOutputPort(
            "active_design_index", 1,
            lambda c, o: o.SetAtIndex(0, c.get_discrete_state(self._z).GetAtIndex(DESIGN)),
            prerequisites_of_calc=xd)
        self.DeclareVectorOutputPort("scheduled_speed_mps", 1, self._calc_scheduled_speed,
                                     prerequisites_of_calc=xd)
        self.DeclareVectorOutputPort("command_row", self.command_row_size,
                                     self._calc_command_row, prerequisites_of_calc=xd)

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
        switched = requested != int(z[DESIGN])  # switch: hand over u_ad, predictor restarts at s
        z[DESIGN] = requested
        design = int(z[DESIGN])
        if speed < self.speed_min_mps:  # stopped: no adaptation, steering held
            if switched:
                z[S_HAT] = l1_law.predictor_memory(self.law_at(design, int(z[GRID])).parameters,
                                                   s, kappa)
            if not z[STOPPED]:
                law = self.law_at(design, int(z[GRID]))
                z[HELD] = self._steering(law, z[U_AD], s, curvatures)
                z[STOPPED] = 1.0
        else:
            z[STOPPED] = 0.0
            z[GRID] = self.grid_index(design, speed)
            law = self.law_at(design, int(z[GRID]))
            if switched:  # the predictor at s, in its jump-free coordinates (l1_law)
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

    def _calc_command_row(self, context, output) -> None:
        z = context.get_discrete_state(self._z).get_value()
        row = np.zeros(self.command_row_size)
        if z[STOPPED]:
            row[-1] = z[HELD]
        else:
            c = self.law_at(int(z[DESIGN]), int(z[GRID])).command
            row[:-1] = c[1:-1]
            row[-1] = c[0] * z[U_AD] + c[-1]
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


def _row_product_system(n_curvatures: int = 1) -> SymbolicVectorSystem:
    """``u = r[0:4] . s + r[4:-1] . kappas + r[-1]`` for inputs [r (5 + n), s (4), kappas (n)]
    in C++; kappas = [kappa] or, with the road preview, [kappa, kappa_p] (n = 2).

    Drake 1.51's SymbolicVectorSystem needs a state in a continuous diagram: one constant
    dummy state (derivative 0), as in :mod:`systems.plants`.
    """
    r = sym.MakeVectorVariable(5 + n_curvatures, "r")
    s = sym.MakeVectorVariable(4, "s")
    kappas = sym.MakeVectorVariable(n_curvatures, "kappa")
    dummy = sym.Variable("unused")
    u = sum((r[i] * s[i] for i in range(4)), sym.Expression(0.0)) + r[-1]
    u = u + sum((r[4 + i] * kappas[i] for i in range(n_curvatures)), sym.Expression(0.0))
    return SymbolicVectorSystem(state=[dummy], input=np.concatenate([r, s, kappas]),
                                dynamics=[sym.Expression(0.0)], output=[u])


class SwitchingL1Controller(Diagram):
    """The switching, speed-scheduled L1 controller (module docstring) as one block.

    :class:`SwitchingL1Law` (Python: the sample every T_s, switching and scheduling) and, for
    ``fast=True``, the steering ``u = r . [s, kappa, 1]`` evaluated in C++ from the law's
    cached ``command_row`` (the output is needed at every integrator stage; the row changes
    only at samples). ``fast=False`` exports the law's Python output, which calls
    ``l1_law.steering_command`` directly (the readable reference). Same ports as the leaf
    (``curvature_preview=True``: also ``curvature_preview_per_m``, the road preview).
    """

    def __init__(self, *, vehicle: VehicleParams, designs: list[ControllerDesign],
                 settings: Settings, law: str = "piecewise_constant",
                 initial_design_index: int = 0, initial_speed_mps: float | None = None,
                 speed_step_mps: float = 0.1, fast: bool = True,
                 curvature_preview: bool = False):
        super().__init__()
        builder = DiagramBuilder()
        self._law = builder.AddNamedSystem("switching_l1_law", SwitchingL1Law(
            vehicle=vehicle, designs=designs, settings=settings, law=law,
            initial_design_index=initial_design_index, initial_speed_mps=initial_speed_mps,
            speed_step_mps=speed_step_mps, fast=fast, curvature_preview=curvature_preview))
        curvature_ports = ["curvature_per_m"] + \
            (["curvature_preview_per_m"] if curvature_preview else [])
        for name in ("state", *curvature_ports, "speed_mps", "design_index"):
            builder.ExportInput(self._law.GetInputPort(name), name)
        if fast:
            n = len(curvature_ports)
            product = builder.AddNamedSystem("steering_from_row", _row_product_system(n))
            mux = builder.AddSystem(Multiplexer([5 + n, 4] + [1] * n))
            builder.Connect(self._law.GetOutputPort("command_row"), mux.get_input_port(0))
            builder.ConnectInput("state", mux.get_input_port(1))
            for i, name in enumerate(curvature_ports):
                builder.ConnectInput(name, mux.get_input_port(2 + i))
            builder.Connect(mux.get_output_port(0), product.get_input_port(0))
            builder.ExportOutput(product.get_output_port(0), "steering_rad")
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
