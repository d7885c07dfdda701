"""Equations of the L1 adaptive lateral controller (DESIGN section 4; paper section IV-B).

Role: the law itself, as functions. Where to start: ``l1_law`` holds the equations (read it
first); ``l1_reference`` runs them in Python for one design (the readable reference);
``l1_controller`` is the same law as fast Drake systems for one design; ``switching_controller``
is what the car runs (designs switched at run time).

Every function here works on floats and on ``pydrake.symbolic`` expressions: called with
numbers it is the readable reference, called with symbolic variables it builds the
C++-evaluated systems of :mod:`drake_cert.systems.l1_controller`. Symbols follow the paper:

  u      = -k_m s + u_ad + u_ff                      steering command (rad), then saturated
  u_ff   = k_ff psidot_des, psidot_des = V kappa      curvature feedforward (nominal e1 = 0)
  s_hat' = A_m s_hat + b_m (w_hat u_ad + theta_hat' s + sigma_hat + u_ff) + g_hat psidot_des
  eta    = w_hat u_ad + theta_hat' s + sigma_hat,     u_ad = -k D(s) (eta - k_g r), D = 1/s, r = 0

Two adaptation laws: the continuous gradient law with Gamma and the projection operator
(:func:`gradient_law`; stiff: integrate it implicitly, DESIGN 4.4), and the piecewise-constant
law sampled at T_s (:func:`piecewise_constant_update`), whose 4-vector estimate reaches the
filter through its input-channel equivalent at DC (:func:`compensated_estimate`, DESIGN 4.5).

Curvature changes (DESIGN 4.3): both predictors run in the jump-free coordinates
``q = s + V kappa e4 = [e1, e1dot, e2, r]`` and compare ``s_hat = q_hat - V kappa e4`` with the
measurement, kappa the curvature under the car (:func:`predicted_measurement`;
``L1Parameters.measured_curvature_gain`` = V, or 0 for the linear plants).

Road preview (DESIGN 4.2; ``controller.preview_ahead_s``, ``preview_window_s``, 0.4 s each by
default): u_ff, in command and predictor, is taken at the mean curvature kappa_p of the road
covered in the window ahead (:meth:`drake_cert.systems.road.Road.preview_curvature_trajectory`),
``g_hat V kappa`` at the curvature under the car; :func:`l1_parameters` with
``curvature_preview=True`` bounds sigma's two terms separately. No synthesis condition changes.

Projection bound (DESIGN 4.4): the gradient law's sigma set is taken at curvature
``1 / controller.min_radius_m`` (25 m, half the design radius); no synthesis condition uses it.
"""

import dataclasses

import numpy as np
import scipy.linalg

from drake_cert.config import Settings, VehicleParams
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.synthesis.uncertainty import (
    E1_SELECTOR,
    curvature_feedforward_gain,
    matched_disturbance,
    matched_uncertainty,
    nominal_model,
    reference_gain,
    stiffness_grid,
)
from drake_cert.systems import generic_math as gm

LAWS = ("piecewise_constant", "gradient")


@dataclasses.dataclass(frozen=True)
class L1Parameters:
    """Numbers the controller needs, all derived from a design at one speed V."""

    speed_mps: float  # V, constant over the episode
    a_m: np.ndarray  # (4, 4) A(C_hat, V) - b_m k_m, Hurwitz
    b_m: np.ndarray  # (4,) b(C_hat)
    g_hat: np.ndarray  # (4,) g(C_hat, V)
    k_m: np.ndarray  # (4,) state feedback (rad per state unit)
    k_ff: float  # u_ff = k_ff psidot_des (rad per rad/s)
    k_g: float  # reference gain -1/(c' A_m^-1 b_m); r = 0 in lane keeping
    filter_gain: float  # k of D(s) = 1/s (1/s)
    p_ad: np.ndarray  # (4, 4) A_m' P + P A_m = -Q_ad
    adaptation_gain: float  # Gamma (1/s)
    w_centre: float  # centre of the input-gain set [w_l, w_u], w = C / C_hat
    w_radius: float  # (w_u - w_l) / 2
    theta_max: float  # radius of the ball holding theta (rad per state unit)
    sigma_max: float  # bound on |sigma| (rad) at the largest curvature, 1 / min_radius_m
    projection_epsilon: float  # eps of the projection's convex function
    sample_period_s: float  # T_s of the piecewise-constant law
    pc_exp: np.ndarray  # (4, 4) e^{A_m T_s}
    pc_phi: np.ndarray  # (4, 4) Phi(T_s) = A_m^-1 (e^{A_m T_s} - I)
    pc_gain: np.ndarray  # (4, 4) -Phi(T_s)^-1 e^{A_m T_s}
    pc_output_inverse: np.ndarray  # (4,) c' A_m^-1 / (c' A_m^-1 b_m), a left inverse of b_m
    # d(measured e2dot)/d(kappa) = -this (m/s): V when e2dot = r - V kappa is computed from the
    # yaw rate (a vehicle, the Fiala plant); 0 for eq. 2.45 integrated as a state (linear plants)
    measured_curvature_gain: float = 0.0


