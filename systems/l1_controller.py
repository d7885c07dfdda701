"""The L1 adaptive lateral controller as a Drake system (DESIGN section 4).

Role: one design's controller, fast (symbolic systems evaluated in C++). Where to start:
``l1_law`` holds the equations (read it first); ``l1_reference`` runs them in Python for one
design (the readable reference); ``l1_controller`` is the same law as fast Drake systems for one
design; ``switching_controller`` is what the car runs (designs switched at run time).

Input ports:  ``state`` s = [e1, e1dot, e2, e2dot] (m, m/s, rad, rad/s),
              ``curvature_per_m`` road curvature kappa (1/m, > 0 left).
Output port:  ``steering_rad`` the command u = -k_m s + u_ad + u_ff (rad), UNSATURATED:
              the diagram puts a ``Saturation`` between controller and plant.

The equations are those of :mod:`drake_cert.systems.l1_law`, instantiated symbolically once:
- ``law="gradient"``: a continuous ``SymbolicVectorSystem`` (state s_hat, w_hat, theta_hat,
  sigma_hat, u_ad; 11 states), derivatives evaluated in C++;
- ``law="piecewise_constant"``: the law is linear in (s_hat, u_ad, s, kappa), so the
  symbolic update is decomposed into the matrices of a discrete ``AffineSystem`` with
  period T_s (state s_hat, u_ad; the command feeds s and kappa through directly).
The speed V is a construction parameter (constant-speed episodes). A Python ``LeafSystem``
running the same functions, :class:`drake_cert.systems.l1_reference.L1AdaptiveControllerReference`,
is the readable reference; the tests check that both give the same closed loop.
"""

import numpy as np
import pydrake.symbolic as sym
from pydrake.systems.framework import Context, Diagram, DiagramBuilder
from pydrake.systems.primitives import AffineSystem, Multiplexer, SymbolicVectorSystem

from drake_cert.config import Settings, VehicleParams
from drake_cert.errors import ConfigError
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.systems import l1_law
from drake_cert.systems.l1_law import L1Parameters


def _affine_matrices(expressions, variables):
    """``(M, c)`` with ``expressions = M @ variables + c`` (exact symbolic decomposition)."""
    m, c = sym.DecomposeAffineExpressions(np.asarray(expressions, dtype=object), variables)
    return np.asarray(m, float), np.asarray(c, float)


def _curvature_inputs(preview: bool):
    """``(inputs, kappa, kappa_ff)``: the curvature input variables (with the preview's)."""
    kappa = sym.Variable("kappa")
    if not preview:
        return [kappa], kappa, None
    kappa_ff = sym.Variable("kappa_ff")
    return [kappa, kappa_ff], kappa, kappa_ff


def gradient_law_system(p: L1Parameters, preview: bool = False) -> SymbolicVectorSystem:
    """Continuous-time gradient-law controller: input [s, kappa(, kappa_ff)], output u (C++)."""
    z = sym.MakeVectorVariable(11, "z")
    s = sym.MakeVectorVariable(4, "s")
    inputs, kappa, kappa_ff = _curvature_inputs(preview)
    _, _, _, _, u_ad = l1_law.unpack_gradient_state(z)
    with np.errstate(invalid="ignore"):  # numpy flags object-array arithmetic spuriously
        dynamics = l1_law.gradient_controller_derivatives(p, z, s, kappa, kappa_ff)
        output = [l1_law.steering_command(p, s, u_ad, kappa, kappa_ff)]
    return SymbolicVectorSystem(state=z, input=np.concatenate([s, inputs]), dynamics=dynamics,
                                output=output)


def piecewise_constant_system(p: L1Parameters, preview: bool = False) -> AffineSystem:
    """Discrete piecewise-constant-law controller at T_s: input [s, kappa(, kappa_ff)],
    output u."""
    z = sym.MakeVectorVariable(5, "z")
    s = sym.MakeVectorVariable(4, "s")
    inputs, kappa, kappa_ff = _curvature_inputs(preview)
    with np.errstate(invalid="ignore"):  # numpy flags object-array arithmetic spuriously
        s_hat_next, u_ad_next = l1_law.piecewise_constant_update(p, z[:4], z[4], s, kappa,
                                                                 kappa_ff)
        command = l1_law.steering_command(p, s, z[4], kappa, kappa_ff)
    zu = np.concatenate([z, s, inputs])
    m, f0 = _affine_matrices(np.concatenate([s_hat_next, [u_ad_next]]), zu)
    c, y0 = _affine_matrices([command], zu)
    return AffineSystem(A=m[:, :5], B=m[:, 5:], f0=f0, C=c[:, :5], D=c[:, 5:], y0=y0,
                        time_period=p.sample_period_s)


