"""The four safe-speed conditions of DESIGN 5.3, each as a margin (> 0: the condition holds).

a. ``l1_condition``: ``1 - max_w ||G_w||_L1 * L`` with ``G_w(s) = H(s) (1 - C_w(s))``,
   ``H(s) = (sI - A_m)^-1 b_m``, ``C_w(s) = w k D(s) / (1 + w k D(s))``, ``D = 1/s``, for every
   ``w`` in ``Omega = [C_lo, C_hi] / C_hat`` (grid incl. ends) and ``L = max_C ||theta||_1``
   (paper eq. (prog)); dimensionless.
b. ``reference_stability``: the reference system (the loop with the true uncertainty in
   place of its estimate) ``[[A(C) - b(C) k_m, b(C)], [-k theta', -k w]]`` is Hurwitz for
   every C in the interval and every speed in ``[V_min, V]``; margin ``-max Re eig`` (1/s).
c. ``steady_state_offset``: lane margin minus ``max_C |e1|`` at the equilibrium of the
   adaptive loop on the design curvature (``synthesis.equilibrium``); metres.
d. ``grip``: steady-state slip angles at ``C_lo`` within ``slip_angle_max`` (rad) and lateral
   acceleration ``V^2 / R <= lateral_accel_fraction * mu_lo * g`` (m/s^2).
"""

import functools

import cvxpy as cp
import numpy as np

from drake_cert.config import GRAVITY_MPS2, VehicleParams
from drake_cert.dynamics import lateral_error_dynamics
from synthesis.equilibrium import adaptive_steady_states
from synthesis.gains import solve_sdp
from synthesis.l1_norm import integral_abs_exponential_sums, l1_norm
from synthesis.uncertainty import NominalModel, matched_uncertainty, nominal_model

L1_CONDITION = "l1_condition"
REFERENCE_STABILITY = "reference_stability"
STEADY_STATE_OFFSET = "steady_state_offset"
GRIP = "grip"
CONDITIONS = (L1_CONDITION, REFERENCE_STABILITY, STEADY_STATE_OFFSET, GRIP)

# margin keys stored in ControllerDesign.margins (units in the name)
MARGIN_KEYS = {
    "gain_decay_per_s": "alpha-shifted stability of A - b k_m: -(max Re eig) - alpha",
    "l1_condition": "1 - ||G||_L1 L (dimensionless)",
    "reference_stability_per_s": "-(max Re eig) of the reference system over [V_min, V]",
    "steady_state_offset_m": "lane margin - max |e1| at equilibrium on the design curve",
    "grip_slip_angle_rad": "slip_angle_max - max(|alpha_f|, |alpha_r|) at C_lo",
    "grip_lateral_accel_mps2": "lateral_accel_fraction mu_lo g - V^2 / R",
}


def filtered_plant_realisation(nominal: NominalModel, w: float, k: float):
    """State space ``(A, B, C)`` of ``G(s) = H(s) (1 - C_w(s))`` (order 5).

    ``1 - C_w(s) = s / (s + w k)``: the filter state ``z' = -w k z + u`` feeds
    ``H`` with ``u - w k z``; the outputs are the four states of H. Shapes (5,5), (5,1), (4,5).
    """
    a = np.zeros((5, 5))
    a[:4, :4] = nominal.a_m
    a[:4, 4] = -w * k * nominal.b_m
    a[4, 4] = -w * k
    b = np.concatenate((nominal.b_m, [1.0])).reshape(5, 1)
    c = np.eye(5)[:4]
    return a, b, c


def high_passed_plant_l1_norms(nominal: NominalModel, w_values, filter_gain: float):
    """``||G_w||_L1`` for every w at once, from one eigendecomposition of ``A_m``.

    ``G_w(s) = H(s) s / (s + w k)`` shares the four poles ``lambda_l`` of ``H`` and adds the
    filter pole ``-w k``. With ``H(s) = sum_l R_l / (s - lambda_l)`` the residues are
    ``R_l lambda_l / (lambda_l + w k)`` at ``lambda_l`` and ``w k (w k I + A_m)^-1 b_m`` at
    ``-w k``; all (w, output) rows go through one call of
    :func:`synthesis.l1_norm.integral_abs_exponential_sums`. Falls back to
    :func:`synthesis.l1_norm.l1_norm` on the order-5 realisation when a filter pole is
    (nearly) one of A_m's or A_m is near-defective. Returns an array over ``w_values``.
    """
    w_values = np.asarray(w_values, dtype=float)
    lam, vec = np.linalg.eig(nominal.a_m)
    if lam.real.max() >= 0.0:
        return np.full(w_values.shape, np.inf)
    bandwidths = w_values * filter_gain
    vec_inv = np.linalg.inv(vec)
    well_posed = (np.abs(vec).sum(axis=0).max() * np.abs(vec_inv).sum(axis=0).max() < 1e8
                  and np.abs(lam[:, None] + bandwidths[None, :]).min() > 1e-6 * np.abs(lam).max())
    if well_posed:
        h_res = vec * (vec_inv @ nominal.b_m)[None, :]  # (4 outputs, 4 modes): R_l columns
        n_w = len(bandwidths)
        poles = np.concatenate((lam, -bandwidths.astype(complex)))
        res = np.zeros((n_w, 4, 4 + n_w), dtype=complex)
        for i, wk in enumerate(bandwidths):
            res[i, :, :4] = h_res * (lam / (lam + wk))[None, :]
            res[i, :, 4 + i] = wk * np.linalg.solve(wk * np.eye(4) + nominal.a_m, nominal.b_m)
        per_row = integral_abs_exponential_sums(res.reshape(n_w * 4, 4 + n_w), poles)
        if per_row is not None:
            return per_row.reshape(n_w, 4).max(axis=1)
    return np.array([l1_norm(*filtered_plant_realisation(nominal, w, filter_gain))
                     for w in w_values])


