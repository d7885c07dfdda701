"""Independent re-check of saved designs (DESIGN 5.5): ``drake-cert verify FILE``.

Nothing here calls the synthesis code paths (no LMI, no eigen-residue L1 norm, no
``adaptive_steady_state``); each claim is recomputed another way (failures named by condition):

* ``gain_decay``: ``max Re eig(A(C, V) - b(C) k_m) <= -alpha`` on a dense grid of
  ``[C_lo, C_hi] x [V_min, gain_speed_max]``.
* ``l1_condition``: ``||G_w||_L1`` by quadrature of the impulse response (exact
  matrix-exponential steps on a graded grid, Lyapunov tail bound); dense grids over w and C.
* ``reference_stability``: eigenvalues of the reference system on a dense (C, V) grid.
* ``steady_state_offset``: the adaptive equilibrium by eliminating ``u_ad``, ``P_ad`` by a
  Kronecker-product solve; dense C grid.
* ``grip``, ``rollover``, ``comfort``: axle shares of grip inverted through the Fiala force by
  bisection, and the certified interval's lower end recomputed at the slip bound; ``V^2 / R``
  against ``rollover_fraction g t / (2 h)`` and the comfort limit, where given.
* ``switching`` (table): the stored certificates by generalized eigenvalues at every corner of
  every covered box (no solver), covering every design with a safe speed of every preset; a
  table without them passes with a note in ``report.notes``, or fails with
  ``require_switching=True``.
* consistency: the certified law and slip bound, ``speed <= gain_speed_max``, ``0 < k <= k_bar``
  (or the sample-period limit, DESIGN 5.3a), ``C_hat`` the midpoint, interval = hull and mu_lo =
  least friction of the labels (when the file holds the conditions); stored margins may not
  overstate the recomputed ones.
* ``completeness`` (table, :func:`completeness_check`): exactly one design per label range of
  ``ConditionsTable.contiguous_ranges``, a design covering a range when its ``labels`` equal it
  in friction order; against the reference conditions when given, else on request.

Every condition is checked on the certified (tire-widened) interval. A no-safe-speed claim
holds when some condition fails at every speed of the synthesis speed grid.
"""

import dataclasses
import functools
import math
from pathlib import Path

import numpy as np
import scipy.linalg

from drake_cert.config import (
    GRAVITY_MPS2,
    ConditionsTable,
    Settings,
    VehicleParams,
    load_conditions,
    load_settings,
    load_vehicle,
)
from drake_cert.dynamics import lateral_error_dynamics
from drake_cert.errors import ConfigError
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.synthesis.design_io import DesignTable, load_design_file
from drake_cert.synthesis.verify_switching import check_table_switching

CONDITION_NAMES = ("gain_decay", "l1_condition", "reference_stability",
                   "steady_state_offset", "grip")
CONSISTENCY = "consistency"
NO_SAFE_SPEED_CLAIM = "no_safe_speed_claim"
MARGIN_CLAIM = "margin_claim"
INPUT_MISMATCH = "reference_inputs"  # embedded vehicle/settings/conditions differ from the given
GAIN_LMI = "gain_lmi"
SWITCHING = "switching"  # the table's switching certificates
COMPLETENESS = "completeness"  # a label range of the conditions without (or with two) designs
NO_SWITCHING_NOTE = ("the file holds no switching certificate (written before them, or "
                     "with switching=False): switching among its designs is not certified; "
                     "re-run drake-cert synthesize --out to add one")

DENSE_STIFFNESS_POINTS = 21
DENSE_SPEED_POINTS = 41
DENSE_W_POINTS = 9
QUADRATURE_STEPS_PER_TIME_CONSTANT = 40.0
QUADRATURE_SEGMENT_STEPS = 256
TAIL_RELATIVE = 1.0e-5
MARGIN_CLAIM_SLACK = (1.0e-3, 1.0e-2)  # (absolute, relative) overstatement allowed


@dataclasses.dataclass
class DesignVerification:
    """Recomputed margins of one design and the conditions that failed (name, message).

    ``interval_n_per_rad``: the design's label (or regression) stiffness interval (N/rad);
    ``speed_mps``: the speed it claims (0: no safe speed, the car stops).
    """

    index: int
    labels: list[str]
    speed_mps: float
    margins: dict
    failures: list[tuple[str, str]]
    interval_n_per_rad: tuple[float, float] = (math.nan, math.nan)
    limited_by: str = ""  # the design's stated binding limit (ControllerDesign.speed_limited_by)

    @property
    def ok(self) -> bool:
        return not self.failures

    @property
    def label_range(self) -> str:
        """The labels joined by ``+`` (``"rain+snow"``); ``""`` for a regression interval."""
        return "+".join(self.labels)