def l1_parameters(vehicle: VehicleParams, design: ControllerDesign, settings: Settings,
                  speed_mps: float, e2dot_from_yaw_rate: bool = True,
                  curvature_preview: bool = False) -> L1Parameters:
    """Controller numbers for ``design`` at speed V (DESIGN 4); sets are bound_factor x max.

    ``e2dot_from_yaw_rate``: the measured e2dot is ``r - V kappa`` and jumps with kappa (a
    vehicle; the Fiala plant). False for the linear plants, which integrate eq. 2.45's e2dot
    as a state (it does not jump); the predictor then ignores curvature changes.
    ``curvature_preview``: u_ff is taken at a road-preview curvature that may differ from the
    curvature under the car (both within ``1 / min_radius_m``), so sigma's two terms are
    bounded separately.
    """
    ctl, syn = settings.controller, settings.synthesis
    c_hat = design.nominal_stiffness_n_per_rad
    c_lo, c_hi = design.certified_interval  # label interval widened to the tire secant
    nom = nominal_model(vehicle, c_hat, speed_mps, design.k_m_array)
    p_ad = scipy.linalg.solve_continuous_lyapunov(nom.a_m.T, -np.diag(ctl.q_ad_diag))
    grid = stiffness_grid(c_lo, c_hi, syn.stiffness_grid_points)
    thetas = [matched_uncertainty(vehicle, c, c_hat, speed_mps, design.k_m_array)[1]
              for c in grid]
    # sigma is linear in psidot_des: its bound at the largest curvature the design admits
    # (1 / controller.min_radius_m) holds for every road at most that curved
    largest_yaw_rate = speed_mps / ctl.min_radius_m
    sigmas = [matched_disturbance(vehicle, c, c_hat, speed_mps, design.k_m_array,
                                  largest_yaw_rate) for c in grid]
    if curvature_preview:  # sigma = (w - 1) k_ff V kappa_ff + b_m^+ (g - g_hat) V kappa
        k_ff = curvature_feedforward_gain(nom)
        sigmas = [abs((c / c_hat - 1.0) * k_ff * largest_yaw_rate)
                  + abs(sg - (c / c_hat - 1.0) * k_ff * largest_yaw_rate)
                  for c, sg in zip(grid, sigmas, strict=True)]
    t = ctl.sample_period_s
    e = scipy.linalg.expm(nom.a_m * t)
    phi = np.linalg.solve(nom.a_m, e - np.eye(4))
    tiny = 1e-9
    return L1Parameters(
        speed_mps=float(speed_mps), a_m=nom.a_m, b_m=nom.b_m, g_hat=nom.g_hat,
        k_m=design.k_m_array, k_ff=curvature_feedforward_gain(nom), k_g=reference_gain(nom),
        filter_gain=float(design.filter_gain), p_ad=p_ad, adaptation_gain=ctl.adaptation_gain,
        w_centre=0.5 * (c_lo + c_hi) / c_hat, w_radius=max(0.5 * (c_hi - c_lo) / c_hat, tiny),
        theta_max=max(ctl.bound_factor * max(np.linalg.norm(th) for th in thetas), tiny),
        sigma_max=max(ctl.bound_factor * max(abs(sg) for sg in sigmas), tiny),
        projection_epsilon=ctl.projection_epsilon, sample_period_s=t,
        pc_exp=e, pc_phi=phi, pc_gain=-np.linalg.solve(phi, e),
        pc_output_inverse=output_equivalent_inverse(nom.a_m, nom.b_m),
        measured_curvature_gain=float(speed_mps) if e2dot_from_yaw_rate else 0.0)


