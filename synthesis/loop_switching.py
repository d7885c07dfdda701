"""Switching among designs with the L1 filter state included (docs/design.md 5.6 (b)).

The reference system of a design (condition 5.3b,
:func:`drake_cert.synthesis.conditions.reference_system_matrix`) is the L1 loop with the ideal
estimate: plant and low-pass filter, state ``z = [s, u_ad]`` (m, m/s, rad, rad/s; rad),
``z' = R_i(C, V) z`` plus the known inputs (feedforward and road). The certificate is posed in
the *steering coordinates* ``zeta = [s, u - u_ff] = T_i z``, ``T_i = [[I, 0], [-k_i', 1]]``
(:func:`steering_coordinates`): at a design switch the piecewise-constant law keeps the
steering and carries its estimate over (``systems/l1_law.py``,
``piecewise_constant_hand_over``), so ``s`` and ``u`` are continuous, and ``zeta`` moves only
by the change of feedforward (0 on a straight road). One matrix ``P_z`` with

    M_i(C, V)' P_z + P_z M_i(C, V) + 2 lambda_z P_z <= 0,    M_i = T_i R_i T_i^-1,

for every design i of a family and every (C, V) of its range makes ``zeta' P_z zeta`` fall at
rate ``2 lambda_z`` whatever design is in force and however often it switches.

Where it is checked. For a fixed speed ``M_i`` is affine in C (``theta``, the unmatched part
and ``w`` are; the piecewise-constant law's ``r_c`` depends on V only; ``T_i`` is constant),
so the two ends of the design's certified interval cover every C between them exactly. In V it
is not affine (``r_c`` holds ``A_m(V)^-1``): speeds are checked on a grid of
:data:`LOOP_SPEED_STEP_MPS` from ``speed_min`` to the design's safe speed plus
:data:`LOOP_SPEED_MARGIN_MPS` (the margin of the state-feedback box), as condition 5.3b is for
this law; a measurement between grid speeds, not a certificate, and stated so. The gradient
law's filter row is affine in ``(C, C/V, 1/V)`` and its corners would suffice, but for the
shipped designs no common matrix exists for it (measured): its families get none.

Solved with cvxpy + Clarabel at the first feasible rate of :data:`LOOP_DECAY_TRIALS` (any
lambda_z > 0 proves the claim; the stored rate is the least the matrix proves on the grid and
on the grid shifted by half a step); verify rechecks it on a shifted grid with its own
reference systems and generalized eigenvalues (no solver;
:mod:`drake_cert.synthesis.verify_switching`).
"""

import dataclasses
import math

import numpy as np

from drake_cert.config import VehicleParams
from drake_cert.synthesis.conditions import GRADIENT, reference_system_matrix
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.synthesis.joint_gains import GAIN_BOX_SPEED_MARGIN_MPS
from drake_cert.synthesis.lyapunov_rate import certified_rate
from drake_cert.synthesis.mode_lyapunov import ModeProblem, largest_jump, least_jump_matrices

LOOP_SPEED_STEP_MPS = 0.25  # speed grid of the loop certificate (as condition 5.3b's pc grid)
# the loops are certified this far above each design's safe speed (m/s), as its state-feedback
# gain box is (joint_gains.GAIN_BOX_SPEED_MARGIN_MPS): the car's speed tracking error and the
# drive's 0.1 m/s protection slack lie within it (docs/design.md 5.6 (b))
LOOP_SPEED_MARGIN_MPS = GAIN_BOX_SPEED_MARGIN_MPS
LOOP_DECAY_TRIALS = (0.1, 0.05, 0.02, 0.0)  # lambda_z tried, largest first (1/s)
COARSE_STRIDE = 4  # the first LMI uses every 4th grid speed (1 m/s)
LOOP_ROUNDS = 4  # LMI solves with grid points added where the matrix falls short


def loop_speed_top(design: ControllerDesign, speed_min_mps: float) -> float:
    """The highest speed (m/s) the loop certificate covers for ``design``: its safe speed plus
    :data:`LOOP_SPEED_MARGIN_MPS`, within the speeds its gain is certified for
    (``gain_speed_max_mps``), at least ``speed_min``."""
    top = min(design.speed_mps + LOOP_SPEED_MARGIN_MPS, design.gain_speed_max_mps)
    return max(top, design.speed_mps, speed_min_mps)