@dataclasses.dataclass
class MissingDesign:
    """A label range the conditions define that the table has no design for."""

    labels: list[str]  # grippiest first, as the preset orders them
    presets: list[str]  # the presets whose contiguous ranges include it

    @property
    def message(self) -> str:
        return (f"no design for label range {'+'.join(self.labels)} "
                f"(preset{'s' if len(self.presets) > 1 else ''} {', '.join(self.presets)})")


@dataclasses.dataclass
class VerificationReport:
    """Per-design checks, and mismatches between the file's embedded inputs and reference files.

    ``checked_against``: ``"embedded"`` when the file's own vehicle, settings and conditions
    were used, else the names of the reference inputs given (e.g. ``"settings, vehicle"``).
    """

    designs: list[DesignVerification]
    input_failures: list[tuple[str, str]] = dataclasses.field(default_factory=list)
    checked_against: str = "embedded"
    # (SWITCHING, message) for each failure of the table's switching certificates
    switching_failures: list[tuple[str, str]] = dataclasses.field(default_factory=list)
    notes: list[str] = dataclasses.field(default_factory=list)  # not failures (e.g. no
    # switching certificate in an old file)
    switching_present: bool = False  # the file holds a switching section
    # completeness (module docstring): "" when not checked, else "reference conditions" or
    # "embedded conditions"
    completeness_against: str = ""
    label_ranges: int = 0  # label ranges the conditions define (when checked)
    missing: list[MissingDesign] = dataclasses.field(default_factory=list)
    # (COMPLETENESS, message): one per missing range, one per range with several designs
    completeness_failures: list[tuple[str, str]] = dataclasses.field(default_factory=list)

    @property
    def ok(self) -> bool:
        return (not self.input_failures and all(d.ok for d in self.designs)
                and not self.switching_failures and not self.completeness_failures)

    @property
    def verdict(self) -> str:
        """``"pass"`` when every check holds, else ``"fail"``."""
        return "pass" if self.ok else "fail"

    @property
    def completeness_checked(self) -> bool:
        return bool(self.completeness_against)

    @property
    def first_failure(self):
        """``(design index, labels, condition, message)`` of the first failure, or None.

        A mismatch of the embedded inputs comes first, with index ``None``; failures of the
        switching certificates and then of completeness (table level, index ``None``) come
        after the designs'.
        """
        if self.input_failures:
            return (None, [], *self.input_failures[0])
        for d in self.designs:
            if d.failures:
                return (d.index, d.labels, *d.failures[0])
        for failures in (self.switching_failures, self.completeness_failures):
            if failures:
                return (None, [], *failures[0])
        return None

    def to_dict(self) -> dict:
        """Plain JSON-able mapping (``drake-cert verify --json``): the overall verdict, one
        entry per design (label range, interval, speed, holds, reasons, margins; a margin that
        could not be computed is ``None``), the completeness and switching verdicts."""
        first = self.first_failure

        def named(failures):
            return [{"condition": c, "message": m} for c, m in failures]

        return {
            "verdict": self.verdict,
            "ok": self.ok,
            "checked_against": self.checked_against,
            "input_failures": named(self.input_failures),
            "safe_speed_claims": sum(d.speed_mps > 0 for d in self.designs),
            "no_safe_speed_claims": [d.label_range for d in self.designs
                                     if not d.speed_mps > 0],
            "designs": [{
                "index": d.index, "labels": list(d.labels), "label_range": d.label_range,
                "interval_n_per_rad": [float(x) for x in d.interval_n_per_rad],
                "speed_mps": float(d.speed_mps), "speed_limited_by": d.limited_by or None,
                "holds": d.ok, "reasons": named(d.failures),
                "margins": {k: (float(v) if math.isfinite(v) else None)
                            for k, v in d.margins.items()},
            } for d in self.designs],
            "completeness": {
                "checked": self.completeness_checked,
                "against": self.completeness_against or None,
                "label_ranges": self.label_ranges,
                "holds": (not self.completeness_failures) if self.completeness_checked else None,
                "missing": [{"labels": list(m.labels), "presets": list(m.presets)}
                            for m in self.missing],
                "failures": named(self.completeness_failures),
            },
            "switching": {
                "present": self.switching_present,
                "holds": not self.switching_failures,
                "failures": named(self.switching_failures),
            },
            "notes": list(self.notes),
            "first_failure": None if first is None else {
                "index": first[0], "labels": list(first[1]), "condition": first[2],
                "message": first[3]},
        }


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
    for c in _dense(*design.certified_interval, DENSE_STIFFNESS_POINTS):
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


