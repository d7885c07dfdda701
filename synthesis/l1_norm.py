"""The L1 norm of a stable, strictly proper LTI system (DESIGN 5.2; paper eq. (prog)).

``||G||_L1 = max_i sum_j integral_0^inf |g_ij(t)| dt`` with the impulse response
``g(t) = C exp(A t) B`` (the induced L-infinity gain of ``xdot = A x + B u, y = C x``).
No library computes it, so this module does, exactly up to root finding:

1. Eigendecomposition ``A = W diag(lambda) W^-1`` gives ``g_ij(t) = sum_l r_ijl exp(lambda_l t)``
   with ``r_ijl = (C W)_il (W^-1 B)_lj``; its antiderivative ``F_ij`` is known in closed form,
   ``F_ij(t) = sum_l r_ijl (exp(lambda_l t) - 1) / lambda_l``.
2. The sign changes of ``g_ij`` are bracketed on a time grid that resolves every mode
   (step ``0.2 / |lambda_l|`` while mode l is alive), then refined by Newton steps.
3. Between consecutive roots ``tau_k`` the sign is constant, so
   ``integral |g_ij| = sum_k |F_ij(tau_(k+1)) - F_ij(tau_k)|`` with ``tau_0 = 0`` and the last
   interval running to infinity (``F_ij(inf) = -sum_l r_ijl / lambda_l``).

Tail bound: the grid runs to ``T`` where every mode has decayed by ``exp(-TAIL_EFOLDS)``; a sign
change after ``T`` can change the result by at most ``2 sum_l |r_ijl| exp(Re lambda_l T) /
|Re lambda_l|``, which is checked to be below ``1e-6`` relative. A pair of roots missed inside
one grid step (closer than a fifth of the fastest live time scale: near-cancelling modes)
loses only that lobe's tiny area, far below the ``1e-4`` relative accuracy claimed. When the
eigenvector matrix is ill-conditioned (near-defective A), the impulse response is instead
integrated from exact matrix exponentials on a fine graded grid (slower, same accuracy).
"""

import numpy as np
import scipy.linalg

TAIL_EFOLDS = 32.0  # the grid ends when every mode has decayed by exp(-32) ~ 1e-14
STEPS_PER_TIME_CONSTANT = 5.0  # grid step 1 / (5 |lambda|) while a mode is alive
NEWTON_STEPS = 3
EIGVEC_COND_MAX = 1.0e8  # above this, use the matrix-exponential fallback
RELATIVE_TOLERANCE = 1.0e-4


