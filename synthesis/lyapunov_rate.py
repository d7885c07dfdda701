"""The decay rate a quadratic Lyapunov matrix proves for a linear system (docs/design.md 5.6).

Shared by the switching certificates of the state-feedback loops
(``drake_cert.synthesis.switching``, 4 x 4) and of the L1 loops with their filter state
(``drake_cert.synthesis.loop_switching``, 5 x 5); no solver, so loading and checking a certificate
needs none.
"""

import numpy as np
import scipy.linalg


def certified_rate(p: np.ndarray, m: np.ndarray) -> float:
    """Largest lambda (1/s) with ``M' P + P M + 2 lambda P <= 0``: ``-lambda_max(P^-1 sym) / 2``
    by the symmetric-definite generalized eigenproblem (P must be positive definite)."""
    lyap = m.T @ p + p @ m
    lyap = 0.5 * (lyap + lyap.T)
    return -0.5 * float(scipy.linalg.eigh(lyap, p, eigvals_only=True).max())