def _output_row(a_m, b_m) -> np.ndarray:
    """Row r with ``r b_m = 1`` and ``r v`` the input with v's steady-state e1 (by lstsq)."""
    x, *_ = np.linalg.lstsq(a_m.T, np.eye(4)[0], rcond=None)  # x' = e1' A_m^-1
    gain = float(x @ b_m)
    if not np.isfinite(gain) or abs(gain) < 1e-12:
        raise np.linalg.LinAlgError("A_m is singular along b_m: the input has no steady-state "
                                    "e1 to normalise the output row by")
    return x / gain


def _filter_row(vehicle, design, stiffness, speed) -> np.ndarray:
    """What the filter sees per unit state, for the design's certified law.

    Gradient: ``theta``. Piecewise-constant: ``r`` applied to the whole state uncertainty
    ``A(C) - b(C) k_m - A_m`` (matched and unmatched; ``r b_m = 1``).
    """
    if design.certified_law == "gradient":
        return _theta(vehicle, design, stiffness, speed)
    a_m, b_m, _, _ = _nominal(vehicle, design, speed)
    a, b, _ = lateral_error_dynamics(vehicle, stiffness, speed)
    return _output_row(a_m, b_m) @ (a - np.outer(b, design.k_m_array) - a_m)


def l1_condition_value(vehicle, design, speed) -> float:
    """``max_w ||G_w||_L1 * max_C ||theta||_1`` on dense grids (must be < 1)."""
    a_m, b_m, _, _ = _nominal(vehicle, design, speed)
    k = design.filter_gain
    bound = max(np.abs(_theta(vehicle, design, c, speed)).sum()
                for c in _dense(*design.certified_interval, DENSE_STIFFNESS_POINTS))
    worst = 0.0
    for c in _dense(*design.certified_interval, DENSE_W_POINTS):
        w = c / design.nominal_stiffness_n_per_rad
        a = np.zeros((5, 5))
        a[:4, :4] = a_m
        a[:4, 4] = -w * k * b_m
        a[4, 4] = -w * k
        worst = max(worst, l1_norm_by_quadrature(a, np.append(b_m, 1.0), np.eye(5)[:4]))
    return worst * bound


def reference_matrix(vehicle, design, stiffness, speed) -> np.ndarray:
    """The reference system ``[[A(C) - b(C) k_m, b(C)], [-k q', -k w]]`` (5 x 5, 1/s) at (C, V),
    with the filter row q of the design's certified law (:func:`_filter_row`)."""
    k = design.filter_gain
    a, b, _ = lateral_error_dynamics(vehicle, stiffness, speed)
    m = np.zeros((5, 5))
    m[:4, :4] = a - np.outer(b, design.k_m_array)
    m[:4, 4] = b
    m[4, :4] = -k * _filter_row(vehicle, design, stiffness, speed)
    m[4, 4] = -k * stiffness / design.nominal_stiffness_n_per_rad
    return m


def reference_abscissas(vehicle, design, speeds) -> np.ndarray:
    """``max Re eig`` of the reference system over the dense C grid, at each speed (1/s)."""
    out = []
    for v in speeds:
        mats = [reference_matrix(vehicle, design, c, v)
                for c in _dense(*design.certified_interval, DENSE_STIFFNESS_POINTS)]
        out.append(np.linalg.eigvals(np.array(mats)).real.max())
    return np.array(out)


