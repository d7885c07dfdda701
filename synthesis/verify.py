"""Independent re-check of saved designs (DESIGN 5.5): ``drake-cert verify FILE``.

Nothing here calls the synthesis code paths (no LMI, no eigen-residue L1 norm, no
``adaptive_steady_state``); every claim is recomputed another way:

* ``gain_decay``: eigenvalues of ``A(C, V) - b(C) k_m`` on a dense (C, V) grid over
  ``[C_lo, C_hi] x [V_min, gain_speed_max]``: ``max Re <= -alpha``.
* ``l1_condition``: ``||G_w||_L1`` by quadrature of the impulse response, computed by exact
  matrix-exponential steps on a graded time grid (trapezoid rule), with a Lyapunov bound
  on the tail; dense grids over w and C.
* ``reference_stability``: eigenvalues of the reference system on a dense grid of
  ``[C_lo, C_hi] x [V_min, V]``.
* ``steady_state_offset``: the adaptive equilibrium by eliminating ``u_ad`` (plant solve,
  then the gradient-law condition), with the feedforward from the bordered nominal
  equilibrium and ``P_ad`` from a Kronecker-product solve; dense C grid.
* ``grip``: slip angles from the steady-state single-track force and moment balance, solved
  for (side velocity, steering) at yaw rate V / R.
* consistency: ``speed <= gain_speed_max``, ``0 < k <= k_bar``, ``C_hat`` the midpoint, and
  (when the file holds the conditions) interval = hull and mu_lo = least friction of the labels;
  stored margins may not overstate the recomputed ones.

A design claiming no safe speed holds when, with its filter gain, some condition fails at
every speed of the synthesis speed grid. Failures are named by condition.
"""

import dataclasses

import numpy as np
import scipy.linalg

from drake_cert.config import GRAVITY_MPS2, ConditionsTable, Settings, VehicleParams
from drake_cert.dynamics import lateral_error_dynamics
from synthesis.design import ControllerDesign
from synthesis.design_io import DesignTable

CONDITION_NAMES = ("gain_decay", "l1_condition", "reference_stability",
                   "steady_state_offset", "grip")
CONSISTENCY = "consistency"
NO_SAFE_SPEED_CLAIM = "no_safe_speed_claim"
MARGIN_CLAIM = "margin_claim"
GAIN_LMI = "gain_lmi"

DENSE_STIFFNESS_POINTS = 21
DENSE_SPEED_POINTS = 41
DENSE_W_POINTS = 9
QUADRATURE_STEPS_PER_TIME_CONSTANT = 40.0
QUADRATURE_SEGMENT_STEPS = 256
TAIL_RELATIVE = 1.0e-5
MARGIN_CLAIM_SLACK = (1.0e-3, 1.0e-2)  # (absolute, relative) overstatement allowed


@dataclasses.dataclass
class DesignVerification:
    """Recomputed margins of one design and the conditions that failed (name, message)."""

    index: int
    labels: list[str]
    speed_mps: float
    margins: dict
    failures: list[tuple[str, str]]

    @property
    def ok(self) -> bool:
        return not self.failures


@dataclasses.dataclass
class VerificationReport:
    designs: list[DesignVerification]

    @property
    def ok(self) -> bool:
        return all(d.ok for d in self.designs)

    @property
    def first_failure(self):
        """``(design index, labels, condition, message)`` of the first failure, or None."""
        for d in self.designs:
            if d.failures:
                return (d.index, d.labels, *d.failures[0])
        return None


# ----------------------------------------------------------------- independent L1 norm

