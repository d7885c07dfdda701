"""Linear lateral error dynamics (Rajamani eq. 2.45; paper eq. (dynamic), section IV-A).

State ``s = [e1, e1dot, e2, e2dot]`` (m, m/s, rad, rad/s): lateral offset from the lane
centre (> 0 left) and heading error. ``sdot = A(C, V) s + b(C) u + g(C, V) psidot_des`` with
front steering ``u`` (rad, > 0 left) and ``psidot_des = V * kappa`` (rad/s; kappa > 0 left
turn). C is the cornering stiffness of ONE front tire (N/rad), a rear tire's is
``C_r = rho C`` with the vehicle's fixed ``rho = rear_stiffness_ratio`` (1 for one scale on
both axles); the model's factor 2 counts the two tires of an axle. A is affine in (C, C/V); b
is C times a constant vector.

Every function accepts floats or numpy arrays of ``pydrake.symbolic.Expression`` for C and V,
so the same equations build the C++-evaluated ``SymbolicVectorSystem`` plants.
"""

import numpy as np

from drake_cert.config import VehicleParams


def lateral_error_dynamics(vehicle: VehicleParams, stiffness_n_per_rad, speed_mps):
    """Return ``(A, b, g)`` of eq. 2.45 for front per-tire stiffness C and speed V.

    Assumes V > 0 (the model has 1/V terms; designs use V >= 5 m/s). Shapes (4, 4), (4,), (4,).
    """
    m, iz = vehicle.mass_kg, vehicle.yaw_inertia_kg_m2
    lf, lr = vehicle.lf_m, vehicle.lr_m
    c, v = stiffness_n_per_rad, speed_mps
    cf, cr = c, vehicle.rear_stiffness_ratio * c
    dtype = object if _is_symbolic(c) or _is_symbolic(v) else float
    a = np.zeros((4, 4), dtype=dtype)
    a[0, 1] = 1.0
    a[1, 1] = -2.0 * (cf + cr) / (m * v)
    a[1, 2] = 2.0 * (cf + cr) / m
    a[1, 3] = 2.0 * (-cf * lf + cr * lr) / (m * v)
    a[2, 3] = 1.0
    a[3, 1] = -2.0 * (cf * lf - cr * lr) / (iz * v)
    a[3, 2] = 2.0 * (cf * lf - cr * lr) / iz
    a[3, 3] = -2.0 * (cf * lf**2 + cr * lr**2) / (iz * v)
    b = np.array([0.0, 2.0 * cf / m, 0.0, 2.0 * cf * lf / iz], dtype=dtype)
    g = np.array([0.0, -2.0 * (cf * lf - cr * lr) / (m * v) - v, 0.0,
                  -2.0 * (cf * lf**2 + cr * lr**2) / (iz * v)], dtype=dtype)
    return a, b, g


def affine_parts(vehicle: VehicleParams):
    """Constant matrices with ``A(C, V) = C * A1 + (C / V) * A2 + A0`` and ``b(C) = C * b1``.

    Used by the corner LMIs: (C, C/V) enters affinely, so convex combinations of corners
    cover the interval. Returns ``(A0, A1, A2, b1)``.
    """
    a_c1_v1, b1, _ = lateral_error_dynamics(vehicle, 1.0, 1.0)
    a_c1_vbig, _, _ = lateral_error_dynamics(vehicle, 1.0, 1.0e12)
    a0 = np.zeros((4, 4))
    a0[0, 1] = a0[2, 3] = 1.0
    a1 = a_c1_vbig - a0  # terms in C alone (the 1/V part vanishes as V -> inf)
    a1[np.abs(a1) < 1e-9] = 0.0
    a2 = a_c1_v1 - a0 - a1
    return a0, a1, a2, b1


def yaw_rate_command(speed_mps, curvature_per_m):
    """Desired yaw rate ``psidot_des = V * kappa`` (rad/s)."""
    return speed_mps * curvature_per_m


def _is_symbolic(x) -> bool:
    return not isinstance(x, (int, float, np.floating, np.integer))


# --------------------------------------------------------------------------- Fiala tire

def fiala_secant_ratio(normalised_slip):
    """Secant stiffness of the Fiala brush tire over its linear stiffness, ``F / (C tan a) / 1``.

    With the normalised slip ``z = C |tan a| / (3 mu F_z)`` (0: free rolling, 1: the contact
    patch starts to slide entirely) the Fiala force is ``|F| = mu F_z (3z - 3z^2 + z^3)`` for
    ``z <= 1`` and ``mu F_z`` beyond, so ``|F| / (C |tan a|) = 1 - z + z^2 / 3`` on ``[0, 1]``
    (decreasing from 1 to 1/3) and ``1 / (3 z)`` beyond. A tire whose slip stays within
    ``z <= z_b`` acts as a linear tire whose stiffness lies in ``[C (1 - z_b + z_b^2/3), C]``.
    Floats or numpy arrays (dimensionless).
    """
    z = np.abs(np.asarray(normalised_slip, dtype=float))
    inside = 1.0 - z + z * z / 3.0
    return np.where(z <= 1.0, inside, 1.0 / (3.0 * np.maximum(z, 1.0)))


def fiala_normalised_slip_at_utilisation(utilisation):
    """Normalised slip ``z`` at which the Fiala force reaches ``utilisation * mu F_z``.

    Inverse of ``u = 3z - 3z^2 + z^3 = 1 - (1 - z)^3`` on ``[0, 1]``: ``z = 1 - (1 - u)^(1/3)``.
    ``utilisation`` in ``[0, 1]`` (dimensionless); 1 gives 1 (full sliding).
    """
    u = np.clip(np.asarray(utilisation, dtype=float), 0.0, 1.0)
    return 1.0 - np.cbrt(1.0 - u)
