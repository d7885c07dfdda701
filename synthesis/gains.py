"""State-feedback gain ``k_m`` from a four-corner LMI (DESIGN 5.1; paper section IV-B3).

``A(C, V) = A0 + C A1 + (C/V) A2`` and ``b(C) = C b1`` are affine in ``(C, C/V)``; the image of
the box ``[C_lo, C_hi] x [V_lo, V_hi]`` in that plane is the convex trapezoid spanned by the
four corners, so an LMI that holds at the corners holds on the whole box. With
``X = P^-1 >= I`` and ``Y = k_m X`` (congruence of ``(A - b k_m)' P + P (A - b k_m) + 2 alpha P``
by X) the decay condition "``A - b k_m + alpha I`` is Hurwitz with the common Lyapunov matrix
P" reads at each corner i:

    A_i X + X A_i' - b_i Y - Y' b_i' + 2 alpha X <= -eps I,

a strict inequality made non-strict by the margin ``eps`` and the normalisation ``X >= I``.
The gain size is bounded by ``[[t, Y], [Y', X]] >= 0`` (``Y X^-1 Y' <= t``, hence
``||k_m||^2 = Y X^-2 Y' <= t`` as ``X >= I``), and ``t`` is minimised. The result is checked
outside the solver: ``max Re eig(A(C, V) - b(C) k_m) <= -alpha`` on a dense (C, V) grid.
"""

import warnings

import cvxpy as cp
import numpy as np

from drake_cert.config import SynthesisSettings, VehicleParams
from drake_cert.dynamics import lateral_error_dynamics
from drake_cert.errors import InfeasibleDesign

GRID_CHECK_POINTS = (21, 26)  # (C, V) points of the eigenvalue check after the solve
GRID_CHECK_TOLERANCE = 1.0e-6  # 1/s slack on the decay rate in the grid check
SPEED_BISECTION_TOLERANCE_MPS = 0.25



def solve_sdp_status(problem: cp.Problem) -> str:
    """Solve ``problem`` with Clarabel; return cvxpy's status (``"solver_error"`` when the
    solver fails). A caller that accepts ``optimal_inaccurate`` must check the solution itself
    (:func:`drake_cert.synthesis.joint_gains.solve_common_lyapunov_gains` does)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            problem.solve(solver=cp.CLARABEL)
    except cp.error.SolverError:
        return "solver_error"
    return str(problem.status)


def solve_sdp(problem: cp.Problem) -> bool:
    """Solve ``problem`` with Clarabel; True only when the status is OPTIMAL.

    Solver failures and "may be inaccurate" warnings count as not solved (the status decides).
    """
    return solve_sdp_status(problem) == cp.OPTIMAL

def corner_points(interval, speed_lo_mps: float, speed_hi_mps: float) -> list[tuple[float, float]]:
    """The four (C, V) corners of ``interval x [speed_lo, speed_hi]``."""
    lo, hi = interval
    return [(c, v) for c in (lo, hi) for v in (speed_lo_mps, speed_hi_mps)]


def state_feedback_lmi(vehicle: VehicleParams, interval, speed_lo_mps: float,
                       speed_hi_mps: float, decay_rate: float, lmi_margin: float):
    """Solve the corner LMI (module docstring) with Clarabel.

    Returns ``k_m`` (4,) with ``u = -k_m s``, or ``None`` when the solver does not report an
    optimal solution (infeasible, or numerically unreliable).
    """
    x = cp.Variable((4, 4), symmetric=True)  # X = P^-1
    y = cp.Variable((1, 4))  # Y = k_m X
    t = cp.Variable((1, 1))  # bound on ||k_m||^2
    eye = np.eye(4)
    constraints = [x >> eye]
    for c, v in corner_points(interval, speed_lo_mps, speed_hi_mps):
        a, b, _ = lateral_error_dynamics(vehicle, c, v)
        b = b.reshape(4, 1)
        lyap = a @ x + x @ a.T - b @ y - y.T @ b.T + 2.0 * decay_rate * x
        constraints.append(0.5 * (lyap + lyap.T) << -lmi_margin * eye)
    constraints.append(cp.bmat([[t, y], [y.T, x]]) >> 0)
    problem = cp.Problem(cp.Minimize(t[0, 0]), constraints)
    if not solve_sdp(problem) or x.value is None:
        return None
    return np.linalg.solve(x.value, y.value.reshape(4))  # k_m = Y X^-1 (X symmetric)


def closed_loop_spectral_abscissa(vehicle: VehicleParams, k_m, interval, speed_lo_mps: float,
                                  speed_hi_mps: float, points=GRID_CHECK_POINTS) -> float:
    """``max Re eig(A(C, V) - b(C) k_m)`` over a uniform (C, V) grid incl. the ends (1/s)."""
    k_m = np.asarray(k_m, dtype=float).reshape(4)
    mats = []
    for c in np.linspace(interval[0], interval[1], points[0]):
        for v in np.linspace(speed_lo_mps, speed_hi_mps, points[1]):
            a, b, _ = lateral_error_dynamics(vehicle, c, v)
            mats.append(a - np.outer(b, k_m))
    return float(np.linalg.eigvals(np.array(mats)).real.max())


def synthesize_state_feedback(vehicle: VehicleParams, interval,
                              settings: SynthesisSettings) -> tuple[np.ndarray, float]:
    """One ``k_m`` for the stiffness interval, valid from ``speed_min`` up to ``speed_hi``.

    Tries ``speed_hi = speed_max``; if the corner LMI is infeasible there, bisects for the
    largest feasible ``speed_hi`` (to 0.25 m/s). Returns ``(k_m, speed_hi_mps)``; raises
    :class:`InfeasibleDesign` if no speed range is feasible or the grid check fails.
    """
    v_lo, v_max = settings.speed_min_mps, settings.speed_max_mps

    def solve(v_hi):
        return state_feedback_lmi(vehicle, interval, v_lo, v_hi, settings.decay_rate,
                                  settings.lmi_margin)

    k_m, v_hi = solve(v_max), v_max
    if k_m is None:
        k_lo = solve(v_lo)
        if k_lo is None:
            raise InfeasibleDesign(
                f"gain LMI infeasible for stiffness interval {interval} N/rad even at "
                f"{v_lo} m/s (decay rate {settings.decay_rate}/s)")
        good, bad, k_m = v_lo, v_max, k_lo
        while bad - good > SPEED_BISECTION_TOLERANCE_MPS:
            mid = 0.5 * (good + bad)
            k_mid = solve(mid)
            if k_mid is None:
                bad = mid
            else:
                good, k_m = mid, k_mid
        v_hi = good
    abscissa = closed_loop_spectral_abscissa(vehicle, k_m, interval, v_lo, v_hi)
    if abscissa > -settings.decay_rate + GRID_CHECK_TOLERANCE:
        raise InfeasibleDesign(
            f"gain LMI solution fails the grid check for interval {interval} N/rad: "
            f"max Re eig(A - b k_m) = {abscissa:.6g}/s > -{settings.decay_rate}/s")
    return k_m, float(v_hi)