def output_equivalent_inverse(a_m: np.ndarray, b_m: np.ndarray) -> np.ndarray:
    """Row ``r = c' A_m^-1 / (c' A_m^-1 b_m)``: ``r b_m = 1`` and ``r v`` is the input with the
    same steady-state e1 as a constant disturbance v (Hovakimyan & Cao sec. 3.3,
    ``H_m(0)^-1 H_um(0)``; c the e1 selector).
    """
    c_ainv = np.linalg.solve(a_m.T, E1_SELECTOR)
    return c_ainv / float(c_ainv @ b_m)


# --------------------------------------------------------------------------- common parts

YAW_RATE_ROW = np.array([0.0, 0.0, 0.0, 1.0])  # e4: s[3] = e2dot = r - V kappa


def predicted_measurement(p: L1Parameters, q_hat, curvature):
    """``s_hat = q_hat - V kappa e4``: the predictor's state ``q_hat = [e1, e1dot, e2, r]`` as
    the measurement ``s = [e1, e1dot, e2, e2dot]`` at the current curvature kappa (1/m).

    Only the fourth entry moves (``e2dot = r - psidot_des``, ``psidot_des = V kappa``): a step
    in kappa steps the predicted e2dot exactly as it steps the measured one.
    """
    return np.asarray(q_hat) - gm.scaled(YAW_RATE_ROW, p.measured_curvature_gain * curvature)


def predictor_memory(p: L1Parameters, s_hat, curvature):
    """Inverse of :func:`predicted_measurement`: ``q_hat = s_hat + V kappa e4``."""
    return np.asarray(s_hat) + gm.scaled(YAW_RATE_ROW, p.measured_curvature_gain * curvature)


def curvature_feedforward(p: L1Parameters, curvature):
    """``u_ff = k_ff psidot_des`` with ``psidot_des = V kappa`` (rad)."""
    return p.k_ff * p.speed_mps * curvature


def steering_command(p: L1Parameters, s, u_ad, curvature, feedforward_curvature=None):
    """``u = -k_m s + u_ad + u_ff`` (rad, before saturation).

    ``u_ff`` is taken at ``feedforward_curvature`` (1/m; the road-preview curvature, see
    :func:`drake_cert.systems.road.Road.preview_curvature_trajectory`), or at ``curvature`` when
    None.
    """
    kappa_ff = curvature if feedforward_curvature is None else feedforward_curvature
    return -gm.dot(p.k_m, s) + u_ad + curvature_feedforward(p, kappa_ff)


def projection_operator(theta, y, theta_max: float, epsilon: float):
    """Hovakimyan & Cao Def. B.3 projection of the update ``y`` at the estimate ``theta``.

    ``f(th) = ((eps + 1)|th|^2 - thmax^2) / (eps thmax^2)``; where ``f > 0`` and
    ``y' grad f > 0``, returns ``y - grad f grad f' y f / |grad f|^2``, else ``y``. Along
    ``thetadot = Gamma Proj(theta, y)`` the estimate never leaves ``|theta| <= thmax``.
    ``theta`` and ``y`` are 1-D arrays of equal length (floats or symbolic).
    """
    theta = np.asarray(theta)
    y = np.asarray(y)
    norm2 = gm.dot(theta, theta)
    f = ((epsilon + 1.0) * norm2 - theta_max**2) / (epsilon * theta_max**2)
    # grad f = 2 (eps + 1) / (eps thmax^2) theta is a positive multiple of theta, so
    # y' grad f > 0 iff theta' y > 0, and grad f (grad f' y) f / |grad f|^2 =
    # theta (theta' y) f / |theta|^2 (|theta| > 0 wherever f > 0).
    theta_y = gm.dot(theta, y)
    active = gm.logical_and(f > 0, theta_y > 0)
    scale = theta_y * f / gm.where(norm2 > 0, norm2, 1.0)
    return np.array([gm.where(active, y[i] - theta[i] * scale, y[i]) for i in range(len(y))])


# --------------------------------------------------------------------------- gradient law

GRADIENT_STATE = ("s_hat", 4), ("w_hat", 1), ("theta_hat", 4), ("sigma_hat", 1), ("u_ad", 1)


def unpack_gradient_state(z):
    """Split the gradient-law controller state into (s_hat, w_hat, theta_hat, sigma_hat, u_ad)."""
    z = np.asarray(z)
    return z[0:4], z[4], z[5:9], z[9], z[10]


def adaptive_signal(w_hat, theta_hat, sigma_hat, u_ad, s):
    """``eta_hat = w_hat u_ad + theta_hat' s + sigma_hat`` (rad)."""
    return w_hat * u_ad + gm.dot(theta_hat, s) + sigma_hat


