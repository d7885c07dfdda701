"""Lyapunov matrices, one per mode, with bounded jumps between them (docs/design.md 5.6 (c)).

The average-dwell argument (Hespanha and Morse) needs, for modes m = 1..M with system matrices
``A_m,j`` (1/s): matrices ``P_m >= I`` with ``A' P_m + P_m A + 2 lambda_0 P_m <= -eps I`` at every
``A`` of mode m, and ``P_m <= mu P_n`` for every pair. For fixed ``lambda_0`` and mu these are
LMIs in the P_m (:class:`ModeProblem`, cvxpy + Clarabel, compiled once); mu is bisected
(:func:`least_jump_matrices`). Used by the state-feedback dwell certificate
(:mod:`drake_cert.synthesis.switching`, 4 x 4) and by the L1 loops' per-design matrices
(:mod:`drake_cert.synthesis.loop_switching`, 5 x 5).
"""

import itertools
import math

import numpy as np
import scipy.linalg


def jump_factor(p_from: np.ndarray, p_to: np.ndarray) -> float:
    """``lambda_max(P_to^-1 P_from)``: the least mu with ``P_from <= mu P_to`` (the growth of
    ``V`` at a switch from the mode of ``p_from`` to that of ``p_to``)."""
    return float(scipy.linalg.eigh(p_from, p_to, eigvals_only=True).max())


def largest_jump(ps) -> float:
    """The largest :func:`jump_factor` over ordered pairs of distinct matrices (1 for one)."""
    return max((jump_factor(ps[i], ps[j]) for i, j in itertools.permutations(range(len(ps)), 2)),
               default=1.0)


def decay_constraints(p, matrices, decay, margin):
    """cvxpy constraints ``sym(M' P + P M + 2 decay P) <= -margin I`` for each matrix M."""
    eye = np.eye(p.shape[0])
    out = []
    for m in matrices:
        lyap = m.T @ p + p @ m + 2.0 * decay * p
        out.append(0.5 * (lyap + lyap.T) << -margin * eye)
    return out


class ModeProblem:
    """Joint ``P_m >= I``, each with the decay LMI on its mode's matrices, and
    ``P_m <= jump P_n`` for all m != n (a feasibility problem). ``modes``: ``[(keys,
    matrices)]``; ``size``: the matrices' order. Decay rate and jump are cvxpy Parameters (the
    problem is DPP: compiled once)."""

    def __init__(self, modes, margin, size: int = 4):
        import cvxpy as cp

        eye = np.eye(size)
        self.decay = cp.Parameter(nonneg=True)
        self.jump = cp.Parameter(nonneg=True)
        self.ps = [cp.Variable((size, size), symmetric=True) for _ in modes]
        constraints = []
        for p, (_, mats) in zip(self.ps, modes, strict=True):
            constraints.append(p >> eye)
            constraints += decay_constraints(p, mats, self.decay, margin)
        constraints += [self.ps[i] << self.jump * self.ps[j]
                        for i, j in itertools.permutations(range(len(self.ps)), 2)]
        self.problem = cp.Problem(cp.Minimize(0), constraints)

    def solve(self, decay, jump):
        """The matrices P_m (not normalised: their ratios matter), or None."""
        from drake_cert.synthesis.gains import solve_sdp

        self.decay.value, self.jump.value = decay, jump
        if not solve_sdp(self.problem) or any(p.value is None for p in self.ps):
            return None
        return [0.5 * (p.value + p.value.T) for p in self.ps]


def least_jump_matrices(problem: ModeProblem, decay: float, start: float,
                        ratio: float) -> list[np.ndarray] | None:
    """The matrices at the least jump factor bisection finds at this decay rate: solved at
    mu = ``start``, then mu bisected geometrically between 1 and the largest jump of the
    matrices in hand until ``hi / lo <= ratio``; None when ``start`` has none."""
    ps = problem.solve(decay, start)
    if ps is None:
        return None
    hi, lo = largest_jump(ps), 1.0
    while hi / lo > ratio:
        mid = math.sqrt(lo * hi)
        trial = problem.solve(decay, mid)
        if trial is None:
            lo = mid
        else:
            ps, hi = trial, min(mid, largest_jump(trial))
    return ps