def _lyapunov_by_kronecker(a_m: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``P`` with ``A_m' P + P A_m = -Q`` from ``(I kron A_m' + A_m' kron I) vec P = -vec Q``."""
    n = a_m.shape[0]
    eye = np.eye(n)
    lhs = np.kron(eye, a_m.T) + np.kron(a_m.T, eye)
    return np.linalg.solve(lhs, -q.reshape(-1)).reshape(n, n)


def equilibrium_offset_m(vehicle, design, settings, stiffness, speed) -> float:
    """e1 (m) at the adaptive equilibrium on the design curvature, by elimination of u_ad.

    The condition closing the equations depends on the certified law: the gradient law rests
    where ``s_tilde' P_ad b_m = 0``; the piecewise-constant law's filter where ``u_ad`` cancels
    the output-equivalent of the whole uncertainty.
    """
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
    if design.certified_law == "gradient":
        u_ad = float(p_b @ (s_hat - s0)) / float(p_b @ s1)  # s_tilde' P_ad b_m = 0
    else:  # piecewise constant, ideal estimate: u_ad + r sigma(s, u_ad) = 0
        r = _output_row(a_m, b_m)
        w = stiffness / design.nominal_stiffness_n_per_rad

        def residual(u):
            s_u = s0 + s1 * u
            sigma = (a_cl - a_m) @ s_u + (w - 1.0) * b_m * (u + u_ff) + (g - g_hat) * psidot
            return u + float(r @ sigma)

        r0 = residual(0.0)
        u_ad = -r0 / (residual(1.0) - r0)  # the residual is affine in u_ad
    return float((s0 + s1 * u_ad)[0])


def offset_margin_m(vehicle, design, settings, speed) -> float:
    worst = max(abs(equilibrium_offset_m(vehicle, design, settings, c, speed))
                for c in _dense(*design.certified_interval, DENSE_STIFFNESS_POINTS))
    return vehicle.lane_margin_m - worst


def cornering_slip_angles(vehicle: VehicleParams, stiffness, speed, radius):
    """Slip angles (rad) of the linear single track in a steady turn (yaw rate V/R).

    Unknowns side velocity v_y and steering delta; ``alpha_f = delta - (v_y + l_f r)/V``,
    ``alpha_r = -(v_y - l_r r)/V``, forces ``2 C alpha_f`` and ``2 C_r alpha_r`` (C_r: the
    vehicle's rear tire, ``rear_tire_stiffness_scale / tire_stiffness_scale`` times C);
    lateral balance ``m V r = F_f + F_r`` and yaw balance ``l_f F_f - l_r F_r = 0``.
    """
    m, lf, lr = vehicle.mass_kg, vehicle.lf_m, vehicle.lr_m
    r = speed / radius
    kf = 2.0 * stiffness
    kr = 2.0 * stiffness * vehicle.rear_stiffness_ratio
    # F_f = kf (delta - (vy + lf r)/V), F_r = kr (-(vy - lr r)/V); unknowns (vy, delta)
    lhs = np.array([[-(kf + kr) / speed, kf], [(-lf * kf + lr * kr) / speed, lf * kf]])
    rhs = np.array([m * speed * r + kf * lf * r / speed - kr * lr * r / speed,
                    lf * kf * lf * r / speed + lr * kr * lr * r / speed])
    vy, delta = np.linalg.solve(lhs, rhs)
    return delta - (vy + lf * r) / speed, -(vy - lr * r) / speed


def fiala_utilisation(z: float) -> float:
    """Share of the grip ``|F| / (mu F_z)`` the Fiala brush tire uses at normalised slip z."""
    z = min(abs(z), 1.0)
    return 3.0 * z - 3.0 * z * z + z**3


def normalised_slip_for_utilisation(utilisation: float) -> float:
    """Inverse of :func:`fiala_utilisation` on ``[0, 1]`` by bisection (60 halvings)."""
    if utilisation >= 1.0:
        return 1.0
    lo, hi = 0.0, 1.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if fiala_utilisation(mid) < utilisation else (lo, mid)
    return 0.5 * (lo + hi)


def cornering_normalised_slip(vehicle: VehicleParams, friction_mu, speed, radius) -> float:
    """Largest normalised tire slip in a steady turn, from the axle force and moment balance.

    Axle forces from ``F_f + F_r = m V^2 / R`` and ``l_f F_f = l_r F_r`` (solved as a 2 x 2
    system), axle loads from the static moment balance, then each axle's utilisation
    ``F / (mu F_z,axle)`` inverted through the Fiala force by bisection.
    """
    m, lf, lr = vehicle.mass_kg, vehicle.lf_m, vehicle.lr_m
    f_f, f_r = np.linalg.solve(np.array([[1.0, 1.0], [lf, -lr]]),
                               np.array([m * speed**2 / radius, 0.0]))
    weight = m * GRAVITY_MPS2
    load_f, load_r = weight * lr / (lf + lr), weight * lf / (lf + lr)  # per axle
    return max(normalised_slip_for_utilisation(abs(f) / (friction_mu * load))
               for f, load in ((f_f, load_f), (f_r, load_r)))


def secant_stiffness_ratio(normalised_slip: float) -> float:
    """``F / (C tan a)`` of the Fiala tire at normalised slip z, from the force itself."""
    if normalised_slip == 0.0:
        return 1.0
    mu_fz, stiffness = 1.0, 1.0  # the ratio does not depend on them
    tan_a = 3.0 * normalised_slip * mu_fz / stiffness
    return mu_fz * fiala_utilisation(normalised_slip) / (stiffness * tan_a)


def vehicle_limit_values(vehicle, settings, speed) -> dict[str, float]:
    """Condition e recomputed from the vehicle's fields: ``limit - V^2 / R`` (m/s^2) for the
    rollover limit ``rollover_fraction g t / (2 h)`` (when the vehicle gives h and t) and the
    comfort limit (when set), keyed like the stored margins."""
    syn = settings.synthesis
    a_y = speed**2 / syn.design_radius_m
    out = {}
    if vehicle.cg_height_m is not None and vehicle.track_width_m is not None:
        tip = GRAVITY_MPS2 * vehicle.track_width_m / (2.0 * vehicle.cg_height_m)
        out["rollover_lateral_accel_mps2"] = syn.rollover_fraction * tip - a_y
    if syn.lateral_accel_limit_mps2 is not None:
        out["comfort_lateral_accel_mps2"] = syn.lateral_accel_limit_mps2 - a_y
    return out


def grip_margin_values(vehicle, design, settings, speed) -> tuple[float, float]:
    """``(z_b - steady normalised slip, fraction mu_lo g - V^2 / R)`` on the design curve."""
    syn = settings.synthesis
    radius = syn.design_radius_m
    z = cornering_normalised_slip(vehicle, design.friction_mu_lo, speed, radius)
    slip = design.tire_slip_bound - z
    accel = syn.lateral_accel_fraction * design.friction_mu_lo * GRAVITY_MPS2 - speed**2 / radius
    return float(slip), float(accel)


# ----------------------------------------------------------------- claims

def _consistency_failures(design, settings, conditions) -> list[tuple[str, str]]:
    syn = settings.synthesis
    out = []
    if design.certified_law != settings.controller.adaptation_law:
        out.append((CONSISTENCY, f"certified for the {design.certified_law} law but the "
                                 f"settings run {settings.controller.adaptation_law}"))
    if not 0.0 <= design.tire_slip_bound <= syn.normalised_slip_max:
        out.append((CONSISTENCY, f"tire slip bound {design.tire_slip_bound} not in [0, "
                                 f"normalised_slip_max {syn.normalised_slip_max}]"))
    tire_lo = design.stiffness_lo_n_per_rad * secant_stiffness_ratio(design.tire_slip_bound)
    if abs(design.certified_interval[0] - tire_lo) > 1e-9 * tire_lo:
        out.append((CONSISTENCY, f"certified lower stiffness {design.certified_interval[0]} is "
                                 f"not the Fiala secant stiffness {tire_lo:.6g} of C_lo at the "
                                 f"slip bound {design.tire_slip_bound}"))
    mid = 0.5 * (design.certified_interval[0] + design.certified_interval[1])
    if abs(design.nominal_stiffness_n_per_rad - mid) > 1e-9 * mid:
        out.append((CONSISTENCY, f"nominal stiffness {design.nominal_stiffness_n_per_rad} is "
                                 f"not the certified interval's midpoint {mid}"))
    # the piecewise-constant law: k w_max T_s <= 1 always (above filter_gain_max only where
    # the L1 condition binds, docs/design.md 5.3a); the gradient law: k <= filter_gain_max
    w_max = design.certified_interval[1] / design.nominal_stiffness_n_per_rad
    if design.certified_law == "piecewise_constant":
        t_s = settings.controller.sample_period_s
        if not 0.0 < design.filter_gain * w_max * t_s <= 1.0 + 1e-12:
            product = design.filter_gain * w_max * t_s
            out.append((CONSISTENCY, f"filter gain {design.filter_gain:g} breaks the sample-period "
                                     f"limit k w_max T_s <= 1 ({product:.4g} with w_max "
                                     f"{w_max:.4g}, T_s {t_s:g} s)"))
    elif not 0.0 < design.filter_gain <= syn.filter_gain_max:
        out.append((CONSISTENCY, f"filter gain {design.filter_gain} not in (0, filter_gain_max "
                                 f"{syn.filter_gain_max:g}]"))
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
        "steady_state_lane_margin_m": _guarded(
            lambda: offset_margin_m(vehicle, design, settings, speed)),
        "grip_normalised_slip": slip,
        "grip_lateral_accel_mps2": accel,
        **vehicle_limit_values(vehicle, settings, speed),
    }


