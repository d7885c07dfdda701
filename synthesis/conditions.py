"""The four safe-speed conditions of DESIGN 5.3, each as a margin (> 0: the condition holds).

a. ``l1_condition``: ``1 - max_w ||G_w||_L1 * L`` with ``G_w(s) = H(s) (1 - C_w(s))``,
   ``H(s) = (sI - A_m)^-1 b_m``, ``C_w(s) = w k D(s) / (1 + w k D(s))``, ``D = 1/s``, for every
   ``w`` in ``Omega = [C_lo, C_hi] / C_hat`` (grid incl. ends) and ``L = max_C ||theta||_1``
   (paper eq. (prog)); dimensionless.
b. ``reference_stability``: the reference system (the loop with the true uncertainty in
   place of its estimate) ``[[A(C) - b(C) k_m, b(C)], [-k theta', -k w]]`` is Hurwitz for
   every C in the interval and every speed in ``[V_min, V]``; margin ``-max Re eig`` (1/s).
c. ``steady_state_offset``: lane margin minus ``max_C |e1|`` at the equilibrium of the
   adaptive loop on the design curvature (``drake_cert.synthesis.equilibrium``); metres (stored as
   ``steady_state_lane_margin_m``: the lane margin left at that equilibrium).
d. ``grip``: the tire as it is at the slip the design admits. The Fiala tire's secant
   stiffness over normalised slips ``z = C |tan a| / (3 mu F_z) <= z_b`` lies in
   ``[C (1 - z_b + z_b^2/3), C]``; a, b and c are evaluated on the widened interval
   ``[C_lo (1 - z_b + z_b^2/3), C_hi]`` (:func:`tire_stiffness_lo`), and d asks that the
   steady slip on the design curve at the least friction stays within ``z_b`` and
   ``V^2 / R <= lateral_accel_fraction * mu_lo * g`` (m/s^2).
e. vehicle limits, each where it is given: ``rollover``, ``V^2 / R <= rollover_fraction g
   t / (2 h)`` (the vehicle's static stability factor), and ``comfort``,
   ``V^2 / R <= lateral_accel_limit_mps2`` (settings); m/s^2.
"""

import dataclasses
import functools

import cvxpy as cp
import numpy as np

from drake_cert.config import GRAVITY_MPS2, VehicleParams
from drake_cert.dynamics import (
    fiala_normalised_slip_at_utilisation,
    fiala_secant_ratio,
    lateral_error_dynamics,
)
from drake_cert.synthesis.design import (
    MARGIN_KEYS as MARGIN_KEYS,  # the stored margins, re-exported
)
from drake_cert.synthesis.equilibrium import (
    SteadyCornering,
    adaptive_steady_states,
    piecewise_constant_steady_states,
)
from drake_cert.synthesis.gains import solve_sdp
from drake_cert.synthesis.l1_norm import integral_abs_exponential_sums, l1_norm
from drake_cert.synthesis.uncertainty import (
    NominalModel,
    matched_uncertainty,
    nominal_model,
    output_equivalent_row,
)

L1_CONDITION = "l1_condition"
REFERENCE_STABILITY = "reference_stability"
STEADY_STATE_OFFSET = "steady_state_offset"
GRIP = "grip"
ROLLOVER = "rollover"  # vehicle limits (5.3e), where the vehicle and settings give them
COMFORT = "comfort"
GRADIENT = "gradient"  # adaptation laws (settings.controller.adaptation_law)
PIECEWISE_CONSTANT = "piecewise_constant"
CONDITIONS = (L1_CONDITION, REFERENCE_STABILITY, STEADY_STATE_OFFSET, GRIP, ROLLOVER, COMFORT)
SPEED_RANGE = "speed_range"  # a speed limited by the top of the searched range, no condition


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
    :func:`drake_cert.synthesis.l1_norm.integral_abs_exponential_sums`. Falls back to
    :func:`drake_cert.synthesis.l1_norm.l1_norm` on the order-5 realisation when a filter pole is
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


def filter_state_row(vehicle: VehicleParams, k_m, nominal_stiffness: float, stiffness: float,
                     speed_mps: float, law: str = GRADIENT) -> np.ndarray:
    """Gain from s to the filter input in the reference system, by adaptation law.

    Gradient law: ``theta`` (the matched part it estimates). Piecewise-constant law: its
    4-vector estimate is the whole uncertainty ``b_m theta' s + U s`` (``U`` the unmatched part)
    and the filter receives ``r`` times it, ``r b_m = 1``: ``theta + U' r``.
    """
    _, theta, unmatched = matched_uncertainty(vehicle, stiffness, nominal_stiffness, speed_mps,
                                              k_m)
    if law == GRADIENT:
        return theta
    nom = nominal_model(vehicle, nominal_stiffness, speed_mps, k_m)
    return theta + unmatched.T @ output_equivalent_row(nom)