def loop_speeds(design: ControllerDesign, speed_min_mps: float, offset: float = 0.0,
                stride: int = 1) -> np.ndarray:
    """``speed_min, speed_min + step, ...`` up to :func:`loop_speed_top` (both ends
    included); with ``offset`` (a fraction of the step) the grid is shifted inside the range
    (the check's), with ``stride`` every stride-th speed is kept."""
    top = loop_speed_top(design, speed_min_mps)
    count = int(np.floor((top - speed_min_mps) / LOOP_SPEED_STEP_MPS + 1e-9))
    grid = speed_min_mps + LOOP_SPEED_STEP_MPS * (np.arange(0, count + 1, stride) + offset)
    grid = grid[grid <= top + 1e-12]
    return np.unique(np.concatenate([[speed_min_mps], grid, [top]]))


def steering_coordinates(reference: np.ndarray, k_m) -> np.ndarray:
    """``T R T^-1`` (5 x 5, 1/s): a design's reference matrix ``R`` on ``z = [s, u_ad]`` as it
    acts on ``zeta = [s, u - u_ff] = T z``, ``T = [[I, 0], [-k_m', 1]]``
    (``u - u_ff = -k_m' s + u_ad``)."""
    k = np.asarray(k_m, dtype=float).reshape(4)
    t = np.eye(5)
    t[4, :4] = -k
    t_inv = np.eye(5)
    t_inv[4, :4] = k
    return t @ reference @ t_inv


def loop_matrices(vehicle: VehicleParams, design: ControllerDesign, speed_min_mps: float,
                  law: str, offset: float = 0.0, stride: int = 1) -> list[np.ndarray]:
    """``M_i(C, V)`` (5 x 5, 1/s; :func:`steering_coordinates` of the reference system) at both
    ends of the certified interval and every speed of :func:`loop_speeds`."""
    return [steering_coordinates(
                reference_system_matrix(vehicle, design.k_m, design.nominal_stiffness_n_per_rad,
                                        c, v, design.filter_gain, law), design.k_m)
            for c in design.certified_interval
            for v in loop_speeds(design, speed_min_mps, offset, stride)]


_SOLVED: dict = {}  # loop_lyapunov_matrix's results by the values of its inputs
_SOLVED_KEPT = 16


def loop_lyapunov_matrix(vehicle: VehicleParams, designs: list[ControllerDesign],
                         speed_min_mps: float, law: str, lmi_margin: float
                         ) -> tuple[np.ndarray, float] | None:
    """``(P_z, lambda_z)`` for the designs with a safe speed (module docstring), P_z normalised
    to smallest eigenvalue 1 and lambda_z the least rate it proves on the grid of
    :data:`LOOP_SPEED_STEP_MPS` and on that grid shifted by half a step (rounded down to 6
    digits); None when none is found, or for the gradient law.

    The LMI is posed on every :data:`COARSE_STRIDE`-th grid speed (and the ends); the
    matrix is then evaluated on the whole grid, and grid points where it proves less than
    half the trial rate are added and the LMI solved again (at most :data:`LOOP_ROUNDS`
    times): a few hundred LMIs instead of a thousand, the same claim. Memoised on the values
    of the inputs: the synthesis asks it (:func:`drake_cert.synthesis.table.
    with_switchable_l1_loops`) before the certificate does, for the same designs."""
    key = repr((dataclasses.asdict(vehicle),
                [dataclasses.asdict(d) for d in designs if d.has_safe_speed],
                float(speed_min_mps), law, float(lmi_margin)))
    if key not in _SOLVED:
        if len(_SOLVED) >= _SOLVED_KEPT:
            _SOLVED.clear()
        _SOLVED[key] = _solve_loop_lyapunov_matrix(vehicle, designs, speed_min_mps, law,
                                                   lmi_margin)
    found = _SOLVED[key]
    return None if found is None else (found[0].copy(), found[1])


