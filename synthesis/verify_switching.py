"""Verify's own check of stored switching certificates (DESIGN 5.5, 5.6): no solver, and none
of the synthesis's matrices.

A certificate (:class:`drake_cert.synthesis.switching.SwitchingCertificate`, the data only) holds
when every design of its family with a safe speed is covered; every stored matrix is finite,
symmetric and positive definite; at every corner of every covered design's box
``certified_interval x [speed_min, gain_speed_max]`` the closed loop ``A(C, V) - b(C) k_m``,
built here from eq. 2.45 itself, decays at the stored rate under the matrix
(``-lambda_max(P^-1 sym(M' P + P M)) / 2``) within :data:`SWITCHING_TOLERANCE` (1/s); for
"dwell", the modes' largest ``lambda_max(P_n^-1 P_m)`` is within the stored mu and the dwell time
at least ``ln(mu) / (2 lambda_0)``; and the L1 loops' 5 x 5 matrix, when stored, reaches its
rate at both interval ends and on a speed grid shifted half a step from the synthesis's, with
the reference system built by the caller (verify's own builder) and moved here to the steering
coordinates ``[s, u - u_ff]`` it is stated on. Failures are readable strings.
"""

import math

import numpy as np
import scipy.linalg

from drake_cert.config import ConditionsTable, Settings, SynthesisSettings, VehicleParams
from drake_cert.dynamics import lateral_error_dynamics
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.synthesis.lyapunov_rate import certified_rate
from drake_cert.synthesis.switching import (
    COMMON,
    DWELL,
    METHODS,
    NONE,
    SwitchingCertificate,
    design_key,
    switching_families,
)

SWITCHING_TOLERANCE = 1.0e-6  # 1/s slack on the stored decay rate (the gain grid check's)
JUMP_TOLERANCE = 1.0e-6  # relative slack on the stored jump factor mu
LOOP_TOLERANCE = 1.0e-6  # 1/s slack on the stored loop decay rate
LOOP_CHECK_STEP_MPS = 0.25  # the loop check's speed grid step, shifted by half a step


def corners(design: ControllerDesign, speed_min_mps: float) -> list[tuple[float, float]]:
    """The four (C, V) corners (N/rad, m/s) of the design's box."""
    lo, hi = design.certified_interval
    top = max(design.gain_speed_max_mps, speed_min_mps)
    return [(c, v) for c in (lo, hi) for v in (speed_min_mps, top)]


def closed_loop(vehicle: VehicleParams, design: ControllerDesign, c: float,
                v: float) -> np.ndarray:
    """``A(C, V) - b(C) k_m`` (4 x 4, 1/s) from eq. 2.45."""
    a, b, _ = lateral_error_dynamics(vehicle, c, v)
    return a - np.outer(b, design.k_m_array)