def _condition_failures(margins, speed) -> list[tuple[str, str]]:
    out = []
    if margins["l1_condition"] <= 0.0:
        out.append(("l1_condition", f"||G||_L1 L = {1 - margins['l1_condition']:.6g} >= 1 at "
                                    f"{speed:.4g} m/s"))
    if margins["reference_stability_per_s"] <= 0.0:
        out.append(("reference_stability", "reference system max Re eig = "
                    f"{-margins['reference_stability_per_s']:.6g}/s >= 0 on [V_min, {speed:.4g}]"))
    if margins["steady_state_lane_margin_m"] < 0.0:
        out.append(("steady_state_offset", "steady-state offset exceeds the lane margin by "
                    f"{-margins['steady_state_lane_margin_m']:.4g} m at {speed:.4g} m/s"))
    if margins["grip_normalised_slip"] < -1e-12:
        out.append(("grip", "tire slip exceeds the bound by "
                            f"{-margins['grip_normalised_slip']:.4g} (normalised) at "
                            f"{speed:.4g} m/s"))
    if margins["grip_lateral_accel_mps2"] < -1e-12:
        out.append(("grip", "lateral acceleration exceeds the friction limit by "
                    f"{-margins['grip_lateral_accel_mps2']:.4g} m/s^2 at {speed:.4g} m/s"))
    for name, what in (("rollover", "the rollover limit"), ("comfort", "the comfort limit")):
        key = f"{name}_lateral_accel_mps2"
        if margins.get(key, 0.0) < -1e-12:
            out.append((name, f"lateral acceleration exceeds {what} by {-margins[key]:.4g} "
                              f"m/s^2 at {speed:.4g} m/s"))
    return out


