"""Steady state of the L1 adaptive loop on a constant-curvature road (DESIGN 4, 5.3c).

The car runs at speed V on curvature kappa (``psidot_des = V kappa``) with true stiffness C,
under ``u = -k_m s + u_ad + u_ff`` with the gradient adaptation law and the filter
``u_ad = -k D(s) eta_hat``, ``D = 1/s``. At an equilibrium of the whole loop:

* the filter state is stationary, so ``eta_hat = 0`` (r = 0);
* the predictor ``s_hat' = A_m s_hat + b_m (eta_hat + u_ff) + g_hat psidot_des`` rests at
  the nominal equilibrium ``s_hat = -A_m^-1 (b_m u_ff + g_hat psidot_des)``, whose e1 is 0 by
  the curvature feedforward;
* the gradient law (``theta_hat' ~ -s_tilde' P_ad b_m s`` etc.) is stationary with the
  estimates inside their sets only if ``s_tilde' P_ad b_m = 0``, ``s_tilde = s_hat - s``,
  ``A_m' P_ad + P_ad A_m = -Q_ad``;
* the plant rests: ``(A(C) - b(C) k_m) s + b(C) (u_ad + u_ff) + g(C) psidot_des = 0``.

The last two lines are five linear equations in ``(s, u_ad)``; their solution is the steady
state (independent of k and Gamma). Assumes the projection is inactive at equilibrium and
the linear tire model (small slip).
"""

import dataclasses

import numpy as np
import scipy.linalg

from drake_cert.config import VehicleParams
from drake_cert.dynamics import lateral_error_dynamics, yaw_rate_command
from drake_cert.synthesis.uncertainty import (
    curvature_feedforward_gain,
    nominal_model,
    output_equivalent_row,
)


@dataclasses.dataclass(frozen=True)
class SteadyCornering:
    """The steady manoeuvre an equilibrium is taken at: constant speed on a constant curve."""

    speed_mps: float  # forward speed V (m/s)
    curvature_per_m: float  # road curvature kappa (1/m, > 0 left)


@dataclasses.dataclass(frozen=True)
class AdaptiveSteadyState:
    """Equilibrium of plant, predictor and gradient law (units of ``s``: m, m/s, rad, rad/s)."""

    state: np.ndarray  # s = [e1, e1dot, e2, e2dot] of the plant
    predictor_state: np.ndarray  # s_hat (nominal equilibrium, e1 = 0)
    adaptive_input_rad: float  # u_ad
    feedforward_input_rad: float  # u_ff

    @property
    def lateral_offset_m(self) -> float:
        """e1 at equilibrium (m, > 0 left of the lane centre)."""
        return float(self.state[0])


def adaptation_lyapunov_matrix(a_m: np.ndarray, q_ad_diag) -> np.ndarray:
    """``P_ad`` solving ``A_m' P_ad + P_ad A_m = -Q_ad`` (DESIGN 4; the paper's form transposed)."""
    q_ad = np.diag(np.asarray(q_ad_diag, dtype=float))
    p_ad = scipy.linalg.solve_continuous_lyapunov(a_m.T, -q_ad)
    return 0.5 * (p_ad + p_ad.T)


def adaptive_steady_state(vehicle: VehicleParams, k_m, nominal_stiffness: float,
                          stiffness: float, cornering: SteadyCornering,
                          q_ad_diag) -> AdaptiveSteadyState:
    """Equilibrium of the L1 loop with the gradient law (module docstring, DESIGN 5.3c).

    ``k_m`` (4,) state feedback, ``nominal_stiffness`` C_hat and ``stiffness`` C per tire
    (N/rad), ``cornering`` (:class:`SteadyCornering`) V (m/s) and kappa (1/m, > 0 left),
    ``q_ad_diag`` the diagonal of Q_ad. Raises ``np.linalg.LinAlgError`` if the equilibrium
    is not unique.
    """
    return adaptive_steady_states(vehicle, k_m, nominal_stiffness, [stiffness], cornering,
                                  q_ad_diag)[0]