def check_switching_certificate(vehicle: VehicleParams, designs: list[ControllerDesign],
                                settings: Settings | SynthesisSettings,
                                certificate: SwitchingCertificate,
                                reference_matrix=None) -> list[str]:
    """Failures of ``certificate`` for the family ``designs`` (module docstring); [] if it
    holds. ``reference_matrix(design, C, V)``: the 5 x 5 reference system of the L1 loop; the
    loop matrix is not checked without it (and a stored one is then a failure)."""
    syn = settings.synthesis if isinstance(settings, Settings) else settings
    name = f"switching certificate ({certificate.family})"
    covered = [d for d in designs if d.has_safe_speed]
    keys = [design_key(d) for d in covered]
    if certificate.method not in METHODS:
        return [f"{name}: unknown method {certificate.method!r}"]
    failures = []
    missing = [k for k in keys if k not in certificate.designs_covered]
    if missing:
        failures.append(f"{name}: design {missing[0]} has a safe speed but is not covered"
                        + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    if certificate.method == NONE:
        return failures
    if not (math.isfinite(certificate.decay_rate_per_s) and certificate.decay_rate_per_s > 0.0):
        return failures + [f"{name}: decay rate {certificate.decay_rate_per_s!r}/s must be "
                           "positive"]
    matrix_of, found = _matrix_assignment(certificate, keys, name)
    failures += found
    if matrix_of is None:
        return failures
    matrices, found = _checked_matrices({v[0]: v[1] for v in matrix_of.values()}, 4, name)
    failures += found
    stored = {key: (matrix_of[key][0], matrices[matrix_of[key][0]]) for key in keys
              if key in matrix_of and matrix_of[key][0] in matrices}
    failures += _corner_failures(vehicle, syn.speed_min_mps, list(zip(covered, keys, strict=True)),
                                 stored, certificate, name)
    if certificate.method == DWELL:
        failures += _dwell_failures(matrices, certificate, name)
    return failures + _loop_failures(covered, settings, syn.speed_min_mps, certificate, name,
                                     reference_matrix)


def check_table_switching(vehicle: VehicleParams, designs: list[ControllerDesign],
                          settings: Settings | SynthesisSettings,
                          conditions: ConditionsTable | None,
                          certificates: tuple[SwitchingCertificate, ...],
                          reference_matrix=None) -> list[str]:
    """:func:`check_switching_certificate` for every switching family of the table; a family
    with a design with a safe speed but no certificate, a family certified twice, and a design
    with a safe speed in no family are failures too (a certificate for a family the conditions
    do not name proves nothing needed and is ignored)."""
    families = switching_families(designs, conditions)
    by_family = {c.family: c for c in certificates}
    failures = []
    if len(by_family) != len(certificates):
        failures.append("switching certificates: a family is certified twice")
    in_family = {design_key(d) for _, members in families for d in members}
    for d in designs:
        if d.has_safe_speed and design_key(d) not in in_family:
            failures.append(f"switching certificates: design {design_key(d)} has a safe speed "
                            "but belongs to no switching family (no preset's label range)")
    for name, members in families:
        if name not in by_family:
            if any(d.has_safe_speed for d in members):
                failures.append(f"switching certificates: family {name} has no certificate")
            continue
        failures += check_switching_certificate(vehicle, members, settings, by_family[name],
                                                reference_matrix)
    return failures


def _matrix_assignment(certificate: SwitchingCertificate, keys: list[str], name: str
                       ) -> tuple[dict | None, list[str]]:
    """Which stored matrix proves each covered design: ``({key: (label, rows)}, failures)``."""
    if certificate.method == COMMON:
        if certificate.lyapunov_matrix is None:
            return None, [f"{name}: method 'common' without a Lyapunov matrix"]
        failures = ([] if certificate.dwell_time_s == 0.0 else
                    [f"{name}: a common P needs no dwell time, but {certificate.dwell_time_s} s "
                     "is stored"])
        return {k: ("P", certificate.lyapunov_matrix) for k in keys}, failures
    matrix_of = {k: (f"P_{i}", mode.lyapunov_matrix)
                 for i, mode in enumerate(certificate.modes) for k in mode.designs}
    unassigned = [k for k in keys if k not in matrix_of]
    return matrix_of, ([f"{name}: design {unassigned[0]} has no mode Lyapunov matrix"]
                       if unassigned else [])


def _checked_matrices(rows_of: dict, size: int, name: str
                      ) -> tuple[dict[str, np.ndarray], list[str]]:
    """The stored matrices that are finite, size x size, symmetric and positive definite, by
    label, and the failures of the others."""
    failures, matrices = [], {}
    for label, rows in rows_of.items():
        p = np.asarray(rows, dtype=float)
        if p.shape != (size, size) or not np.all(np.isfinite(p)):
            failures.append(f"{name}: {label} must be a finite {size} x {size} matrix")
        elif np.abs(p - p.T).max() > 1e-9 * max(np.abs(p).max(), 1.0):
            failures.append(f"{name}: {label} is not symmetric")
        elif np.linalg.eigvalsh(p).min() <= 0.0:
            failures.append(f"{name}: {label} is not positive definite (smallest eigenvalue "
                            f"{np.linalg.eigvalsh(p).min():.6g})")
        else:
            matrices[label] = p
    return matrices, failures


def _corner_failures(vehicle, speed_min_mps, covered: list, stored: dict, certificate,
                     name) -> list[str]:
    """The covered designs (first failing corner each) whose matrix proves less than the
    stored decay rate. ``covered``: (design, key) pairs; ``stored``: key -> (label, P) of the
    designs with a checked matrix (the others are skipped: their failure is reported
    elsewhere)."""
    failures = []
    wanted = certificate.decay_rate_per_s - SWITCHING_TOLERANCE
    for d, key in covered:
        if key not in stored:
            continue
        label, p = stored[key]
        for c, v in corners(d, speed_min_mps):
            m = closed_loop(vehicle, d, c, v)
            rate = certified_rate(p, m)
            if rate < wanted:
                lyap = m.T @ p + p @ m + 2.0 * certificate.decay_rate_per_s * p
                worst = float(np.linalg.eigvalsh(0.5 * (lyap + lyap.T)).max())
                failures.append(
                    f"{name}: at design {key}'s corner C = {c:.6g} N/rad, V = {v:.4g} m/s, "
                    f"{label} proves decay {rate:.6g}/s < the stored {certificate.decay_rate_per_s}"
                    f"/s (max eig of the symmetrised LMI {worst:.6g} > 0)")
                break
    return failures


def _dwell_failures(matrices: dict[str, np.ndarray], certificate: SwitchingCertificate,
                    name: str) -> list[str]:
    """For "dwell": the stored jump factor mu and dwell time against the modes' matrices."""
    ps = list(matrices.values())
    mu = max((float(scipy.linalg.eigh(a, b, eigvals_only=True).max())
              for a in ps for b in ps if a is not b), default=1.0)
    failures = []
    if mu > certificate.jump_factor * (1.0 + JUMP_TOLERANCE):
        failures.append(f"{name}: jump factor max lambda_max(P_n^-1 P_m) = {mu:.6g} exceeds "
                        f"the stored {certificate.jump_factor}")
    need = math.log(max(mu, 1.0)) / (2.0 * certificate.decay_rate_per_s)
    if certificate.dwell_time_s < need * (1.0 - JUMP_TOLERANCE):
        failures.append(f"{name}: dwell time {certificate.dwell_time_s} s is below "
                        f"ln(mu) / (2 lambda_0) = {need:.6g} s")
    return failures


def check_speeds(design: ControllerDesign, speed_min_mps: float) -> np.ndarray:
    """The loop check's speeds: both ends of ``[speed_min, design speed + margin]``
    (:func:`drake_cert.synthesis.loop_switching.loop_speed_top`) and the points half a step
    inside a grid of :data:`LOOP_CHECK_STEP_MPS` (speeds the synthesis did not pose its LMI
    at)."""
    from drake_cert.synthesis.loop_switching import loop_speed_top

    top = loop_speed_top(design, speed_min_mps)
    inner = np.arange(speed_min_mps + 0.5 * LOOP_CHECK_STEP_MPS, top, LOOP_CHECK_STEP_MPS)
    return np.unique(np.concatenate([[speed_min_mps], inner, [top]]))


def _on_steering(reference: np.ndarray, k_m: np.ndarray) -> np.ndarray:
    """The reference matrix on ``[s, u_ad]`` as it acts on ``[s, u_ad - k_m' s]``: the last row
    gains ``-k_m'`` times the plant rows, the last column's effect is added back into the
    state columns (``u_ad = zeta_5 + k_m' s``)."""
    m = np.array(reference, dtype=float)
    m[4, :] -= k_m @ m[:4, :]
    m[:, :4] += np.outer(m[:, 4], k_m)
    return m


def _loop_failures(covered, settings, speed_min_mps, certificate, name,
                   reference_matrix) -> list[str]:
    """The L1 loops' matrix (or per-design matrices), when stored: for the law of ``settings``
    (when known), finite, symmetric, positive definite, and its rate reached at every check
    point of its designs; for per-design matrices also every design covered, the stored jump
    factor at least ``lambda_max(P_j^-1 P_i)`` and the dwell at least ``ln(mu) / (2 lambda)``.
    A loop decay claimed without a matrix is a failure."""
    stored = ({"loop_lyapunov_matrix": certificate.loop_lyapunov_matrix}
              if certificate.loop_lyapunov_matrix is not None else
              {f"loop_modes[{i}]": m.lyapunov_matrix
               for i, m in enumerate(certificate.loop_modes)})
    if not stored:
        if certificate.loop_decay_rate_per_s > 0.0:
            return [f"{name}: claims loop decay {certificate.loop_decay_rate_per_s}/s for the L1 "
                    "loops but stores no loop matrix that proves it"]
        return []
    law = certificate.loop_law
    if isinstance(settings, Settings) and law != settings.controller.adaptation_law:
        return [f"{name}: the loop matrix is for the {law!r} law, the settings run "
                f"{settings.controller.adaptation_law!r}"]
    if certificate.loop_decay_rate_per_s <= 0.0:
        return [f"{name}: loop_decay_rate_per_s = {certificate.loop_decay_rate_per_s} must be "
                "positive"]
    matrices, failures = _checked_matrices(stored, 5, name)
    if failures:
        return failures
    if reference_matrix is None:
        return [f"{name}: a loop matrix is stored but no reference system was given to check it"]
    if certificate.loop_lyapunov_matrix is not None:
        of_design = {design_key(d): matrices["loop_lyapunov_matrix"] for d in covered}
    else:
        of_design = {key: matrices[f"loop_modes[{i}]"]
                     for i, m in enumerate(certificate.loop_modes) for key in m.designs}
        missing = [design_key(d) for d in covered if design_key(d) not in of_design]
        if missing:
            return [f"{name}: loop_modes cover no matrix for design {missing[0]}"]
    for d in covered:
        failure = _loop_rate_failure(d, of_design[design_key(d)], reference_matrix,
                                     speed_min_mps, certificate, name)
        if failure:
            return [failure]
    if certificate.loop_modes:
        return _loop_dwell_failures(list(of_design.values()), certificate, name)
    return []


def _loop_rate_failure(design, p, reference_matrix, speed_min_mps, certificate, name) -> str:
    """'' when ``p`` proves the stored loop rate at both ends of ``design``'s interval and every
    check speed; else the failure."""
    key = design_key(design)
    for c in design.certified_interval:
        for v in check_speeds(design, speed_min_mps):
            try:
                m = _on_steering(reference_matrix(design, c, v), design.k_m_array)
            except np.linalg.LinAlgError:  # e.g. a gain that leaves A_m singular
                return (f"{name}: design {key} has no reference loop to check the loop "
                        "matrix on (its nominal loop A_m is singular)")
            if not np.all(np.isfinite(m)):
                return (f"{name}: design {key}'s reference loop is not finite at "
                        f"C = {c:.6g} N/rad, V = {v:.4g} m/s")
            rate = certified_rate(p, m)
            if rate < certificate.loop_decay_rate_per_s - LOOP_TOLERANCE:
                return (f"{name}: the loop matrix proves decay {rate:.6g}/s < the stored "
                        f"{certificate.loop_decay_rate_per_s}/s for design {key} at "
                        f"C = {c:.6g} N/rad, V = {v:.4g} m/s")
    return ""


def _loop_dwell_failures(ps: list[np.ndarray], certificate, name) -> list[str]:
    """The per-design loop matrices' jump factor and the dwell it needs, recomputed."""
    mu = max([1.0] + [float(scipy.linalg.eigh(a, b, eigvals_only=True).max())
                      for i, a in enumerate(ps) for j, b in enumerate(ps) if i != j])
    if mu > certificate.loop_jump_factor * (1.0 + JUMP_TOLERANCE):
        return [f"{name}: the loop matrices jump by {mu:.6g} at a switch > the stored "
                f"loop_jump_factor {certificate.loop_jump_factor}"]
    need = math.log(mu) / (2.0 * certificate.loop_decay_rate_per_s) if mu > 1.0 else 0.0
    if certificate.loop_dwell_time_s < need * (1.0 - 1e-9):
        return [f"{name}: loop_dwell_time_s = {certificate.loop_dwell_time_s} s is below "
                f"ln(mu_z) / (2 lambda_z) = {need:.6g} s"]
    return []