SPEED_LIMITS = ("", "l1_condition", "reference_stability", "steady_state_offset", "grip",
                "rollover", "comfort", "speed_range")  # ControllerDesign.speed_limited_by


def _binding_failures(vehicle, design, settings) -> list[tuple[str, str]]:
    """The stated binding limit is a known one; a rollover or comfort limit said to bind is
    given and lies within one speed-grid step above the design speed."""
    claim = design.speed_limited_by
    if claim not in SPEED_LIMITS:
        return [(CONSISTENCY, f"speed_limited_by = {claim!r}; known: "
                              f"{', '.join(s for s in SPEED_LIMITS if s)}")]
    if claim not in ("rollover", "comfort"):
        return []
    syn = settings.synthesis
    room = vehicle_limit_values(vehicle, settings, design.speed_mps).get(
        f"{claim}_lateral_accel_mps2")
    if room is None:
        return [(CONSISTENCY, f"speed said to be limited by {claim}, which this vehicle and "
                              "these settings do not give")]
    limit_speed = math.sqrt((room + design.speed_mps**2 / syn.design_radius_m)
                            * syn.design_radius_m)
    if limit_speed - design.speed_mps > syn.speed_grid_step_mps:
        return [(CONSISTENCY, f"speed said to be limited by {claim}, but that limit allows "
                              f"{limit_speed:.4g} m/s, above the design's {design.speed_mps:.4g}")]
    return []


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
    if conditions is not None:  # the vehicle's tires scale the table's stiffness
        conditions = conditions.with_stiffness_scale(vehicle.tire_stiffness_scale)
    failures = _consistency_failures(design, settings, conditions)
    margins: dict = {}
    if design.failed_condition == GAIN_LMI and design.speed_mps == 0.0:
        # no k_m was found: the car stops, which is always safe; nothing else is claimed
        return DesignVerification(index, list(design.labels), 0.0, margins, failures,
                                  design.interval, design.speed_limited_by)
    margins["gain_decay_per_s"] = gain_decay_margin(vehicle, design, settings)
    if margins["gain_decay_per_s"] < -1e-6:
        failures.append(("gain_decay", "k_m does not give decay rate "
                         f"{syn.decay_rate}/s: max Re eig(A - b k_m) = "
                         f"{-margins['gain_decay_per_s'] - syn.decay_rate:.6g}/s"))
        if margins["gain_decay_per_s"] + syn.decay_rate <= 0.0:
            # A - b k_m not Hurwitz: A_m, P_ad and the equilibrium do not exist
            return DesignVerification(index, list(design.labels), design.speed_mps, margins,
                                      failures, design.interval, design.speed_limited_by)
    if design.speed_mps > 0.0:
        margins.update(_conditions_at(vehicle, design, settings, design.speed_mps))
        failures += _condition_failures(margins, design.speed_mps)
        failures += _binding_failures(vehicle, design, settings)
        failures += _claim_failures(design.margins, margins)
    else:
        failures += _no_safe_speed_failures(vehicle, design, settings, margins)
    return DesignVerification(index, list(design.labels), design.speed_mps, margins, failures,
                              design.interval, design.speed_limited_by)