@dataclasses.dataclass(frozen=True)
class L1Options:
    """Which L1 law a single-design controller runs and what it is wired to
    (:class:`~drake_cert.systems.l1_controller.L1AdaptiveController` and its reference)."""

    law: str | None = None  # "piecewise_constant" or "gradient"; None: the settings' law
    e2dot_from_yaw_rate: bool = True  # measured e2dot jumps with kappa (a vehicle, Fiala)
    curvature_preview: bool = False  # input curvature_preview_per_m: u_ff at the preview


@dataclasses.dataclass(frozen=True)
class AdaptiveEstimates:
    """The gradient law's estimates and filter state (floats or symbolic expressions)."""

    w_hat: object  # input-gain estimate (dimensionless)
    theta_hat: object  # state-gain estimate (4,), rad per unit of s
    sigma_hat: object  # disturbance estimate (rad)
    u_ad: object  # adaptive steering input (rad)


def predictor_derivative(p: L1Parameters, s_hat, s, estimates: AdaptiveEstimates,
                         curvature, feedforward_curvature=None):
    """State predictor with the known inputs u_ff and g_hat psidot_des (DESIGN 4).

    ``u_ff`` is the one the command applies (at ``feedforward_curvature``, the preview, when
    given); ``g_hat psidot_des`` is the road as it is under the car (``curvature``).
    """
    e = estimates
    kappa_ff = curvature if feedforward_curvature is None else feedforward_curvature
    psidot = p.speed_mps * curvature
    eta = adaptive_signal(e.w_hat, e.theta_hat, e.sigma_hat, e.u_ad, s)
    return (gm.matvec(p.a_m, s_hat) + gm.scaled(p.b_m, eta + curvature_feedforward(p, kappa_ff))
            + gm.scaled(p.g_hat, psidot))


def gradient_law(p: L1Parameters, s_tilde, s, estimates: AdaptiveEstimates):
    """Paper eq. (adaptive) with projection about each set's centre: (w', theta', sigma').

    ``w_hat' = Gamma Proj(w_hat - w_c, -s_tilde' P b_m u_ad)``,
    ``theta_hat' = Gamma Proj(theta_hat, -s_tilde' P b_m s)``,
    ``sigma_hat' = Gamma Proj(sigma_hat, -s_tilde' P b_m)``.
    """
    w_hat, theta_hat = estimates.w_hat, estimates.theta_hat
    sigma_hat, u_ad = estimates.sigma_hat, estimates.u_ad
    e = p.projection_epsilon
    gamma = p.adaptation_gain
    pb = gm.dot(s_tilde, p.p_ad @ p.b_m)  # s_tilde' P b_m
    w_dot = gamma * projection_operator([w_hat - p.w_centre], [-pb * u_ad], p.w_radius, e)[0]
    theta_dot = gm.scaled(projection_operator(theta_hat, gm.scaled(s, -pb), p.theta_max, e),
                          gamma)
    sigma_dot = gamma * projection_operator([sigma_hat], [-pb], p.sigma_max, e)[0]
    return w_dot, theta_dot, sigma_dot


def low_pass_filter_derivative(p: L1Parameters, eta_hat, reference=0.0):
    """``u_ad' = -k (eta_hat - k_g r)``: the filter ``u_ad = -k D(s)(eta_hat - k_g r)``, D = 1/s."""
    return -p.filter_gain * (eta_hat - p.k_g * reference)


def gradient_controller_derivatives(p: L1Parameters, z, s, curvature,
                                    feedforward_curvature=None):
    """Time derivative of the gradient-law controller state ``[q_hat, w, theta, sigma, u_ad]``.

    ``q_hat`` is the predictor in jump-free coordinates (:func:`predicted_measurement`):
    ``q_hat' = s_hat'`` with ``s_hat = q_hat - V kappa e4`` (kappa piecewise constant).
    """
    q_hat, w_hat, theta_hat, sigma_hat, u_ad = unpack_gradient_state(z)
    s_hat = predicted_measurement(p, q_hat, curvature)
    s = np.asarray(s)
    estimates = AdaptiveEstimates(w_hat, theta_hat, sigma_hat, u_ad)
    s_hat_dot = predictor_derivative(p, s_hat, s, estimates, curvature, feedforward_curvature)
    w_dot, theta_dot, sigma_dot = gradient_law(p, s_hat - s, s, estimates)
    u_ad_dot = low_pass_filter_derivative(p, adaptive_signal(w_hat, theta_hat, sigma_hat,
                                                             u_ad, s))
    return np.concatenate([s_hat_dot, [w_dot], theta_dot, [sigma_dot], [u_ad_dot]])