def adaptive_steady_states(vehicle: VehicleParams, k_m, nominal_stiffness: float, stiffnesses,
                           cornering: SteadyCornering, q_ad_diag) -> list[AdaptiveSteadyState]:
    """:func:`adaptive_steady_state` for several true stiffnesses (shares A_m, P_ad, s_hat)."""
    speed_mps, curvature_per_m = cornering.speed_mps, cornering.curvature_per_m
    k_m = np.asarray(k_m, dtype=float).reshape(4)
    nom = nominal_model(vehicle, nominal_stiffness, speed_mps, k_m)
    psidot = yaw_rate_command(speed_mps, curvature_per_m)
    u_ff = curvature_feedforward_gain(nom) * psidot
    s_hat = -np.linalg.solve(nom.a_m, nom.b_m * u_ff + nom.g_hat * psidot)
    p_b = adaptation_lyapunov_matrix(nom.a_m, q_ad_diag) @ nom.b_m
    out = []
    for stiffness in stiffnesses:
        a, b, g = lateral_error_dynamics(vehicle, stiffness, speed_mps)
        lhs = np.zeros((5, 5))
        lhs[:4, :4] = a - np.outer(b, k_m)
        lhs[:4, 4] = b
        lhs[4, :4] = p_b
        rhs = np.concatenate((-(b * u_ff + g * psidot), [p_b @ s_hat]))
        sol = np.linalg.solve(lhs, rhs)
        out.append(AdaptiveSteadyState(sol[:4], s_hat, float(sol[4]), float(u_ff)))
    return out


def piecewise_constant_steady_states(vehicle: VehicleParams, k_m, nominal_stiffness: float,
                                     stiffnesses, speed_mps: float,
                                     curvature_per_m: float) -> list[AdaptiveSteadyState]:
    """Equilibria of the loop with the piecewise-constant law in its ideal limit (T_s -> 0).

    The 4-vector estimate equals the whole uncertainty ``sigma = (A(C) - b(C) k_m - A_m) s +
    (w - 1) b_m (u_ad + u_ff) + (g - g_hat) psidot`` and the filter rests when
    ``u_ad + r sigma = 0`` (``r`` the output-equivalent row, ``r b_m = 1``); with the plant at
    rest these are five linear equations in ``(s, u_ad)``. The predictor equals the plant
    (``s_hat = s``). Analytically e1 = 0 (the feedforward and r make the nominal DC gain
    exact), which this solve checks rather than assumes.
    """
    k_m = np.asarray(k_m, dtype=float).reshape(4)
    nom = nominal_model(vehicle, nominal_stiffness, speed_mps, k_m)
    psidot = yaw_rate_command(speed_mps, curvature_per_m)
    u_ff = curvature_feedforward_gain(nom) * psidot
    r = output_equivalent_row(nom)
    out = []
    for stiffness in stiffnesses:
        a, b, g = lateral_error_dynamics(vehicle, stiffness, speed_mps)
        a_cl = a - np.outer(b, k_m)
        w = stiffness / nominal_stiffness
        lhs = np.zeros((5, 5))
        lhs[:4, :4] = a_cl
        lhs[:4, 4] = b
        # u_ad + r sigma = 0, sigma = (a_cl - A_m) s + (w - 1) b_m (u_ad + u_ff) + dg psidot
        lhs[4, :4] = r @ (a_cl - nom.a_m)
        lhs[4, 4] = 1.0 + (w - 1.0)
        rhs = np.concatenate((-(b * u_ff + g * psidot),
                              [-(w - 1.0) * u_ff - r @ (g - nom.g_hat) * psidot]))
        sol = np.linalg.solve(lhs, rhs)
        out.append(AdaptiveSteadyState(sol[:4], sol[:4], float(sol[4]), float(u_ff)))
    return out