def _no_safe_speed_failures(vehicle, design, settings, margins) -> list[tuple[str, str]]:
    """The claim 'no safe speed' holds if some condition fails at every grid speed."""
    syn = settings.synthesis
    v_hi = max(design.gain_speed_max_mps, syn.speed_min_mps)
    count = int(np.floor((v_hi - syn.speed_min_mps) / syn.speed_grid_step_mps + 1e-9))
    grid = syn.speed_min_mps + syn.speed_grid_step_mps * np.arange(count + 1)
    ref = np.maximum.accumulate(reference_abscissas(vehicle, design, grid))
    for v, abscissa in zip(grid, ref, strict=True):
        slip, accel = grip_margin_values(vehicle, design, settings, v)
        limits = vehicle_limit_values(vehicle, settings, v)
        if min(slip, accel, *limits.values()) < 0.0 or abscissa >= 0.0:
            continue
        if _guarded(lambda v=v: offset_margin_m(vehicle, design, settings, v)) < 0.0:
            continue
        l1 = _guarded(lambda v=v: 1.0 - l1_condition_value(vehicle, design, v))
        if l1 > 0.0:
            margins.update({"l1_condition": l1, "reference_stability_per_s": -float(abscissa),
                            "grip_normalised_slip": slip, "grip_lateral_accel_mps2": accel,
                            **limits})
            return [(NO_SAFE_SPEED_CLAIM, f"claims no safe speed ({design.failed_condition}) "
                                          f"but every condition holds at {v:.4g} m/s")]
    return []


def _differences(embedded, reference, path: str) -> list[str]:
    """Paths (``settings.synthesis.design_radius_m``) where two plain structures differ."""
    if isinstance(embedded, dict) and isinstance(reference, dict):
        out = []
        for key in list(reference) + [k for k in embedded if k not in reference]:
            if key not in embedded or key not in reference:
                out.append(f"{path}.{key}")
            else:
                out += _differences(embedded[key], reference[key], f"{path}.{key}")
        return out
    if isinstance(embedded, list) and isinstance(reference, list):
        if len(embedded) != len(reference):
            return [path]
        return [d for i, (a, b) in enumerate(zip(embedded, reference, strict=True))
                for d in _differences(a, b, f"{path}[{i}]")]
    return [] if embedded == reference else [path]


def _lookup(data, path: str):
    for part in path.replace("[", ".[").split(".")[1:]:
        if part.startswith("["):
            data = data[int(part[1:-1])]
        else:
            data = data.get(part, "(absent)") if isinstance(data, dict) else "(absent)"
    return data


def reference_input_failures(table: DesignTable, vehicle: VehicleParams | None = None,
                             settings: Settings | None = None,
                             conditions: ConditionsTable | None = None
                             ) -> list[tuple[str, str]]:
    """``(INPUT_MISMATCH, message)`` for each given reference that the file's copy differs from.

    The message names the first differing field (``settings.synthesis.lateral_accel_fraction``)
    with both values. A file without embedded conditions fails when conditions are given.
    """
    out = []
    for name, embedded, reference in (("vehicle", table.vehicle, vehicle),
                                      ("settings", table.settings, settings),
                                      ("conditions", table.conditions, conditions)):
        if reference is None:
            continue
        if embedded is None:
            out.append((INPUT_MISMATCH, f"the file embeds no {name}; --{name} was given"))
            continue
        ref, emb = dataclasses.asdict(reference), dataclasses.asdict(embedded)
        diffs = _differences(emb, ref, name)
        if diffs:
            out.append((INPUT_MISMATCH, f"embedded {diffs[0]} = {_lookup(emb, diffs[0])!r} differs "
                                        f"from the reference {_lookup(ref, diffs[0])!r}"
                        + (f" (and {len(diffs) - 1} more)" if len(diffs) > 1 else "")))
    return out


def completeness_check(designs: list[ControllerDesign], conditions: ConditionsTable
                       ) -> tuple[int, list[MissingDesign], list[tuple[str, str]], list[str]]:
    """``(label ranges, missing, failures, notes)`` of a table against ``conditions``.

    The label ranges are every run of consecutive labels of each preset in its friction order
    (``ConditionsTable.contiguous_ranges``), one per label tuple across presets: what
    ``drake_cert.synthesis.table.design_label_ranges`` synthesizes. A range without a design with
    exactly those labels is missing (a :data:`COMPLETENESS` failure naming it and its presets); a
    range with several designs is a failure too (which one the run time would use is not defined).
    A design whose labels are no such range (unused at run time) is a note; a regression
    design (no labels) is not counted.
    """
    presets_of: dict[tuple[str, ...], list[str]] = {}
    for preset in conditions.presets:
        for labels in conditions.contiguous_ranges(preset.name):
            presets_of.setdefault(tuple(labels), []).append(preset.name)
    indices_of: dict[tuple[str, ...], list[int]] = {}
    for i, d in enumerate(designs):
        if d.labels:
            indices_of.setdefault(tuple(d.labels), []).append(i)
    missing = [MissingDesign(list(r), p) for r, p in presets_of.items() if r not in indices_of]
    failures = [(COMPLETENESS, m.message) for m in missing]
    failures += [(COMPLETENESS, f"{len(idx)} designs for label range {'+'.join(r)} (designs "
                                f"{', '.join(map(str, idx))}): the run time would use one of them")
                 for r, idx in indices_of.items() if r in presets_of and len(idx) > 1]
    notes = [f"design {idx[0]} ({'+'.join(r)}) is for no label range of the conditions' "
             "presets (never selected at run time)"
             for r, idx in indices_of.items() if r not in presets_of]
    return len(presets_of), missing, failures, notes