def reference_system_matrix(vehicle: VehicleParams, k_m, nominal_stiffness: float,
                            stiffness: float, speed_mps: float, filter_gain: float,
                            law: str = GRADIENT) -> np.ndarray:
    """``[[A(C) - b(C) k_m, b(C)], [-k q', -k w]]`` (5, 5): plant and filter, no adaptation.

    The filter ``u_ad' = -k (w u_ad + q' s)`` acts on the ideal estimate, ``q`` from
    :func:`filter_state_row` for the law (exogenous inputs drop out of stability).
    """
    k_m = np.asarray(k_m, dtype=float).reshape(4)
    a, b, _ = lateral_error_dynamics(vehicle, stiffness, speed_mps)
    w = stiffness / nominal_stiffness
    m = np.zeros((5, 5))
    m[:4, :4] = a - np.outer(b, k_m)
    m[:4, 4] = b
    m[4, :4] = -filter_gain * filter_state_row(vehicle, k_m, nominal_stiffness, stiffness,
                                               speed_mps, law)
    m[4, 4] = -filter_gain * w
    return m


@dataclasses.dataclass(frozen=True)
class OperatingBox:
    """The stiffness interval x speed range condition b is stated on (DESIGN 5.3b)."""

    interval: tuple[float, float]  # (C_lo, C_hi), N/rad; C_hat is its midpoint
    speed_lo_mps: float  # V_lo (m/s)
    speed_mps: float  # V_hi (m/s)


def reference_stability_margin(vehicle: VehicleParams, k_m, box: OperatingBox,
                               filter_gain: float, grid: tuple[int, int],
                               law: str = GRADIENT) -> float:
    """Condition b on a grid: ``-max Re eig`` of the reference system over C x [V_lo, V] (1/s);
    ``grid``: (stiffness points, speed points), each at least 2."""
    interval = box.interval
    stiffness_points, speed_points = grid
    c_hat = 0.5 * (interval[0] + interval[1])
    mats = [reference_system_matrix(vehicle, k_m, c_hat, c, v, filter_gain, law)
            for c in np.linspace(interval[0], interval[1], max(stiffness_points, 2))
            for v in np.linspace(box.speed_lo_mps, box.speed_mps, max(speed_points, 2))]
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


def reference_stability_lmi(vehicle: VehicleParams, k_m, box: OperatingBox, filter_gain: float,
                            lmi_margin: float) -> bool:
    """Condition b certified: one P with ``M_i' P + P M_i <= -eps I``, ``P >= I`` at 4 corners.

    The reference matrix is affine in ``(C, C/V, 1/V)`` (``theta`` carries ``C_hat / V``), i.e.
    bilinear in ``(C, 1/V)``: each point of ``[C_lo, C_hi] x [V_lo, V]`` is the bilinear
    interpolation (a convex combination) of the four corner matrices, so a common Lyapunov
    matrix at the corners certifies every C and every speed in ``[V_lo, V]``.
    """
    interval, speed_lo_mps, speed_mps = box.interval, box.speed_lo_mps, box.speed_mps
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
                               stiffness_points: int, law: str = GRADIENT) -> float:
    """Condition c: ``lane margin - max_C |e1|`` at the adaptive equilibrium of the law (m)."""
    c_hat = 0.5 * (interval[0] + interval[1])
    grid = np.linspace(interval[0], interval[1], max(stiffness_points, 2))
    if law == GRADIENT:
        states = adaptive_steady_states(vehicle, k_m, c_hat, grid,
                                        SteadyCornering(speed_mps, 1.0 / design_radius_m),
                                        q_ad_diag)
    else:
        states = piecewise_constant_steady_states(vehicle, k_m, c_hat, grid, speed_mps,
                                                  1.0 / design_radius_m)
    worst = max(abs(state.lateral_offset_m) for state in states)
    return vehicle.lane_margin_m - worst


def steady_state_slip_angles(vehicle: VehicleParams, stiffness: float, speed_mps: float,
                             radius_m: float) -> tuple[float, float]:
    """Front and rear slip angles (rad) of the single track cornering at ``a_y = V^2 / R``.

    Steady cornering: the axle forces carry the centripetal force, ``F_f + F_r = m a_y``, and
    cancel in yaw, ``F_f l_f = F_r l_r``; so ``F_f = m a_y l_r / (l_f + l_r)`` and
    ``F_r = m a_y l_f / (l_f + l_r)``. Each axle has two tires, ``F_f = 2 C alpha_f`` and
    ``F_r = 2 rho C alpha_r`` (``rho``: the vehicle's rear stiffness ratio), giving
    ``alpha_f = m l_r a_y / (2 C (l_f + l_r))`` and ``alpha_r = m l_f a_y / (2 rho C (l_f + l_r))``
    (small angles, linear tires).
    """
    a_y = speed_mps**2 / radius_m
    wheelbase = vehicle.lf_m + vehicle.lr_m
    alpha_f = vehicle.mass_kg * vehicle.lr_m * a_y / (2.0 * stiffness * wheelbase)
    alpha_r = vehicle.mass_kg * vehicle.lf_m * a_y / (2.0 * vehicle.rear_stiffness_ratio
                                                      * stiffness * wheelbase)
    return alpha_f, alpha_r