def matched_uncertainty_bound(vehicle: VehicleParams, k_m, interval, speed_mps: float,
                              stiffness_points: int = 2) -> float:
    """``L = max_C ||theta(C)||_1`` over the interval (paper after eq. (prog)).

    ``theta`` is affine in C at fixed V, so the convex ``||theta||_1`` peaks at an end; the
    grid (incl. both ends) is only a cross-check.
    """
    lo, hi = interval
    c_hat = 0.5 * (lo + hi)
    return max(float(np.abs(matched_uncertainty(vehicle, c, c_hat, speed_mps, k_m)[1]).sum())
               for c in np.linspace(lo, hi, max(stiffness_points, 2)))


def l1_condition_margin(vehicle: VehicleParams, k_m, interval, speed_mps: float,
                        filter_gain: float, w_points: int, stiffness_points: int = 2) -> float:
    """Condition a: ``1 - max_{w in Omega} ||G_w||_L1 * L`` (module docstring)."""
    lo, hi = interval
    c_hat = 0.5 * (lo + hi)
    nom = nominal_model(vehicle, c_hat, speed_mps, k_m)
    bound = matched_uncertainty_bound(vehicle, k_m, interval, speed_mps, stiffness_points)
    worst = high_passed_plant_l1_norms(
        nom, np.linspace(lo, hi, max(w_points, 2)) / c_hat, filter_gain).max()
    return 1.0 - worst * bound


def reference_system_matrix(vehicle: VehicleParams, k_m, nominal_stiffness: float,
                            stiffness: float, speed_mps: float, filter_gain: float) -> np.ndarray:
    """``[[A(C) - b(C) k_m, b(C)], [-k theta', -k w]]`` (5, 5): plant and filter, no adaptation.

    The filter ``u_ad' = -k (w u_ad + theta' s)`` acts on the true matched uncertainty
    ``eta = w u_ad + theta' s`` (sigma is an exogenous input and drops out of stability).
    """
    k_m = np.asarray(k_m, dtype=float).reshape(4)
    a, b, _ = lateral_error_dynamics(vehicle, stiffness, speed_mps)
    w, theta, _ = matched_uncertainty(vehicle, stiffness, nominal_stiffness, speed_mps, k_m)
    m = np.zeros((5, 5))
    m[:4, :4] = a - np.outer(b, k_m)
    m[:4, 4] = b
    m[4, :4] = -filter_gain * theta
    m[4, 4] = -filter_gain * w
    return m


def reference_stability_margin(vehicle: VehicleParams, k_m, interval, speed_lo_mps: float,
                               speed_mps: float, filter_gain: float, stiffness_points: int,
                               speed_points: int) -> float:
    """Condition b on a grid: ``-max Re eig`` of the reference system over C x [V_lo, V] (1/s)."""
    c_hat = 0.5 * (interval[0] + interval[1])
    mats = [reference_system_matrix(vehicle, k_m, c_hat, c, v, filter_gain)
            for c in np.linspace(interval[0], interval[1], max(stiffness_points, 2))
            for v in np.linspace(speed_lo_mps, speed_mps, max(speed_points, 2))]
    return -float(np.linalg.eigvals(np.array(mats)).real.max())


@functools.cache
def _reference_lmi_problem():
    """Parametrised common-Lyapunov LMI over four corner matrices (compiled once, DPP)."""
    mats = [cp.Parameter((5, 5)) for _ in range(4)]
    p = cp.Variable((5, 5), symmetric=True)
    eps = cp.Parameter(nonneg=True)
    eye = np.eye(5)
    constraints = [p >> eye]
    for m in mats:
        lyap = m.T @ p + p @ m
        constraints.append(0.5 * (lyap + lyap.T) << -eps * eye)
    problem = cp.Problem(cp.Minimize(cp.trace(p) * 1e-6), constraints)
    return problem, mats, eps


