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
search tries. Solved with cvxpy + Clarabel (:func:`solve_common_lyapunov_gains`: a solution is
kept when its matrix proves the decay, whatever the solver's status, and the program is rescaled
once before giving up); the gains pass the grid check of 5.1, and
:mod:`drake_cert.synthesis.switching` recomputes the common certificate from the final gains.
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
    solve_sdp_status,
)
from drake_cert.synthesis.lyapunov_rate import certified_rate

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


@dataclasses.dataclass(frozen=True)
class JointSolve:
    """What the joint program returned and how it was accepted (the table's provenance).

    ``gains``: one ``k_i`` per box, or None (no certified solution: the table falls back to
    separate gains). ``status``: Clarabel's status of the solve that was kept (or of the last
    one tried). ``rescaled``: solved in balanced coordinates (module docstring). ``proved_rate``:
    the least decay rate (1/s) the returned ``X`` proves over every corner of every box for the
    returned gains (:func:`corner_rate`), ``nan`` without a solution. ``condition_number``:
    ``cond X`` of the original coordinates.
    """

    gains: list[np.ndarray] | None
    status: str
    rescaled: bool = False
    proved_rate: float = float("nan")
    condition_number: float = float("nan")

    def as_dict(self) -> dict:
        """Plain mapping for the design file's provenance."""
        return {"solver_status": self.status, "rescaled": self.rescaled,
                "accepted": self.gains is not None,
                "proved_decay_per_s": float(self.proved_rate),
                "lyapunov_condition_number": float(self.condition_number)}


def corner_rate(vehicle: VehicleParams, boxes: list[GainBox], x: np.ndarray,
                gains: list[np.ndarray]) -> float:
    """The least decay rate (1/s) that ``P = X^-1`` proves for ``A(C, V) - b(C) k_i`` over the
    four corners of every box i (:func:`drake_cert.synthesis.lyapunov_rate.certified_rate`;
    corners suffice, the loop is affine in ``(C, C/V)``), ``-inf`` when ``X`` is not positive
    definite. The a-posteriori check of a solve, independent of the solver's status."""
    x = 0.5 * (x + x.T)
    if not np.all(np.isfinite(x)) or np.linalg.eigvalsh(x).min() <= 0.0:
        return -np.inf
    p = np.linalg.inv(x)
    p = 0.5 * (p + p.T)
    rate = np.inf
    for box, k_m in zip(boxes, gains, strict=True):
        for c, v in corner_points(box.interval, box.speed_lo_mps, box.speed_hi_mps):
            a, b, _ = lateral_error_dynamics(vehicle, c, v)
            rate = min(rate, certified_rate(p, a - np.outer(b, k_m)))
    return float(rate)


def _joint_program(vehicle, boxes, settings, scale: np.ndarray):
    """The joint LMI in coordinates ``z = D s``, ``D = diag(scale)`` (``A -> D A D^-1``,
    ``b -> D b``); returns the problem, ``X_z`` and the ``Y_z``."""
    syn = settings.synthesis
    eye = np.eye(4)
    d, d_inv = np.diag(scale), np.diag(1.0 / scale)
    x = cp.Variable((4, 4), symmetric=True)
    constraints = [x >> eye]
    ys, ts = [], []
    for box in boxes:
        y, t = cp.Variable((1, 4)), cp.Variable((1, 1))
        ys.append(y)
        ts.append(t)
        for c, v in corner_points(box.interval, box.speed_lo_mps, box.speed_hi_mps):
            a, b, _ = lateral_error_dynamics(vehicle, c, v)
            a, b = d @ a @ d_inv, (d @ b).reshape(4, 1)
            lyap = a @ x + x @ a.T - b @ y - y.T @ b.T + 2.0 * syn.decay_rate * x
            constraints.append(0.5 * (lyap + lyap.T) << -syn.lmi_margin * eye)
        constraints.append(cp.bmat([[t, y], [y.T, x]]) >> 0)
    return cp.Problem(cp.Minimize(sum(t[0, 0] for t in ts)), constraints), x, ys


def solve_common_lyapunov_gains(vehicle: VehicleParams, boxes: list[GainBox],
                                settings: Settings) -> JointSolve:
    """The joint program of the module docstring, kept whenever its solution certifies.

    A solve is kept when Clarabel reports it optimal, or optimal but inaccurate and the
    returned ``X`` still proves the decay rate at every corner for the returned gains
    (:func:`corner_rate` >= ``decay_rate``: the certificate is the matrix, not the status).
    When the first solve is kept by neither, the program is solved once more in balanced
    coordinates ``z = D s``, ``D = diag(X_ii)^-1/2`` from that first solution (the states mix
    metres and radians; ``cond X`` reaches 10^3 for tall SUVs), and its gains ``k = k_z D``
    are checked the same way in the original coordinates. A kept gain must also pass the
    eigenvalue grid check of 5.1 on its box."""
    first, x = _solve_in(vehicle, boxes, settings, np.ones(4))
    if first.gains is not None or x is None:
        return first
    diag = np.diag(x)
    if not (np.all(np.isfinite(diag)) and np.all(diag > 0.0)):
        return first
    second, _ = _solve_in(vehicle, boxes, settings, 1.0 / np.sqrt(diag))
    return second if second.gains is not None else first


def _solve_in(vehicle, boxes, settings, scale) -> tuple[JointSolve, np.ndarray | None]:
    """One solve in the coordinates ``z = diag(scale) s``: the result (gains None unless kept,
    :func:`solve_common_lyapunov_gains`) and ``X`` in the original coordinates (None when the
    solver returned none)."""
    syn = settings.synthesis
    problem, x_z, ys = _joint_program(vehicle, boxes, settings, scale)
    status = solve_sdp_status(problem)
    rescaled = not np.all(scale == 1.0)
    if x_z.value is None or any(y.value is None for y in ys):
        return JointSolve(None, status, rescaled), None
    d_inv = np.diag(1.0 / scale)
    x = d_inv @ x_z.value @ d_inv  # X = D^-1 X_z D^-1
    gains = [np.linalg.solve(x_z.value, y.value.reshape(4)) * scale for y in ys]  # k_z D
    rate = corner_rate(vehicle, boxes, x, gains)
    cond_x = float(np.linalg.cond(0.5 * (x + x.T)))
    kept = status == cp.OPTIMAL or (status == cp.OPTIMAL_INACCURATE and rate >= syn.decay_rate)
    for box, k_m in zip(boxes, gains, strict=True):  # the grid check of 5.1, outside the solver
        abscissa = closed_loop_spectral_abscissa(vehicle, k_m, box.interval, box.speed_lo_mps,
                                                 box.speed_hi_mps)
        kept = kept and abscissa <= -syn.decay_rate + GRID_CHECK_TOLERANCE
    return JointSolve(gains if kept else None, status, rescaled, rate, cond_x), x


def common_lyapunov_gains(vehicle: VehicleParams, boxes: list[GainBox],
                          settings: Settings) -> list[np.ndarray] | None:
    """One ``k_i`` (4,) per box, all certified by one ``X = P^-1`` (module docstring) at
    ``settings.synthesis.decay_rate``; None when no solve certifies
    (:func:`solve_common_lyapunov_gains`) or a gain fails the eigenvalue grid check of 5.1."""
    return solve_common_lyapunov_gains(vehicle, boxes, settings).gains