def _solve_loop_lyapunov_matrix(vehicle, designs, speed_min_mps, law, lmi_margin):
    """:func:`loop_lyapunov_matrix` without the memo."""
    import cvxpy as cp

    from drake_cert.synthesis.gains import solve_sdp_status

    covered = [d for d in designs if d.has_safe_speed]
    if not covered or law == GRADIENT:
        return None
    try:
        grid = [m for d in covered for m in loop_matrices(vehicle, d, speed_min_mps, law)]
        chosen = [m for d in covered for m in loop_matrices(vehicle, d, speed_min_mps, law,
                                                            stride=COARSE_STRIDE)]
    except np.linalg.LinAlgError:  # a design whose nominal loop A_m is singular: none
        return None
    if not all(np.all(np.isfinite(m)) for m in grid):
        return None
    for _ in range(LOOP_ROUNDS):
        eye = np.eye(5)
        p = cp.Variable((5, 5), symmetric=True)
        decay = cp.Parameter(nonneg=True)
        constraints = [p >> eye]
        for m in chosen:
            lyap = m.T @ p + p @ m + 2.0 * decay * p
            constraints.append(0.5 * (lyap + lyap.T) << -lmi_margin * eye)
        problem = cp.Problem(cp.Minimize(0), constraints)
        found = None
        for rate in LOOP_DECAY_TRIALS:
            decay.value = rate
            # an inaccurate solution is judged below by what its matrix proves, as any other
            if (solve_sdp_status(problem) in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE)
                    and p.value is not None):
                found = (0.5 * (p.value + p.value.T), rate)
                break
        if found is None:
            return None
        best, trial = found
        rates = np.array([certified_rate(best, m) for m in grid])
        if rates.min() > 0.5 * trial or (trial == 0.0 and rates.min() > 0.0):
            best = best / float(np.linalg.eigvalsh(best).min())
            shifted = [m for d in covered
                       for m in loop_matrices(vehicle, d, speed_min_mps, law, offset=0.5)]
            rate = min(certified_rate(best, m) for m in grid + shifted)
            if rate <= 0.0:
                return None
            return best, float(f"{np.floor(rate * 1e6) / 1e6:.6g}")
        chosen += [grid[i] for i in np.flatnonzero(rates <= 0.5 * trial)]
    return None


LOOP_DWELL_DECAYS = (0.05, 0.02)  # lambda_0 tried for the per-design matrices (1/s)
LOOP_JUMP_START = 1.0e4  # first mu tried (feasible whenever every design has a matrix alone)
LOOP_JUMP_RATIO = 1.05  # the mu bisection stops when hi / lo <= this


def loop_dwell_matrices(vehicle: VehicleParams, designs: list[ControllerDesign],
                        speed_min_mps: float, law: str, lmi_margin: float
                        ) -> tuple[list[np.ndarray], float, float] | None:
    """Per-design matrices for the L1 loops when they share none (docs/design.md 5.6 (b)):
    ``(P_i per design with a safe speed, lambda_0, mu)`` with ``M' P_i + P_i M + 2 lambda_0 P_i
    <= 0`` at every matrix of design i's grid (:func:`loop_matrices`, and its half-step shift)
    and ``P_i <= mu P_j`` for every pair; or None (the gradient law, or a design whose loops
    have no matrix alone).

    zeta is continuous at a switch (the estimate carried, the steering kept), so
    ``zeta' P_sigma zeta`` grows by at most mu at a switch and falls at ``2 lambda_0`` between
    switches: stable for switching with an average dwell above ``ln(mu) / (2 lambda_0)``
    (Hespanha and Morse). Posed on every :data:`COARSE_STRIDE`-th grid speed, checked on the
    whole grid and its shift, grid points added where a matrix falls short (at most
    :data:`LOOP_ROUNDS` rounds); for each lambda_0 of :data:`LOOP_DWELL_DECAYS` mu is bisected
    (geometric, to :data:`LOOP_JUMP_RATIO`) and the pair with the least dwell kept. The returned
    lambda_0 and mu are what the matrices prove (a shared scale: the smallest eigenvalue
    among them is 1)."""
    covered = [d for d in designs if d.has_safe_speed]
    if not covered or law == GRADIENT:
        return None
    try:
        grids = [loop_matrices(vehicle, d, speed_min_mps, law)
                 + loop_matrices(vehicle, d, speed_min_mps, law, offset=0.5) for d in covered]
        chosen = [loop_matrices(vehicle, d, speed_min_mps, law, stride=COARSE_STRIDE)
                  for d in covered]
    except np.linalg.LinAlgError:
        return None
    if not all(np.all(np.isfinite(m)) for grid in grids for m in grid):
        return None
    best = None
    for decay in LOOP_DWELL_DECAYS:
        for _ in range(LOOP_ROUNDS):
            found = least_jump_matrices(ModeProblem([((), mats) for mats in chosen],
                                                    lmi_margin, 5),
                                        decay, LOOP_JUMP_START, LOOP_JUMP_RATIO)
            if found is None:
                break
            shortfalls = [[m for m in grid if certified_rate(p, m) <= 0.5 * decay]
                          for p, grid in zip(found, grids, strict=True)]
            if not any(shortfalls):
                scale = min(float(np.linalg.eigvalsh(p).min()) for p in found)
                ps = [p / scale for p in found]
                rate = min(certified_rate(p, m) for p, grid in zip(ps, grids, strict=True)
                           for m in grid)
                mu = max(largest_jump(ps), 1.0)
                dwell = math.log(mu) / (2.0 * rate)
                if best is None or dwell < best[0]:
                    best = (dwell, ps, rate, mu)
                break
            chosen = [c + s for c, s in zip(chosen, shortfalls, strict=True)]
    if best is None:
        return None
    return best[1], best[2], best[3]