def reference_stability_lmi(vehicle: VehicleParams, k_m, interval, speed_lo_mps: float,
                            speed_mps: float, filter_gain: float, lmi_margin: float) -> bool:
    """Condition b certified: one P with ``M_i' P + P M_i <= -eps I``, ``P >= I`` at 4 corners.

    The reference matrix is affine in ``(C, C/V, 1/V)`` (``theta`` carries ``C_hat / V``), i.e.
    bilinear in ``(C, 1/V)``: each point of ``[C_lo, C_hi] x [V_lo, V]`` is the bilinear
    interpolation (a convex combination) of the four corner matrices, so a common Lyapunov
    matrix at the corners certifies every C and every speed in ``[V_lo, V]``.
    """
    problem, mats, eps = _reference_lmi_problem()
    c_hat = 0.5 * (interval[0] + interval[1])
    scale = 0.0
    corner_mats = []
    for c in interval:
        for v in (speed_lo_mps, speed_mps):
            corner_mats.append(reference_system_matrix(vehicle, k_m, c_hat, c, v, filter_gain))
            scale = max(scale, np.abs(corner_mats[-1]).max())
    for param, m in zip(mats, corner_mats, strict=True):
        param.value = m / scale  # same Lyapunov matrix; better conditioned for the solver
    eps.value = lmi_margin
    return solve_sdp(problem)


def steady_state_offset_margin(vehicle: VehicleParams, k_m, interval, speed_mps: float,
                               design_radius_m: float, q_ad_diag,
                               stiffness_points: int) -> float:
    """Condition c: ``lane margin - max_C |e1|`` at the adaptive equilibrium (m)."""
    c_hat = 0.5 * (interval[0] + interval[1])
    states = adaptive_steady_states(
        vehicle, k_m, c_hat, np.linspace(interval[0], interval[1], max(stiffness_points, 2)),
        speed_mps, 1.0 / design_radius_m, q_ad_diag)
    worst = max(abs(state.lateral_offset_m) for state in states)
    return vehicle.lane_margin_m - worst


def steady_state_slip_angles(vehicle: VehicleParams, stiffness: float, speed_mps: float,
                             radius_m: float) -> tuple[float, float]:
    """Front and rear slip angles (rad) of the single track cornering at ``a_y = V^2 / R``.

    Steady cornering: the axle forces carry the centripetal force, ``F_f + F_r = m a_y``, and
    cancel in yaw, ``F_f l_f = F_r l_r``; so ``F_f = m a_y l_r / (l_f + l_r)`` and
    ``F_r = m a_y l_f / (l_f + l_r)``. Each axle has two tires of stiffness C,
    ``F = 2 C alpha``, giving ``alpha_f = m l_r a_y / (2 C (l_f + l_r))`` and
    ``alpha_r = m l_f a_y / (2 C (l_f + l_r))`` (small angles, linear tires).
    """
    a_y = speed_mps**2 / radius_m
    wheelbase = vehicle.lf_m + vehicle.lr_m
    alpha_f = vehicle.mass_kg * vehicle.lr_m * a_y / (2.0 * stiffness * wheelbase)
    alpha_r = vehicle.mass_kg * vehicle.lf_m * a_y / (2.0 * stiffness * wheelbase)
    return alpha_f, alpha_r


def grip_margins(vehicle: VehicleParams, stiffness_lo: float, friction_mu_lo: float,
                 speed_mps: float, radius_m: float, slip_angle_max_rad: float,
                 lateral_accel_fraction: float) -> tuple[float, float]:
    """Condition d: ``(slip margin (rad), lateral-acceleration margin (m/s^2))``.

    Slip angles scale with 1/C, so C_lo is the worst case of the interval.
    """
    slip = max(steady_state_slip_angles(vehicle, stiffness_lo, speed_mps, radius_m))
    a_y = speed_mps**2 / radius_m
    return (slip_angle_max_rad - slip,
            lateral_accel_fraction * friction_mu_lo * GRAVITY_MPS2 - a_y)


def grip_speed_limit_mps(vehicle: VehicleParams, stiffness_lo: float, friction_mu_lo: float,
                         radius_m: float, slip_angle_max_rad: float,
                         lateral_accel_fraction: float) -> float:
    """Largest speed meeting condition d (both margins grow monotonically worse with V^2)."""
    wheelbase = vehicle.lf_m + vehicle.lr_m
    a_slip = slip_angle_max_rad * 2.0 * stiffness_lo * wheelbase / (
        vehicle.mass_kg * max(vehicle.lf_m, vehicle.lr_m))
    a_mu = lateral_accel_fraction * friction_mu_lo * GRAVITY_MPS2
    return float(np.sqrt(min(a_slip, a_mu) * radius_m))
