"""Switching among designs with the L1 filter state included (docs/design.md 5.6).

The reference system of a design (condition 5.3b,
:func:`drake_cert.synthesis.conditions.reference_system_matrix`) is the L1 loop with the ideal
estimate: plant and low-pass filter, state ``z = [s, u_ad]`` (m, m/s, rad, rad/s; rad),
``z' = R_i(C, V) z`` plus the known inputs (feedforward and road). At a design switch ``s``
is continuous and the piecewise-constant law hands ``u_ad`` over
(``systems/switching_controller.py``), so ``z`` is continuous, and one matrix ``P_z`` with

    R_i(C, V)' P_z + P_z R_i(C, V) + 2 lambda_z P_z <= 0

for every design i of a family and every (C, V) of its range makes ``z' P_z z`` fall at rate
``2 lambda_z`` whatever design is in force and however often it switches.

Where it is checked. For a fixed speed ``R_i`` is affine in C (``theta``, the unmatched part
and ``w`` are; the piecewise-constant law's ``r_c`` depends on V only), so the two ends of the
design's certified interval cover every C between them exactly. In V it is not affine (``r_c``
holds ``A_m(V)^-1``): speeds are checked on a grid of :data:`LOOP_SPEED_STEP_MPS` from
``speed_min`` to the design's safe speed plus :data:`LOOP_SPEED_MARGIN_MPS` (the margin of the
state-feedback box), as condition 5.3b is for this law; a measurement
between grid speeds, not a certificate, and stated so. The gradient law's filter row is affine
in ``(C, C/V, 1/V)`` and its corners would suffice, but for the shipped designs no common
matrix exists for it (measured): its families get none.

Solved with cvxpy + Clarabel at the first feasible rate of :data:`LOOP_DECAY_TRIALS` (any
lambda_z > 0 proves the claim; the stored rate is the least the matrix proves on the grid and
on the grid shifted by half a step); verify rechecks it on a shifted grid with its own
reference systems and generalized eigenvalues (no solver;
:mod:`drake_cert.synthesis.verify_switching`).
"""

import numpy as np

from drake_cert.config import VehicleParams
from drake_cert.synthesis.conditions import GRADIENT, reference_system_matrix
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.synthesis.joint_gains import GAIN_BOX_SPEED_MARGIN_MPS
from drake_cert.synthesis.lyapunov_rate import certified_rate

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


def loop_matrices(vehicle: VehicleParams, design: ControllerDesign, speed_min_mps: float,
                  law: str, offset: float = 0.0, stride: int = 1) -> list[np.ndarray]:
    """``R_i(C, V)`` (5 x 5, 1/s) at both ends of the certified interval and every speed of
    :func:`loop_speeds`."""
    return [reference_system_matrix(vehicle, design.k_m, design.nominal_stiffness_n_per_rad,
                                    c, v, design.filter_gain, law)
            for c in design.certified_interval
            for v in loop_speeds(design, speed_min_mps, offset, stride)]


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
    times): a few hundred LMIs instead of a thousand, the same claim."""
    import cvxpy as cp

    from drake_cert.synthesis.gains import solve_sdp

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
            if solve_sdp(problem) and p.value is not None:
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


def dropout_jump(reference: np.ndarray, sample_period_s: float) -> np.ndarray:
    """The jump ``z+ = J z-`` (5 x 5) of a design switch on the L1 loop ``z = [s, u_ad]``
    whose reference matrix at the (C, V) in force is ``reference`` (docs/design.md 5.6 (b)).

    At a switch the piecewise-constant law restarts its predictor at the measured state, so
    for one sample period T_s the filter ``u_ad' = -k w (u_ad - u*)``, ``u* = -q' s / w``,
    runs without its input: at the period's end ``u_ad`` lacks ``(1 - e^{-k w T_s}) u*`` of
    what the reference loop (the ideal estimate) would hold, with s frozen over the period
    (1 ms against time constants above 0.1 s). So ``J = I + (1 - e^{-k w T_s}) e_5 [q'/w, 0]``,
    read off the reference matrix's filter row ``[-k q', -k w]``.
    """
    kw = -float(reference[4, 4])
    jump = np.eye(5)
    jump[4, :4] += (1.0 - np.exp(-kw * sample_period_s)) * reference[4, :4] / reference[4, 4]
    return jump


def dropout_factor(p: np.ndarray, reference: np.ndarray, sample_period_s: float) -> float:
    """The most one switch's dropout at this reference matrix multiplies ``z' P_z z`` by: the
    largest generalized eigenvalue of ``(J' P_z J, P_z)``, J of :func:`dropout_jump`."""
    import scipy.linalg

    jump = dropout_jump(reference, sample_period_s)
    return float(scipy.linalg.eigh(jump.T @ p @ jump, p, eigvals_only=True).max())


def loop_jump_factor(vehicle: VehicleParams, designs: list[ControllerDesign],
                     speed_min_mps: float, law: str, p: np.ndarray,
                     sample_period_s: float, offset: float = 0.0) -> float:
    """``mu_z``: the largest factor by which one switch's dropout (:func:`dropout_jump`) can
    multiply ``z' P_z z``, the largest generalized eigenvalue of ``(J' P_z J, P_z)`` over both
    ends of every design's certified interval and the speeds of :func:`loop_speeds` (at least
    1). With the loops decaying at ``lambda_z`` between switches, an average dwell above
    ``ln(mu_z) / (2 lambda_z)`` keeps them stable (Hespanha and Morse; docs/design.md 5.6 (b))."""
    return max([1.0] + [dropout_factor(p, m, sample_period_s) for d in designs
                        if d.has_safe_speed
                        for m in loop_matrices(vehicle, d, speed_min_mps, law, offset=offset)])