def tire_stiffness_lo(stiffness_lo: float, normalised_slip_max: float) -> float:
    """Least effective (secant) stiffness of a Fiala tire whose slip stays within the bound.

    ``C_lo (1 - z_b + z_b^2 / 3)`` (:func:`drake_cert.dynamics.fiala_secant_ratio`): with the
    slip bound scaled by ``mu F_z / C`` (``|tan a| <= 3 z_b mu F_z / C``) the ratio is the same
    for every C, mu and load, so the widened interval is ``[C_lo ratio(z_b), C_hi]`` (N/rad).
    """
    return float(stiffness_lo * fiala_secant_ratio(normalised_slip_max))


def steady_state_normalised_slip(friction_mu_lo: float, speed_mps: float,
                                 radius_m: float) -> float:
    """Normalised slip ``z`` of every tire in steady cornering at ``a_y = V^2 / R`` (Fiala).

    On static loads both axles carry the same share of their grip: the axle forces
    ``m a_y l_r / L`` and ``m a_y l_f / L`` over the axle grip ``mu m g l_r / L`` and
    ``mu m g l_f / L`` are both ``u = a_y / (mu g)``; the Fiala tire gives that utilisation at
    ``z = 1 - (1 - u)^(1/3)`` (1 when ``u >= 1``: the car slides). Uses the least friction,
    so a label with more grip has less slip. Dimensionless.
    """
    utilisation = speed_mps**2 / radius_m / (friction_mu_lo * GRAVITY_MPS2)
    return float(fiala_normalised_slip_at_utilisation(min(utilisation, 1.0)))


def grip_margins(friction_mu_lo: float, speed_mps: float, radius_m: float,
                 normalised_slip_max: float, lateral_accel_fraction: float
                 ) -> tuple[float, float]:
    """Condition d: ``(slip margin (normalised), lateral-acceleration margin (m/s^2))``.

    ``z_b - z(V)`` with :func:`steady_state_normalised_slip`: the steady slip lies inside the
    range whose secant stiffness the certified interval covers; and
    ``fraction mu_lo g - V^2 / R``.
    """
    slip = steady_state_normalised_slip(friction_mu_lo, speed_mps, radius_m)
    a_y = speed_mps**2 / radius_m
    return (normalised_slip_max - slip,
            lateral_accel_fraction * friction_mu_lo * GRAVITY_MPS2 - a_y)


def grip_speed_limit_mps(friction_mu_lo: float, radius_m: float, normalised_slip_max: float,
                         lateral_accel_fraction: float) -> float:
    """Largest speed meeting condition d (both margins grow monotonically worse with V^2).

    ``a_y <= mu_lo g min(fraction, 1 - (1 - z_b)^3)``, i.e. ``V = sqrt(a_y R)``.
    """
    utilisation = min(lateral_accel_fraction, 1.0 - (1.0 - min(normalised_slip_max, 1.0))**3)
    return float(np.sqrt(utilisation * friction_mu_lo * GRAVITY_MPS2 * radius_m))


def vehicle_lateral_accel_limits(vehicle: VehicleParams, settings) -> dict[str, float]:
    """Condition e: the steady lateral accelerations (m/s^2) the vehicle limits allow, keyed
    ``rollover`` (``rollover_fraction g t / (2 h)``, when the vehicle gives h and t) and
    ``comfort`` (``lateral_accel_limit_mps2``, when set); empty when neither applies."""
    syn = settings.synthesis
    limits = {}
    if vehicle.static_stability_factor is not None:
        limits[ROLLOVER] = syn.rollover_fraction * GRAVITY_MPS2 * vehicle.static_stability_factor
    if syn.lateral_accel_limit_mps2 is not None:
        limits[COMFORT] = float(syn.lateral_accel_limit_mps2)
    return limits


def vehicle_limit_margins(vehicle: VehicleParams, settings, speed_mps: float) -> dict[str, float]:
    """Condition e as margins on the design curve: ``limit - V^2 / R`` (m/s^2) under the keys
    ``rollover_lateral_accel_mps2`` and ``comfort_lateral_accel_mps2`` that apply."""
    a_y = speed_mps**2 / settings.synthesis.design_radius_m
    return {f"{name}_lateral_accel_mps2": limit - a_y
            for name, limit in vehicle_lateral_accel_limits(vehicle, settings).items()}


def vehicle_speed_limit_mps(vehicle: VehicleParams, settings) -> tuple[float, str]:
    """The largest speed condition e allows on the design curve and the limit that sets it:
    ``(sqrt(a_y R), name)``, or ``(inf, "")`` without vehicle limits."""
    limits = vehicle_lateral_accel_limits(vehicle, settings)
    if not limits:
        return float("inf"), ""
    name = min(limits, key=limits.get)
    return float(np.sqrt(limits[name] * settings.synthesis.design_radius_m)), name

