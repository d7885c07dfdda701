"""A readable Python ``LeafSystem`` running the L1 equations of :mod:`drake_cert.systems.l1_law`.

Role: the reference implementation the fast one is tested against. Where to start: ``l1_law``
holds the equations (read it first); ``l1_reference`` runs them in Python for one design (the
readable reference); ``l1_controller`` is the same law as fast Drake systems for one design;
``switching_controller`` is what the car runs (designs switched at run time).

Same ports and the same numbers as :class:`drake_cert.systems.l1_controller.L1AdaptiveController`,
with the equations evaluated in Python (about 20 us per evaluation, so ~10x slower): it is the
reference the C++-evaluated controller is tested against, and the place to read the law.
"""

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from drake_cert.config import Settings, VehicleParams
from drake_cert.errors import ConfigError
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.systems import l1_law


class L1AdaptiveControllerReference(LeafSystem):
    """L1 adaptive lateral controller, Python reference (see
    :mod:`drake_cert.systems.l1_controller`)."""

    def __init__(self, *, vehicle: VehicleParams, design: ControllerDesign, settings: Settings,
                 speed_mps: float, options: l1_law.L1Options | None = None):
        super().__init__()
        options = options or l1_law.L1Options()
        e2dot_from_yaw_rate, curvature_preview = (options.e2dot_from_yaw_rate,
                                                  options.curvature_preview)
        self.law = options.law or settings.controller.adaptation_law
        if self.law not in l1_law.LAWS:
            raise ConfigError(f"unknown adaptation law {self.law!r}; expected one of "
                              f"{l1_law.LAWS}")
        self.curvature_preview = bool(curvature_preview)
        self.parameters = l1_law.l1_parameters(vehicle, design, settings, speed_mps,
                                                  e2dot_from_yaw_rate, self.curvature_preview)
        self._s = self.DeclareVectorInputPort("state", 4)  # s = [e1, e1dot, e2, e2dot]
        self._kappa = self.DeclareVectorInputPort("curvature_per_m", 1)  # 1/m
        self._kappa_ff = (self.DeclareVectorInputPort("curvature_preview_per_m", 1)  # 1/m
                          if self.curvature_preview else None)
        if self.law == "gradient":
            # [s_hat (4), w_hat, theta_hat (4), sigma_hat, u_ad]
            self.DeclareContinuousState(11)
            self.DeclareVectorOutputPort("steering_rad", 1, self._command_gradient)
        else:
            # [s_hat (4), u_ad], updated every T_s
            self._z = self.DeclareDiscreteState(5)
            self.DeclarePeriodicDiscreteUpdateEvent(
                period_sec=self.parameters.sample_period_s, offset_sec=0.0,
                update=self._sample)
            self.DeclareVectorOutputPort("steering_rad", 1, self._command_sampled)

    def _inputs(self, context):
        """(s, kappa, kappa_ff): kappa_ff None without the preview port (u_ff at kappa)."""
        kappa_ff = None if self._kappa_ff is None else float(self._kappa_ff.Eval(context)[0])
        return self._s.Eval(context), float(self._kappa.Eval(context)[0]), kappa_ff

    def DoCalcTimeDerivatives(self, context, derivatives):
        if self.law != "gradient":  # Drake asks every subsystem, also those without x_c
            return
        s, kappa, kappa_ff = self._inputs(context)
        z = context.get_continuous_state_vector().CopyToVector()
        derivatives.get_mutable_vector().SetFromVector(
            l1_law.gradient_controller_derivatives(self.parameters, z, s, kappa,
                                                   kappa_ff).astype(float))

    def _sample(self, context, discrete_state):
        s, kappa, kappa_ff = self._inputs(context)
        z = context.get_discrete_state(self._z).CopyToVector()
        s_hat, u_ad = l1_law.piecewise_constant_update(self.parameters, z[:4], z[4], s, kappa,
                                                       kappa_ff)
        discrete_state.get_mutable_vector(self._z).SetFromVector(np.append(s_hat, u_ad))

    def _command_gradient(self, context, output: BasicVector):
        s, kappa, kappa_ff = self._inputs(context)
        u_ad = context.get_continuous_state_vector().GetAtIndex(10)
        output.SetAtIndex(0, l1_law.steering_command(self.parameters, s, u_ad, kappa, kappa_ff))

    def _command_sampled(self, context, output: BasicVector):
        s, kappa, kappa_ff = self._inputs(context)
        u_ad = context.get_discrete_state(self._z).GetAtIndex(4)
        output.SetAtIndex(0, l1_law.steering_command(self.parameters, s, u_ad, kappa, kappa_ff))

    def initial_state(self, s0, curvature: float = 0.0) -> np.ndarray:
        """Predictor at s0, estimates at their centres (as the fast controller)."""
        if self.law == "gradient":
            return l1_law.gradient_initial_state(self.parameters, s0, curvature)
        return l1_law.piecewise_constant_initial_state(s0, self.parameters, curvature)

    def set_initial_state(self, context, s0, curvature: float = 0.0) -> None:
        """Write :meth:`initial_state` into this system's context within the root ``context``."""
        mine = self.GetMyMutableContextFromRoot(context)
        if self.law == "gradient":
            mine.SetContinuousState(self.initial_state(s0, curvature))
        else:
            mine.SetDiscreteState(self.initial_state(s0, curvature))