class L1AdaptiveController(Diagram):
    """L1 adaptive lateral controller for one design at speed V (DESIGN 4).

    ``options`` (:class:`~drake_cert.systems.l1_law.L1Options`): ``law`` is
    "piecewise_constant" (sampled at settings.controller.sample_period_s) or "gradient"
    (Gamma = settings.controller.adaptation_gain, projection operator); None takes
    settings.controller.adaptation_law. ``parameters`` holds the derived numbers.
    ``e2dot_from_yaw_rate`` (default True: a vehicle, the Fiala plant) says the measured e2dot
    jumps with the curvature; False for the linear plants (:func:`l1_law.l1_parameters`).
    ``curvature_preview`` adds the input port ``curvature_preview_per_m`` (1/m): the
    curvature feedforward u_ff is taken at it (the road ahead, averaged; see
    :meth:`drake_cert.systems.road.Road.preview_curvature_trajectory`) instead of at
    ``curvature_per_m``.
    """

    def __init__(self, *, vehicle: VehicleParams, design: ControllerDesign, settings: Settings,
                 speed_mps: float, options: l1_law.L1Options | None = None):
        super().__init__()
        options = options or l1_law.L1Options()
        e2dot_from_yaw_rate, curvature_preview = (options.e2dot_from_yaw_rate,
                                                  options.curvature_preview)
        law = options.law or settings.controller.adaptation_law
        if law not in l1_law.LAWS:
            raise ConfigError(f"unknown adaptation law {law!r}; expected one of {l1_law.LAWS}")
        if not speed_mps > 0:
            raise ConfigError(f"speed_mps = {speed_mps!r} must be positive")
        self.law = law
        self.curvature_preview = bool(curvature_preview)
        self.parameters = l1_law.l1_parameters(vehicle, design, settings, speed_mps,
                                                  e2dot_from_yaw_rate, self.curvature_preview)
        builder = DiagramBuilder()
        if law == "gradient":
            core = gradient_law_system(self.parameters, self.curvature_preview)
        else:
            core = piecewise_constant_system(self.parameters, self.curvature_preview)
        self._core = builder.AddNamedSystem(f"l1_{law}", core)
        mux = builder.AddSystem(Multiplexer([4, 1, 1] if self.curvature_preview else [4, 1]))
        builder.Connect(mux.get_output_port(0), self._core.get_input_port(0))
        builder.ExportInput(mux.get_input_port(0), "state")
        builder.ExportInput(mux.get_input_port(1), "curvature_per_m")
        if self.curvature_preview:
            builder.ExportInput(mux.get_input_port(2), "curvature_preview_per_m")
        builder.ExportOutput(self._core.get_output_port(0), "steering_rad")
        builder.BuildInto(self)
        self.set_name("l1_adaptive_controller")

    def initial_state(self, s0, curvature: float = 0.0) -> np.ndarray:
        """Controller state for plant state s0: predictor at s0, estimates at their centres."""
        if self.law == "gradient":
            return l1_law.gradient_initial_state(self.parameters, s0, curvature)
        return l1_law.piecewise_constant_initial_state(s0, self.parameters, curvature)

    def set_initial_state(self, context: Context, s0, curvature: float = 0.0) -> None:
        """Write :meth:`initial_state` into this controller's (sub)context."""
        sub = self._core.GetMyMutableContextFromRoot(context)
        if self.law == "gradient":
            sub.SetContinuousState(self.initial_state(s0, curvature))
        else:
            sub.SetDiscreteState(self.initial_state(s0, curvature))

    def core(self):
        """The system holding the controller state (SymbolicVectorSystem or AffineSystem)."""
        return self._core