def l1_norm(a, b, c) -> float:
    """``||G||_L1`` of ``xdot = A x + B u, y = C x`` (DESIGN 5.2).

    ``a`` (n, n) Hurwitz, ``b`` (n, m) or (n,), ``c`` (p, n) or (n,). Returns the maximum over the
    p outputs of the sum over the m inputs of ``integral_0^inf |g_ij(t)| dt`` (units: output per
    input), to 1e-4 relative accuracy; ``inf`` if A is not Hurwitz.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c = np.asarray(c, dtype=float)
    b = b.reshape(-1, 1) if b.ndim == 1 else b
    c = c.reshape(1, -1) if c.ndim == 1 else c
    n = a.shape[0]
    if a.shape != (n, n) or b.shape[0] != n or c.shape[1] != n:
        raise ValueError(f"l1_norm: incompatible shapes A {a.shape}, B {b.shape}, C {c.shape}")
    lam, vec = np.linalg.eig(a)
    if not np.all(np.isfinite(lam)) or lam.real.max() >= 0.0:
        return float("inf")
    try:
        vec_inv = np.linalg.inv(vec)
    except np.linalg.LinAlgError:
        return _l1_norm_by_expm(a, b, c, lam)
    if np.abs(vec).sum(axis=0).max() * np.abs(vec_inv).sum(axis=0).max() > EIGVEC_COND_MAX:
        return _l1_norm_by_expm(a, b, c, lam)
    cw = c @ vec  # (p, n)
    wb = vec_inv @ b  # (n, m)
    p, m = c.shape[0], b.shape[1]
    # residues r[(i, j), l] of g_ij(t) = sum_l r exp(lambda_l t)
    r = (cw[:, None, :] * wb.T[None, :, :]).reshape(p * m, n)
    per_channel = integral_abs_exponential_sums(r, lam)
    if per_channel is None:  # residues too large for the tail bound: near-cancelling modes
        return _l1_norm_by_expm(a, b, c, lam)
    return float(per_channel.reshape(p, m).sum(axis=1).max())


def _time_grid(lam: np.ndarray) -> np.ndarray:
    """Union of per-mode uniform grids: step ``1/(5 |lambda|)`` up to ``32 / |Re lambda|``."""
    pieces = []
    upper = lam[lam.imag >= 0.0]  # a conjugate pair needs one grid
    for mag, decay in zip(np.abs(upper), -upper.real, strict=True):
        t_end = TAIL_EFOLDS / decay
        step = 1.0 / (STEPS_PER_TIME_CONSTANT * mag)
        pieces.append(np.arange(0.0, t_end + step, step))
    return np.unique(np.concatenate(pieces))


def integral_abs_exponential_sums(r: np.ndarray, lam: np.ndarray) -> np.ndarray | None:
    """``integral_0^inf |sum_l r[q, l] exp(lambda_l t)| dt`` for every row q (see module doc).

    ``r`` (q, n) complex residues, ``lam`` (n,) poles with ``Re < 0``, closed under conjugation
    with conjugate residues (so each sum is real); zero residues are allowed, which lets
    several systems that share poles be evaluated in one call. Returns None when the tail
    bound exceeds 1e-6 of a result (the caller falls back).
    """
    t = _time_grid(lam)
    e = np.exp(np.outer(lam, t))  # (n, N)
    # einsum, not ``@``: a threaded complex GEMM is ~20x slower on a loaded 2-core machine
    g = np.einsum("ql,ln->qn", r, e).real  # (q, N)
    sign = np.signbit(g)
    qi, ki = np.nonzero(sign[:, 1:] != sign[:, :-1])  # root of row qi in (t[ki], t[ki+1]]
    g0, g1 = g[qi, ki], g[qi, ki + 1]
    ta, tb = t[ki], t[ki + 1]
    denom = np.where(g1 != g0, g1 - g0, 1.0)
    tau = ta - g0 * (tb - ta) / denom
    rq = r[qi]
    for _ in range(NEWTON_STEPS):
        ex = np.exp(np.outer(tau, lam))  # (roots, n)
        val = np.einsum("kl,kl->k", rq, ex).real
        der = np.einsum("kl,kl->k", rq * lam, ex).real
        step = np.where(der != 0.0, val / np.where(der != 0.0, der, 1.0), 0.0)
        tau = np.clip(tau - step, ta, tb)
    antider_inf = (-(r / lam).sum(axis=1)).real  # F(inf) per row
    # F at every root; rows are sorted (np.nonzero is row-major), so the intervals of a row
    # are [0, tau_1], [tau_1, tau_2], ..., [tau_last, inf)
    total = np.zeros(r.shape[0])
    f_last = np.zeros(r.shape[0])
    if qi.size:
        f_roots = np.einsum("kl,kl->k", (np.exp(np.outer(tau, lam)) - 1.0) / lam, rq).real
        first = np.r_[True, qi[1:] != qi[:-1]]
        last = np.r_[qi[1:] != qi[:-1], True]
        prev = np.where(first, 0.0, np.r_[0.0, f_roots[:-1]])
        total += np.bincount(qi, weights=np.abs(f_roots - prev), minlength=r.shape[0])
        f_last[qi[last]] = f_roots[last]
    total += np.abs(antider_inf - f_last)
    tail = 2.0 * (np.abs(r) * np.exp(lam.real * t[-1]) / -lam.real).sum(axis=1)
    if np.any(tail > 1e-2 * RELATIVE_TOLERANCE * np.maximum(total, 1e-300)):
        return None
    return total


def _l1_norm_by_expm(a, b, c, lam) -> float:
    """Fallback for near-defective A: trapezoid rule on exact ``exp(A h)`` steps.

    The step starts at ``1 / (100 |lambda|_max)`` and doubles (``exp(2 A h) = exp(A h)^2``)
    while it stays below ``1 / (100 |lambda|)`` for every mode still alive
    (``Re lambda t > -36``); 400 steps per segment, up to ``36 / decay rate``.
    """
    t_end = TAIL_EFOLDS / -lam.real.max()
    h = 1.0 / (100.0 * np.abs(lam).max())
    phi = scipy.linalg.expm(a * h)
    x = b.copy()
    t = 0.0
    total = np.zeros((c.shape[0], b.shape[1]))
    prev = np.abs(c @ x)
    while t < t_end:
        alive = lam.real * t > -TAIL_EFOLDS
        while 2.0 * h <= 1.0 / (100.0 * np.abs(lam[alive]).max()):
            h, phi = 2.0 * h, phi @ phi
        for _ in range(400):
            x = phi @ x
            cur = np.abs(c @ x)
            total += 0.5 * h * (prev + cur)
            prev = cur
        t += 400 * h
    return float(total.sum(axis=1).max())