def gradient_initial_state(p: L1Parameters, s0, curvature: float = 0.0) -> np.ndarray:
    """Predictor at the plant's state s0 (at curvature kappa), w_hat at its set's centre,
    theta = sigma = u_ad = 0."""
    q0 = predictor_memory(p, np.asarray(s0, float), float(curvature))
    return np.concatenate([q0, [p.w_centre], np.zeros(4), [0.0], [0.0]])


# --------------------------------------------------------------------------- piecewise constant

def piecewise_constant_estimate(p: L1Parameters, s_tilde):
    """``sigma_hat(iT_s) = -Phi(T_s)^-1 e^{A_m T_s} s_tilde(iT_s)`` (4-vector).

    Hovakimyan & Cao's piecewise-constant law: the estimate that, held over one period,
    drives the predictor's error to zero at the next sample. It covers matched and
    unmatched directions; all of it acts on the predictor.
    """
    return gm.matvec(p.pc_gain, s_tilde)


def compensated_estimate(p: L1Parameters, sigma_hat):
    """The input-channel equivalent of the 4-vector estimate that enters the filter (rad).

    ``eta_m = r sigma_hat`` with ``r = c' A_m^-1 / (c' A_m^-1 b_m)``: its matched part
    ``b_m sigma_1`` maps to ``sigma_1``, and its unmatched part to the input with the same
    steady-state e1 (H&C sec. 3.3 ``eta_2m = H_m^-1 H_um eta_2``, taken at DC). Compensating
    only the orthogonal matched part ``b_m^+ sigma_hat`` leaves the unmatched stiffness
    error uncompensated: with a corner-LMI design for heavy rain at its design speed and
    C = C_lo, the car then ends a 50 m curve 0.5 m (linear plant) to 1.2 m (Fiala plant) off
    the lane centre.
    """
    return gm.dot(p.pc_output_inverse, sigma_hat)


def piecewise_constant_update(p: L1Parameters, s_hat, u_ad, s, curvature,
                              feedforward_curvature=None):
    """One sample of the piecewise-constant law: ``(s_hat, u_ad)`` for the next period.

    The predictor argument and result are held in the jump-free coordinates
    ``q_hat = s_hat + V kappa e4`` of the sample they belong to (:func:`predictor_memory`):
    at t_k the prediction compared with s is ``q_hat - V kappa_k e4``, so a curvature step
    between samples moves the prediction as it moves the measurement. At constant kappa this
    is the law below in s coordinates.

    At t_k, with ``sigma_hat`` from the prediction error and ``eta = u_ad + eta_m``
    (:func:`compensated_estimate`): the filter ``u_ad' = -k eta`` is solved exactly over
    T_s with eta held (the new u_ad is applied over [t_k, t_k + T_s)), and the predictor
    ``s_hat' = A_m s_hat + b_m (u_ad + u_ff) + sigma_hat + g_hat psidot_des`` is solved
    exactly with its inputs held: ``s_hat(t_k+1) = e^{A_m T} s_hat + Phi(T)(...)``; u_ff is
    taken at ``feedforward_curvature`` (the road preview) when given, else at ``curvature``.
    """
    kappa_ff = curvature if feedforward_curvature is None else feedforward_curvature
    s_hat = predicted_measurement(p, s_hat, curvature)
    sigma_hat = piecewise_constant_estimate(p, s_hat - np.asarray(s))
    eta_matched = compensated_estimate(p, sigma_hat)
    decay = float(np.exp(-p.filter_gain * p.sample_period_s))
    u_ad_next = decay * u_ad - (1.0 - decay) * eta_matched
    forcing = (gm.scaled(p.b_m, u_ad_next + curvature_feedforward(p, kappa_ff)) + sigma_hat
               + gm.scaled(p.g_hat, p.speed_mps * curvature))
    s_hat_next = gm.matvec(p.pc_exp, s_hat) + gm.matvec(p.pc_phi, forcing)
    return predictor_memory(p, s_hat_next, curvature), u_ad_next