def completeness_reference(table: DesignTable, conditions: ConditionsTable | None,
                           complete: bool | None) -> str:
    """Which conditions completeness is checked against: ``"reference conditions"``,
    ``"embedded conditions"`` or ``""`` (not checked). ``complete=None`` checks it when
    reference ``conditions`` are given (the command line also turns it on for a table that
    embeds its conditions); :class:`ConfigError` when it is asked for and the file embeds no
    conditions and none are given."""
    if complete is None:
        complete = conditions is not None
    if not complete:
        return ""
    if conditions is not None:
        return "reference conditions"
    if table.conditions is None:
        raise ConfigError("cannot check that the design table is complete: the design file "
                          "embeds no conditions and no reference conditions were given")
    return "embedded conditions"


def _loaded(value, loader):
    """``value`` as it is, or loaded from a path with ``loader`` (which raises the typed error
    naming the file when it cannot be read)."""
    if value is None or not isinstance(value, (str, Path)):
        return value
    return loader(value)


def verify_design_table(table: DesignTable | str | Path, progress=None, *,
                        vehicle: VehicleParams | str | Path | None = None,
                        settings: Settings | str | Path | None = None,
                        conditions: ConditionsTable | str | Path | None = None,
                        require_switching: bool = False,
                        complete: bool | None = None) -> VerificationReport:
    """Verify every design of a design table; ``progress(i, n)`` is called per design.

    ``table``: a loaded :class:`DesignTable` or the path of a design file (table or single
    design); ``vehicle``, ``settings``, ``conditions``: loaded objects or paths of YAML files.
    An unreadable or invalid file raises :class:`drake_cert.errors.DesignFormatError` (the
    design file) or :class:`drake_cert.errors.ConfigError` (a reference file), naming it.

    The table's switching certificates, when present, are rechecked
    (:func:`drake_cert.synthesis.verify_switching.check_table_switching`, with this module's
    reference systems; failures named ``switching``). A
    table with at most one design with a safe speed needs none; otherwise a missing section is a
    note (``report.notes``), or a failure with ``require_switching``.

    Reference inputs (``vehicle``, ``settings``, ``conditions``), when given, must equal the
    copies the file embeds (else :data:`INPUT_MISMATCH` failures naming the field), and every
    condition is recomputed with them; without them the file's own copies are used, which
    only shows the file is self-consistent (``report.checked_against == "embedded"``).

    ``complete``: whether the table must hold a design for every label range the conditions
    define (:func:`completeness_check`; failures named ``completeness``). ``None`` (default):
    when reference ``conditions`` are given. Checked against the reference conditions, else
    the embedded ones; :class:`ConfigError` when there are none to check against.
    """
    table = _loaded(table, load_design_file)
    vehicle = _loaded(vehicle, load_vehicle)
    settings = _loaded(settings, load_settings)
    conditions = _loaded(conditions, load_conditions)
    completeness_against = completeness_reference(table, conditions, complete)
    given = [n for n, x in (("vehicle", vehicle), ("settings", settings),
                            ("conditions", conditions)) if x is not None]
    input_failures = reference_input_failures(table, vehicle, settings, conditions)
    vehicle = vehicle if vehicle is not None else table.vehicle
    settings = settings if settings is not None else table.settings
    conditions = conditions if conditions is not None else table.conditions
    out = []
    for i, design in enumerate(table.designs):
        if progress is not None:
            progress(i, len(table.designs))
        out.append(verify_design(design, vehicle, settings, conditions, i))
    switching_failures, notes = [], []
    if table.switching is not None:
        switching_failures = [(SWITCHING, m) for m in check_table_switching(
            vehicle, table.designs, settings, conditions, table.switching,
            functools.partial(reference_matrix, vehicle))]
    elif sum(d.has_safe_speed for d in table.designs) > 1:
        if require_switching:
            switching_failures.append((SWITCHING, NO_SWITCHING_NOTE))
        else:
            notes.append(NO_SWITCHING_NOTE)
    ranges, missing, completeness_failures = 0, [], []
    if completeness_against:
        ranges, missing, completeness_failures, extra = completeness_check(table.designs,
                                                                           conditions)
        notes += extra
    return VerificationReport(out, input_failures, ", ".join(given) or "embedded",
                              switching_failures, notes, table.switching is not None,
                              completeness_against, ranges, missing, completeness_failures)
