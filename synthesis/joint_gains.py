"""Gains of every design from one LMI with a common Lyapunov matrix (docs/design.md 5.6).

Each design's state feedback ``k_i`` must make ``A(C, V) - b(C) k_i`` decay at rate alpha on
the design's *gain box* ``B_i = [C_lo ratio(z_max), C_hi] x [speed_min, V_grip,i + 1 m/s]``:
its label interval widened for the tire at the largest slip bound (5.3d) and the speeds up to
the grip limit of its least friction, above which no safe speed can lie (5.3d caps every design
there), plus :data:`GAIN_BOX_SPEED_MARGIN_MPS` for the speed tracking (the car is at most at
the safe speed of the design in force, 6.2, up to the tracking error).
With ``X = P^-1 >= I`` shared by all designs and ``Y_i = k_i X`` one per box, the corner
inequalities of 5.1

    A_c X + X A_c' - b_c Y_i - Y_i' b_c' + 2 alpha X <= -eps I     (every corner c of B_i)

are linear in ``(X, Y_1, ..., Y_n)``: one convex program certifies every design's loop with the
same quadratic Lyapunov function ``s' P s``, so the switched reference loops decay at rate
alpha whatever design is in force and however often it switches. ``[[t_i, Y_i], [Y_i', X]] >= 0``
bounds ``||k_i||^2 <= t_i`` and ``sum t_i`` is minimised, as 5.1 minimises one t.

Smaller slip bounds and lower speeds give sub-boxes of ``B_i`` (the image of a sub-box in the
``(C, C/V)`` plane lies in the image of the box), so ``k_i`` serves every slip bound the speed
search tries. Solved with cvxpy + Clarabel; the caller checks the result again on grids (5.5)
and :mod:`drake_cert.synthesis.switching` recomputes the common certificate from the final gains.
"""

import dataclasses

import cvxpy as cp
import numpy as np

from drake_cert.config import Settings, VehicleParams
from drake_cert.dynamics import lateral_error_dynamics
from drake_cert.synthesis.conditions import grip_speed_limit_mps, tire_stiffness_lo
from drake_cert.synthesis.gains import (
    GRID_CHECK_TOLERANCE,
    closed_loop_spectral_abscissa,
    corner_points,
    solve_sdp,
)

JOINT = "joint"  # one LMI, common Lyapunov matrix (the default)
SEPARATE = "separate"  # one LMI per interval, each with its own Lyapunov matrix
GAIN_SYNTHESES = (JOINT, SEPARATE)
GAIN_BOX_SPEED_MARGIN_MPS = 1.0  # the gain box reaches this far above the grip speed (m/s)


@dataclasses.dataclass(frozen=True)
class GainBox:
    """Where one gain must hold: stiffness ``interval`` (N/rad) x ``[speed_lo, speed_hi]``
    (m/s)."""

    interval: tuple[float, float]
    speed_lo_mps: float
    speed_hi_mps: float


def gain_box(interval: tuple[float, float], friction_mu_lo: float,
             settings: Settings) -> GainBox:
    """The gain box of a design (module docstring): the label ``interval`` (N/rad) widened
    at ``normalised_slip_max``, speeds from ``speed_min`` to the grip speed of
    ``friction_mu_lo`` at that slip bound on the design radius plus
    :data:`GAIN_BOX_SPEED_MARGIN_MPS` (at most ``speed_max``)."""
    syn = settings.synthesis
    lo = tire_stiffness_lo(float(interval[0]), syn.normalised_slip_max)
    top = grip_speed_limit_mps(friction_mu_lo, syn.design_radius_m, syn.normalised_slip_max,
                               syn.lateral_accel_fraction)
    top = min(max(top + GAIN_BOX_SPEED_MARGIN_MPS, syn.speed_min_mps), syn.speed_max_mps)
    return GainBox((lo, float(interval[1])), syn.speed_min_mps, float(top))


def common_lyapunov_gains(vehicle: VehicleParams, boxes: list[GainBox],
                          settings: Settings) -> list[np.ndarray] | None:
    """One ``k_i`` (4,) per box, all certified by one ``X = P^-1`` (module docstring) at
    ``settings.synthesis.decay_rate``; None when Clarabel reports no optimal solution (the
    joint program is infeasible, or numerically unreliable) or a gain fails the eigenvalue
    grid check of 5.1 on its box."""
    syn = settings.synthesis
    eye = np.eye(4)
    x = cp.Variable((4, 4), symmetric=True)
    constraints = [x >> eye]
    ys, ts = [], []
    for box in boxes:
        y, t = cp.Variable((1, 4)), cp.Variable((1, 1))
        ys.append(y)
        ts.append(t)
        for c, v in corner_points(box.interval, box.speed_lo_mps, box.speed_hi_mps):
            a, b, _ = lateral_error_dynamics(vehicle, c, v)
            b = b.reshape(4, 1)
            lyap = a @ x + x @ a.T - b @ y - y.T @ b.T + 2.0 * syn.decay_rate * x
            constraints.append(0.5 * (lyap + lyap.T) << -syn.lmi_margin * eye)
        constraints.append(cp.bmat([[t, y], [y.T, x]]) >> 0)
    problem = cp.Problem(cp.Minimize(sum(t[0, 0] for t in ts)), constraints)
    if not solve_sdp(problem) or x.value is None:
        return None
    gains = [np.linalg.solve(x.value, y.value.reshape(4)) for y in ys]
    for box, k_m in zip(boxes, gains, strict=True):  # the grid check of 5.1, outside the solver
        abscissa = closed_loop_spectral_abscissa(vehicle, k_m, box.interval, box.speed_lo_mps,
                                                 box.speed_hi_mps)
        if abscissa > -syn.decay_rate + GRID_CHECK_TOLERANCE:
            return None
    return gains