def piecewise_constant_inverse_estimate(p: L1Parameters, sigma_hat):
    """The prediction error ``s_tilde`` from which :func:`piecewise_constant_estimate` gives
    ``sigma_hat``: ``s_tilde = -e^{-A_m T_s} Phi(T_s) sigma_hat`` (4-vector)."""
    return np.linalg.solve(p.pc_gain, np.asarray(sigma_hat, dtype=float))


@dataclasses.dataclass(frozen=True)
class SwitchSample:
    """What the controller reads at the sample where it switches design: the state ``s``
    [e1 (m), e1' (m/s), e2 (rad), e2' (rad/s)], the curvature under the car (1/m) and the one
    the feedforward reads (the preview; None: the same)."""

    s: np.ndarray
    curvature: float
    feedforward_curvature: float | None = None

    @property
    def kappa_ff(self) -> float:
        return self.curvature if self.feedforward_curvature is None else self.feedforward_curvature


def carried_estimate(old: L1Parameters, new: L1Parameters, sigma_old, u_ad: tuple,
                     at: SwitchSample):
    """The new design's uncertainty estimate at a switch, from the old design's (DESIGN 5.6).

    Each design d models ``s' = A_m,d s + b_d (u_ad,d + u_ff,d) + g_d V_d kappa + sigma_d``
    (``u_ff,d`` at the preview curvature, ``g_d V_d kappa`` at the curvature under the car), so
    at one instant with the same ``s'`` (the steering continuous across the switch,
    :func:`piecewise_constant_hand_over`) the two totals differ by known terms only:

        sigma_new = sigma_old + (A_m,old - A_m,new) s + b_old (u_ad,old + u_ff,old)
                    - b_new (u_ad,new + u_ff,new) + g_old V_old kappa - g_new V_new kappa.

    Nothing about the plant (its stiffness, its tire) enters. ``u_ad`` is the pair
    ``(u_ad,old, u_ad,new)`` (rad).
    """
    s = np.asarray(at.s, dtype=float)

    def known(p: L1Parameters, adaptive: float):
        return (p.a_m @ s + p.b_m * (adaptive + curvature_feedforward(p, at.kappa_ff))
                + p.g_hat * (p.speed_mps * at.curvature))

    return np.asarray(sigma_old, dtype=float) + known(old, u_ad[0]) - known(new, u_ad[1])


def piecewise_constant_hand_over(old: L1Parameters, new: L1Parameters, q_hat, u_ad: float,
                                 at: SwitchSample):
    """A design switch of the piecewise-constant law at a sample: ``(q_hat, u_ad)`` for the
    new design's parameters, to be advanced by :func:`piecewise_constant_update` (DESIGN 5.6).

    Bumpless: ``u_ad,new = u + k_m,new' s - u_ff,new`` keeps the steering ``u`` the old design
    applies. Carried: the old design's estimate at this sample (from its own prediction error)
    becomes the new design's by :func:`carried_estimate`, and the predictor is placed where the
    new design's law reads exactly that estimate (:func:`piecewise_constant_inverse_estimate`).
    So the loop state ``[s, u - u_ff]`` and the estimate run on through the switch; the one
    thing that moves is ``u - u_ff`` by the change of feedforward, ``u_ff,old - u_ff,new``
    (0 on a straight road). ``q_hat`` is in the old design's jump-free coordinates, the result
    in the new's.
    """
    s, kappa = np.asarray(at.s, dtype=float), at.curvature
    u = steering_command(old, s, u_ad, kappa, at.kappa_ff)
    u_ad_new = float(u + new.k_m @ s - curvature_feedforward(new, at.kappa_ff))
    sigma_old = piecewise_constant_estimate(old, predicted_measurement(old, q_hat, kappa) - s)
    sigma_new = carried_estimate(old, new, sigma_old, (u_ad, u_ad_new), at)
    s_hat = s + piecewise_constant_inverse_estimate(new, sigma_new)
    return predictor_memory(new, s_hat, kappa), u_ad_new


def piecewise_constant_initial_state(s0, p: L1Parameters | None = None,
                                     curvature: float = 0.0) -> np.ndarray:
    """Predictor at the plant's state s0 (at curvature kappa; needs ``p`` when kappa != 0),
    u_ad = 0: ``[q_hat, u_ad]``, ``q_hat = s0 + V kappa e4``."""
    s0 = np.asarray(s0, float)
    if curvature != 0.0:
        s0 = predictor_memory(p, s0, float(curvature))
    return np.concatenate([s0, [0.0]])
