"""Nominal model and the matched/unmatched split of the stiffness uncertainty (DESIGN 4).

With nominal stiffness ``C_hat`` (midpoint of the certified interval), ``b_m = b(C_hat)``,
``A_m = A(C_hat, V) - b_m k_m`` (the paper's ``A - k_m s`` read as ``A - b_m k_m``) and
``w = C / C_hat``, ``dA = A(C, V) - A(C_hat, V)``:

    A(C) - b(C) k_m = A_m + b_m theta' + (I - b_m b_m^+) dA,
    theta' = b_m^+ dA - (w - 1) k_m,

and the curvature input splits the same way: ``sigma = (w - 1) u_ff + b_m^+ (g - g_hat)
psidot_des`` is matched, ``(I - b_m b_m^+)(g - g_hat) psidot_des`` is not.
"""

import dataclasses

import numpy as np

from drake_cert.config import VehicleParams
from drake_cert.dynamics import lateral_error_dynamics

E1_SELECTOR = np.array([1.0, 0.0, 0.0, 0.0])  # c: the output is the lateral offset e1


@dataclasses.dataclass(frozen=True)
class NominalModel:
    """Nominal closed loop at (C_hat, V): ``A_m`` Hurwitz, ``b_m``, ``g_hat``."""

    a_m: np.ndarray  # (4, 4)
    b_m: np.ndarray  # (4,)
    g_hat: np.ndarray  # (4,)
    stiffness_n_per_rad: float  # C_hat
    speed_mps: float  # V


def nominal_model(vehicle: VehicleParams, nominal_stiffness, speed_mps, k_m) -> NominalModel:
    """``A_m = A(C_hat, V) - b_m k_m`` and ``b_m = b(C_hat)`` (paper eq. l1dynamic)."""
    a, b, g = lateral_error_dynamics(vehicle, nominal_stiffness, speed_mps)
    k_m = np.asarray(k_m, dtype=float).reshape(4)
    return NominalModel(a - np.outer(b, k_m), b, g, float(nominal_stiffness), float(speed_mps))


def pseudo_inverse(b_m: np.ndarray) -> np.ndarray:
    """``b_m^+ = b_m' / (b_m' b_m)`` (a row vector, shape (4,))."""
    return b_m / float(b_m @ b_m)


def matched_uncertainty(vehicle: VehicleParams, stiffness, nominal_stiffness, speed_mps, k_m):
    """Return ``(w, theta, unmatched)`` for the true stiffness C (DESIGN 4).

    ``w = C / C_hat`` (input gain), ``theta`` (4,) the matched state gain and ``unmatched``
    (4, 4) = ``(I - b_m b_m^+) dA``, so that ``A(C) - b(C) k_m = A_m + b_m theta' + unmatched``.
    """
    k_m = np.asarray(k_m, dtype=float).reshape(4)
    a, _, _ = lateral_error_dynamics(vehicle, stiffness, speed_mps)
    a_hat, b_m, _ = lateral_error_dynamics(vehicle, nominal_stiffness, speed_mps)
    w = stiffness / nominal_stiffness
    d_a = a - a_hat
    b_pinv = pseudo_inverse(b_m)
    theta = b_pinv @ d_a - (w - 1.0) * k_m
    unmatched = (np.eye(4) - np.outer(b_m, b_pinv)) @ d_a
    return w, theta, unmatched


def curvature_feedforward_gain(nominal: NominalModel) -> float:
    """Gain ``k_ff`` with ``u_ff = k_ff * psidot_des``: nominal steady state e1 = 0.

    ``u_ff = -(c' A_m^-1 g_hat psidot) / (c' A_m^-1 b_m)`` (DESIGN 4), c the e1 selector.
    """
    ainv_g = np.linalg.solve(nominal.a_m, nominal.g_hat)
    ainv_b = np.linalg.solve(nominal.a_m, nominal.b_m)
    return -float(E1_SELECTOR @ ainv_g) / float(E1_SELECTOR @ ainv_b)


def reference_gain(nominal: NominalModel) -> float:
    """``k_g = -1 / (c' A_m^-1 b_m)`` (paper, after eq. filterinput)."""
    return -1.0 / float(E1_SELECTOR @ np.linalg.solve(nominal.a_m, nominal.b_m))


def matched_disturbance(vehicle: VehicleParams, stiffness, nominal_stiffness, speed_mps,
                        k_m, psidot_des) -> float:
    """``sigma = (w - 1) u_ff + b_m^+ (g(C) - g_hat) psidot_des`` (DESIGN 4)."""
    nom = nominal_model(vehicle, nominal_stiffness, speed_mps, k_m)
    _, _, g = lateral_error_dynamics(vehicle, stiffness, speed_mps)
    w = stiffness / nominal_stiffness
    u_ff = curvature_feedforward_gain(nom) * psidot_des
    return float((w - 1.0) * u_ff + pseudo_inverse(nom.b_m) @ (g - nom.g_hat) * psidot_des)


def stiffness_grid(lo: float, hi: float, points: int) -> np.ndarray:
    """Uniform grid over [lo, hi] including both ends."""
    return np.linspace(lo, hi, max(int(points), 2))


def output_equivalent_row(nominal: NominalModel) -> np.ndarray:
    """``r = c' A_m^-1 / (c' A_m^-1 b_m)`` (4,): ``r b_m = 1``; the piecewise-constant law feeds
    the filter ``r sigma_hat``, the input with the same steady-state e1 as the 4-vector
    estimate (Hovakimyan & Cao sec. 3.3 at DC; the controller's own copy is in systems)."""
    c_ainv = np.linalg.solve(nominal.a_m.T, E1_SELECTOR)
    return c_ainv / float(c_ainv @ nominal.b_m)