def l1_norm_by_quadrature(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """``max_i integral |c_i' exp(A t) b| dt`` by trapezoid quadrature of exact steps.

    Time grid: segments of 256 equal steps, each step ``1 / (40 |lambda|)`` of the fastest mode
    still alive (``Re lambda t > -36``), non-decreasing; inside a segment the states come from
    powers of ``Phi = expm(A h)`` by doubling. Stops when the Lyapunov tail bound
    ``sqrt(c_i' P^-1 c_i) ||x(T)||_P / beta`` (``(A + beta I)' P + P (A + beta I) = -I``,
    ``beta`` half the decay rate) is below 1e-5 of the integral. ``b`` (n,), ``c`` (p, n).
    """
    lam = np.linalg.eigvals(a)
    decay = -lam.real.max()
    if decay <= 0.0:
        return float("inf")
    beta = 0.5 * decay
    n = a.shape[0]
    p_tail = scipy.linalg.solve_continuous_lyapunov((a + beta * np.eye(n)).T, -np.eye(n))
    c_norm = np.sqrt(np.einsum("ij,ij->i", c, np.linalg.solve(p_tail, c.T).T))
    x = np.asarray(b, dtype=float).reshape(n)
    total = np.zeros(c.shape[0])
    t = 0.0
    h = 1.0 / (QUADRATURE_STEPS_PER_TIME_CONSTANT * np.abs(lam).max())
    phi = expm_taylor(a * h)
    while True:
        alive = lam.real * t > -36.0
        h_target = 1.0 / (QUADRATURE_STEPS_PER_TIME_CONSTANT * np.abs(lam[alive]).max())
        while 2.0 * h <= h_target:  # grow the step by doubling: Phi(2h) = Phi(h)^2
            h, phi = 2.0 * h, phi @ phi
        states = x.reshape(n, 1)
        power = phi
        while states.shape[1] < QUADRATURE_SEGMENT_STEPS + 1:
            states = np.hstack((states, power @ states))
            power = power @ power
        states = states[:, :QUADRATURE_SEGMENT_STEPS + 1]
        y = np.abs(c @ states)  # (p, steps + 1), column 0 is x
        total += 0.5 * h * (y[:, 1:] + y[:, :-1]).sum(axis=1)
        x = states[:, -1]
        t += QUADRATURE_SEGMENT_STEPS * h
        tail = c_norm * np.sqrt(max(float(x @ p_tail @ x), 0.0)) / beta
        if np.all(tail <= TAIL_RELATIVE * np.maximum(total, 1e-300)) or t > 1e4 / decay:
            return float((total + tail).max())


def expm_taylor(m: np.ndarray) -> np.ndarray:
    """``exp(M)`` by scaling and squaring of a degree-14 Taylor polynomial (||M/2^s||_inf <= 1/4).

    Truncation error below ``(1/4)^15 / 15!`` relative per scaled step; used instead of
    ``scipy.linalg.expm`` to stay independent of synthesis and fast for 5 x 5 matrices.
    """
    norm = float(np.abs(m).sum(axis=1).max())
    squarings = max(0, int(np.ceil(np.log2(norm / 0.25)))) if norm > 0.0 else 0
    x = m / 2.0**squarings
    term = np.eye(m.shape[0])
    out = term.copy()
    for j in range(1, 15):
        term = term @ x / j
        out = out + term
    for _ in range(squarings):
        out = out @ out
    return out


# ----------------------------------------------------------------- recomputed conditions

def _dense(lo, hi, points):
    return np.linspace(lo, hi, points)


def gain_decay_margin(vehicle, design, settings) -> float:
    """``-(max Re eig(A - b k_m)) - alpha`` on the dense grid up to ``gain_speed_max`` (1/s)."""
    k_m = design.k_m_array
    v_lo = settings.synthesis.speed_min_mps
    v_hi = max(design.gain_speed_max_mps, v_lo)
    mats = []
    for c in _dense(*design.interval, DENSE_STIFFNESS_POINTS):
        for v in _dense(v_lo, v_hi, DENSE_SPEED_POINTS):
            a, b, _ = lateral_error_dynamics(vehicle, c, v)
            mats.append(a - np.outer(b, k_m))
    return -float(np.linalg.eigvals(np.array(mats)).real.max()) - settings.synthesis.decay_rate


def _nominal(vehicle, design, speed):
    """``(A_m, b_m, g_hat, A_hat)`` at the design's C_hat and speed."""
    a_hat, b_m, g_hat = lateral_error_dynamics(vehicle, design.nominal_stiffness_n_per_rad, speed)
    return a_hat - np.outer(b_m, design.k_m_array), b_m, g_hat, a_hat


def _theta(vehicle, design, stiffness, speed):
    """Matched gain ``theta`` with ``b(C) = w b_m``: least-squares fit of ``A(C) - b(C) k_m``.

    ``theta' = argmin ||(A(C) - b(C) k_m) - A_m - b_m theta'||_F`` (the projection onto
    span(b_m)), computed by ``lstsq`` rather than the pseudo-inverse formula.
    """
    a_m, b_m, _, _ = _nominal(vehicle, design, speed)
    a, b, _ = lateral_error_dynamics(vehicle, stiffness, speed)
    resid = a - np.outer(b, design.k_m_array) - a_m
    theta, *_ = np.linalg.lstsq(b_m.reshape(4, 1), resid, rcond=None)
    return theta.reshape(4)


def l1_condition_value(vehicle, design, speed) -> float:
    """``max_w ||G_w||_L1 * max_C ||theta||_1`` on dense grids (must be < 1)."""
    a_m, b_m, _, _ = _nominal(vehicle, design, speed)
    k = design.filter_gain
    bound = max(np.abs(_theta(vehicle, design, c, speed)).sum()
                for c in _dense(*design.interval, DENSE_STIFFNESS_POINTS))
    worst = 0.0
    for c in _dense(*design.interval, DENSE_W_POINTS):
        w = c / design.nominal_stiffness_n_per_rad
        a = np.zeros((5, 5))
        a[:4, :4] = a_m
        a[:4, 4] = -w * k * b_m
        a[4, 4] = -w * k
        worst = max(worst, l1_norm_by_quadrature(a, np.append(b_m, 1.0), np.eye(5)[:4]))
    return worst * bound


def reference_abscissas(vehicle, design, speeds) -> np.ndarray:
    """``max Re eig`` of the reference system over the dense C grid, at each speed (1/s)."""
    k = design.filter_gain
    out = []
    for v in speeds:
        a_m, b_m, _, _ = _nominal(vehicle, design, v)
        mats = []
        for c in _dense(*design.interval, DENSE_STIFFNESS_POINTS):
            a, b, _ = lateral_error_dynamics(vehicle, c, v)
            w = c / design.nominal_stiffness_n_per_rad
            m = np.zeros((5, 5))
            m[:4, :4] = a - np.outer(b, design.k_m_array)
            m[:4, 4] = b
            m[4, :4] = -k * _theta(vehicle, design, c, v)
            m[4, 4] = -k * w
            mats.append(m)
        out.append(np.linalg.eigvals(np.array(mats)).real.max())
    return np.array(out)


def _lyapunov_by_kronecker(a_m: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``P`` with ``A_m' P + P A_m = -Q`` from ``(I kron A_m' + A_m' kron I) vec P = -vec Q``."""
    n = a_m.shape[0]
    eye = np.eye(n)
    lhs = np.kron(eye, a_m.T) + np.kron(a_m.T, eye)
    return np.linalg.solve(lhs, -q.reshape(-1)).reshape(n, n)


def equilibrium_offset_m(vehicle, design, settings, stiffness, speed) -> float:
    """e1 (m) at the adaptive equilibrium on the design curvature, by elimination of u_ad."""
    radius = settings.synthesis.design_radius_m
    psidot = speed / radius
    a_m, b_m, g_hat, _ = _nominal(vehicle, design, speed)
    # nominal equilibrium with e1 = 0: [A_m b_m; e1' 0] [s_hat; u_ff] = [-g_hat psidot; 0]
    border = np.zeros((5, 5))
    border[:4, :4] = a_m
    border[:4, 4] = b_m
    border[4, 0] = 1.0
    sol = np.linalg.solve(border, np.append(-g_hat * psidot, 0.0))
    s_hat, u_ff = sol[:4], sol[4]
    p_b = _lyapunov_by_kronecker(a_m, np.diag(settings.controller.q_ad_diag)) @ b_m
    a, b, g = lateral_error_dynamics(vehicle, stiffness, speed)
    a_cl = a - np.outer(b, design.k_m_array)
    s0 = -np.linalg.solve(a_cl, b * u_ff + g * psidot)  # plant rest with u_ad = 0
    s1 = -np.linalg.solve(a_cl, b)  # d s / d u_ad
    u_ad = float(p_b @ (s_hat - s0)) / float(p_b @ s1)  # s_tilde' P_ad b_m = 0
    return float((s0 + s1 * u_ad)[0])


def offset_margin_m(vehicle, design, settings, speed) -> float:
    worst = max(abs(equilibrium_offset_m(vehicle, design, settings, c, speed))
                for c in _dense(*design.interval, DENSE_STIFFNESS_POINTS))
    return vehicle.lane_margin_m - worst


def cornering_slip_angles(vehicle: VehicleParams, stiffness, speed, radius):
    """Slip angles (rad) of the linear single track in a steady turn (yaw rate V/R).

    Unknowns side velocity v_y and steering delta; ``alpha_f = delta - (v_y + l_f r)/V``,
    ``alpha_r = -(v_y - l_r r)/V``, forces ``2 C alpha``; lateral balance
    ``m V r = F_f + F_r`` and yaw balance ``l_f F_f - l_r F_r = 0``.
    """
    m, lf, lr = vehicle.mass_kg, vehicle.lf_m, vehicle.lr_m
    r = speed / radius
    k2 = 2.0 * stiffness
    # F_f = k2 (delta - (vy + lf r)/V), F_r = k2 (-(vy - lr r)/V); unknowns (vy, delta)
    lhs = np.array([[-k2 / speed - k2 / speed, k2], [-lf * k2 / speed + lr * k2 / speed, lf * k2]])
    rhs = np.array([m * speed * r + k2 * lf * r / speed - k2 * lr * r / speed,
                    lf * k2 * lf * r / speed + lr * k2 * lr * r / speed])
    vy, delta = np.linalg.solve(lhs, rhs)
    return delta - (vy + lf * r) / speed, -(vy - lr * r) / speed


def grip_margin_values(vehicle, design, settings, speed) -> tuple[float, float]:
    syn = settings.synthesis
    radius = syn.design_radius_m
    af, ar = cornering_slip_angles(vehicle, design.stiffness_lo_n_per_rad, speed, radius)
    slip = syn.slip_angle_max_rad - max(abs(af), abs(ar))
    accel = syn.lateral_accel_fraction * design.friction_mu_lo * GRAVITY_MPS2 - speed**2 / radius
    return float(slip), float(accel)


# ----------------------------------------------------------------- claims

def _consistency_failures(design, settings, conditions) -> list[tuple[str, str]]:
    syn = settings.synthesis
    out = []
    mid = 0.5 * (design.stiffness_lo_n_per_rad + design.stiffness_hi_n_per_rad)
    if abs(design.nominal_stiffness_n_per_rad - mid) > 1e-9 * mid:
        out.append((CONSISTENCY, f"nominal stiffness {design.nominal_stiffness_n_per_rad} is "
                                 f"not the interval midpoint {mid}"))
    if not 0.0 < design.filter_gain <= syn.filter_gain_max:
        out.append((CONSISTENCY, f"filter gain {design.filter_gain} not in (0, "
                                 f"{syn.filter_gain_max}]"))
    if design.speed_mps > 0.0:
        if design.failed_condition:
            out.append((CONSISTENCY, f"speed {design.speed_mps} m/s with failed condition "
                                     f"{design.failed_condition!r}"))
        if not syn.speed_min_mps <= design.speed_mps <= design.gain_speed_max_mps + 1e-9:
            out.append((CONSISTENCY, f"speed {design.speed_mps} m/s outside [{syn.speed_min_mps}, "
                                     f"gain_speed_max {design.gain_speed_max_mps}]"))
    elif not design.failed_condition:
        out.append((CONSISTENCY, "speed 0 without a failed condition"))
    if design.gain_speed_max_mps > syn.speed_max_mps + 1e-9:
        out.append((CONSISTENCY, f"gain_speed_max {design.gain_speed_max_mps} m/s above "
                                 f"speed_max {syn.speed_max_mps} m/s"))
    if conditions is not None and design.labels:
        try:
            hull = conditions.hull(design.labels)
            mu = conditions.least_friction(design.labels)
        except Exception as e:  # unknown label
            return out + [(CONSISTENCY, str(e))]
        if tuple(hull) != design.interval:
            out.append((CONSISTENCY, f"interval {design.interval} is not the hull {hull} of "
                                     f"labels {design.labels}"))
        if abs(mu - design.friction_mu_lo) > 1e-12:
            out.append((CONSISTENCY, f"friction_mu_lo {design.friction_mu_lo} is not the least "
                                     f"friction {mu} of labels {design.labels}"))
    return out


def _guarded(fn) -> float:
    """A margin, or ``-inf`` when its computation breaks down (singular or non-finite)."""
    try:
        value = float(fn())
    except (np.linalg.LinAlgError, ArithmeticError, ValueError):
        return -np.inf
    return value if np.isfinite(value) else -np.inf


def _conditions_at(vehicle, design, settings, speed):
    """Recomputed margins at one speed: dict keyed like ControllerDesign.margins."""
    syn = settings.synthesis
    speeds = _dense(syn.speed_min_mps, speed, DENSE_SPEED_POINTS)
    slip, accel = grip_margin_values(vehicle, design, settings, speed)
    return {
        "l1_condition": _guarded(lambda: 1.0 - l1_condition_value(vehicle, design, speed)),
        "reference_stability_per_s": _guarded(
            lambda: -reference_abscissas(vehicle, design, speeds).max()),
        "steady_state_offset_m": _guarded(
            lambda: offset_margin_m(vehicle, design, settings, speed)),
        "grip_slip_angle_rad": slip,
        "grip_lateral_accel_mps2": accel,
    }


def _condition_failures(margins, speed) -> list[tuple[str, str]]:
    out = []
    if margins["l1_condition"] <= 0.0:
        out.append(("l1_condition", f"||G||_L1 L = {1 - margins['l1_condition']:.6g} >= 1 at "
                                    f"{speed:.4g} m/s"))
    if margins["reference_stability_per_s"] <= 0.0:
        out.append(("reference_stability", "reference system max Re eig = "
                    f"{-margins['reference_stability_per_s']:.6g}/s >= 0 on [V_min, {speed:.4g}]"))
    if margins["steady_state_offset_m"] < 0.0:
        out.append(("steady_state_offset", "steady-state offset exceeds the lane margin by "
                    f"{-margins['steady_state_offset_m']:.4g} m at {speed:.4g} m/s"))
    if margins["grip_slip_angle_rad"] < -1e-12:
        out.append(("grip", f"slip angle exceeds the limit by {-margins['grip_slip_angle_rad']:.4g}"
                            f" rad at {speed:.4g} m/s"))
    if margins["grip_lateral_accel_mps2"] < -1e-12:
        out.append(("grip", "lateral acceleration exceeds the friction limit by "
                    f"{-margins['grip_lateral_accel_mps2']:.4g} m/s^2 at {speed:.4g} m/s"))
    return out


def _claim_failures(stored: dict, recomputed: dict) -> list[tuple[str, str]]:
    """Stored margins may not exceed the recomputed ones beyond numerical slack."""
    absolute, relative = MARGIN_CLAIM_SLACK
    out = []
    for key, value in recomputed.items():
        if key in stored and stored[key] > value + absolute + relative * abs(value):
            out.append((MARGIN_CLAIM, f"stored margin {key} = {stored[key]:.6g} exceeds the "
                                      f"recomputed {value:.6g}"))
    return out


def verify_design(design: ControllerDesign, vehicle: VehicleParams, settings: Settings,
                  conditions: ConditionsTable | None = None, index: int = 0) -> DesignVerification:
    """Recompute every claim of one design (module docstring)."""
    syn = settings.synthesis
    failures = _consistency_failures(design, settings, conditions)
    margins: dict = {}
    if design.failed_condition == GAIN_LMI and design.speed_mps == 0.0:
        # no k_m was found: the car stops, which is always safe; nothing else is claimed
        return DesignVerification(index, list(design.labels), 0.0, margins, failures)
    margins["gain_decay_per_s"] = gain_decay_margin(vehicle, design, settings)
    if margins["gain_decay_per_s"] < -1e-6:
        failures.append(("gain_decay", "k_m does not give decay rate "
                         f"{syn.decay_rate}/s: max Re eig(A - b k_m) = "
                         f"{-margins['gain_decay_per_s'] - syn.decay_rate:.6g}/s"))
        if margins["gain_decay_per_s"] + syn.decay_rate <= 0.0:
            # A - b k_m not Hurwitz: A_m, P_ad and the equilibrium do not exist
            return DesignVerification(index, list(design.labels), design.speed_mps, margins,
                                      failures)
    if design.speed_mps > 0.0:
        margins.update(_conditions_at(vehicle, design, settings, design.speed_mps))
        failures += _condition_failures(margins, design.speed_mps)
        failures += _claim_failures(design.margins, margins)
    else:
        failures += _no_safe_speed_failures(vehicle, design, settings, margins)
    return DesignVerification(index, list(design.labels), design.speed_mps, margins, failures)


def _no_safe_speed_failures(vehicle, design, settings, margins) -> list[tuple[str, str]]:
    """The claim 'no safe speed' holds if some condition fails at every grid speed."""
    syn = settings.synthesis
    v_hi = max(design.gain_speed_max_mps, syn.speed_min_mps)
    count = int(np.floor((v_hi - syn.speed_min_mps) / syn.speed_grid_step_mps + 1e-9))
    grid = syn.speed_min_mps + syn.speed_grid_step_mps * np.arange(count + 1)
    ref = np.maximum.accumulate(reference_abscissas(vehicle, design, grid))
    for v, abscissa in zip(grid, ref, strict=True):
        slip, accel = grip_margin_values(vehicle, design, settings, v)
        if min(slip, accel) < 0.0 or abscissa >= 0.0:
            continue
        if _guarded(lambda v=v: offset_margin_m(vehicle, design, settings, v)) < 0.0:
            continue
        l1 = _guarded(lambda v=v: 1.0 - l1_condition_value(vehicle, design, v))
        if l1 > 0.0:
            margins.update({"l1_condition": l1, "reference_stability_per_s": -float(abscissa),
                            "grip_slip_angle_rad": slip, "grip_lateral_accel_mps2": accel})
            return [(NO_SAFE_SPEED_CLAIM, f"claims no safe speed ({design.failed_condition}) "
                                          f"but every condition holds at {v:.4g} m/s")]
    return []


def verify_design_table(table: DesignTable, progress=None) -> VerificationReport:
    """Verify every design of a loaded file; ``progress(i, n)`` is called per design."""
    out = []
    for i, design in enumerate(table.designs):
        if progress is not None:
            progress(i, len(table.designs))
        out.append(verify_design(design, table.vehicle, table.settings, table.conditions, i))
    return VerificationReport(out)
