"""Switching certificate: one Lyapunov argument for switching among controller designs.

Certifies the switched *reference (state-feedback) loops* of one preset's designs
(``drake_cert.systems.certified_interval.designs_for_preset``),

    s' = (A(C(t), V(t)) - b(C(t)) k_sigma(t)) s,      (C(t), V(t)) in B_sigma(t),

with s = [e1, e1dot, e2, e2dot] (m, m/s, rad, rad/s), decay rates in 1/s, times in s, and
``B_i = [C_lo, C_hi] x [speed_min, gain_speed_max]`` the box of design i, ``[C_lo, C_hi]`` its
:attr:`~drake_cert.synthesis.design.ControllerDesign.certified_interval` (tire-widened, where
the true stiffness lies while the design is in force if perception is right). C and V may vary
in time inside the box of the design in force.

``method = "common"``: one matrix ``P`` (smallest eigenvalue 1) with
``(A - b k_i)' P + P (A - b k_i) + 2 lambda P <= 0`` (lambda = ``decay_rate_per_s``) at the four
corners of every covered box; the corners suffice exactly, since the left side is affine in
``(C, C/V)``. Stability at rate lambda under switching at any rate: ``dwell_time_s = 0``.
``method = "dwell"`` (no common P): one ``P_m`` per mode (designs sharing gain, certified
interval and gain speed range) at a common rate ``lambda_0``, with ``P_m <= mu P_n``;
exponentially stable for switching with average dwell above
``dwell_time_s = ln(mu) / (2 lambda_0)`` (Hespanha and Morse). The argument for both, and the
measured rates: DESIGN 5.6 (a) and (c).

The L1 loops with their filter state get a matrix of their own, stored in the same
certificate (:mod:`drake_cert.synthesis.loop_switching`, DESIGN 5.6 (b)). With jointly
synthesized gains (:mod:`drake_cert.synthesis.joint_gains`, the default) "common" exists.
The solve uses cvxpy + Clarabel (:func:`drake_cert.synthesis.gains.solve_sdp`); the stored
claim is what the returned matrices prove (generalized eigenvalues), and
verify rechecks it its own way, without any solver
(:mod:`drake_cert.synthesis.verify_switching`).
"""

import dataclasses
import math
import time

import numpy as np

from drake_cert.config import ConditionsTable, Settings, SynthesisSettings, VehicleParams
from drake_cert.dynamics import lateral_error_dynamics
from drake_cert.errors import InfeasibleDesign
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.synthesis.lyapunov_rate import certified_rate
from drake_cert.synthesis.mode_lyapunov import (
    ModeProblem,
    decay_constraints,
    largest_jump,
    least_jump_matrices,
)

COMMON = "common"
DWELL = "dwell"
NONE = "none"  # no design of the set has a safe speed: nothing switches
METHODS = (COMMON, DWELL, NONE)
TABLE_FAMILY = "table"  # the family name when a table embeds no conditions (all its designs)
# the state the L1 loops' matrix is stated on (loop_switching.steering_coordinates); files
# written before it have a matrix on [s, u_ad] with a dwell for the estimate's dropout
LOOP_STATE = "s, u - u_ff"

DECAY_BISECTION_TOLERANCE = 1.0e-3  # 1/s, the common-P decay bisection
DWELL_DECAY_FRACTIONS = (0.5, 0.75)  # of settings.decay_rate: lambda_0 candidates
JUMP_START = 1.0e4  # first mu tried (the joint problem is feasible there in practice)
JUMP_BISECTION_RATIO = 1.05  # mu bisection stops when hi / lo <= this


@dataclasses.dataclass(frozen=True)
class SwitchingMode:
    """Designs sharing one Lyapunov matrix in a ``"dwell"`` certificate.

    ``designs``: their :func:`design_key` names; ``lyapunov_matrix``: P_m (4 x 4, or 5 x 5 for
    the L1 loops' ``loop_modes``; symmetric;
    the modes' matrices share one scale, the least smallest eigenvalue among them is 1)."""

    designs: tuple[str, ...]
    lyapunov_matrix: tuple[tuple[float, ...], ...]


@dataclasses.dataclass(frozen=True)
class SwitchingCertificate:
    """What is proved about switching among one family's designs (module docstring).

    ``family``: the preset whose designs switch among each other (or ``"table"``);
    ``method``: ``"common"``, ``"dwell"`` or ``"none"`` (no design with a safe speed);
    ``designs_covered``: :func:`design_key` of every design with a safe speed of the family;
    ``decay_rate_per_s``: lambda (common) or lambda_0 (dwell), the state decay rate (1/s);
    ``dwell_time_s``: 0 for "common"; ``ln(mu) / (2 lambda_0)`` for "dwell" (the average dwell
    time must exceed it); ``lyapunov_matrix``: the common P (4 x 4, smallest eigenvalue 1),
    None for "dwell"; ``modes``: the per-mode matrices (dwell only); ``jump_factor``: mu (1 for
    common); ``condition_number``: of P (common) or the largest of the P_m;
    ``loop_lyapunov_matrix``: P_z (5 x 5) common to the designs' L1 reference loops with the
    filter state (:mod:`drake_cert.synthesis.loop_switching`), None when there is none (the
    gradient law, or none found); ``loop_decay_rate_per_s``: the rate lambda_z it proves on its
    grid; ``loop_law``: the adaptation law whose reference loops it covers;
    the matrix is stated on the steering coordinates ``[s, u - u_ff]`` (:data:`LOOP_STATE`), which
    a switch leaves in place, so the L1 loops need no dwell; ``loop_modes``: where the L1 loops
    share no matrix, one 5 x 5 matrix per design (:func:`drake_cert.synthesis.loop_switching.
    loop_dwell_matrices`), then ``loop_decay_rate_per_s`` is their common rate lambda_0,
    ``loop_jump_factor`` mu_z the most a switch multiplies ``zeta' P zeta`` by and
    ``loop_dwell_time_s`` = ``ln(mu_z) / (2 lambda_0)`` the average dwell they need (not
    enforced by the car; each drive reports whether it kept it);
    ``solve_time_s``: wall time of the solve (informative: not checked, not saved).
    """

    family: str
    method: str
    designs_covered: tuple[str, ...]
    decay_rate_per_s: float
    dwell_time_s: float
    lyapunov_matrix: tuple[tuple[float, ...], ...] | None = None
    modes: tuple[SwitchingMode, ...] = ()
    jump_factor: float = 1.0
    condition_number: float = 1.0
    loop_lyapunov_matrix: tuple[tuple[float, ...], ...] | None = None
    loop_decay_rate_per_s: float = 0.0
    loop_law: str = ""
    loop_modes: tuple[SwitchingMode, ...] = ()
    loop_jump_factor: float = 1.0
    loop_dwell_time_s: float = 0.0
    solve_time_s: float = dataclasses.field(default=0.0, compare=False)


def has_loop_certificate(certificate: SwitchingCertificate) -> bool:
    """Whether the L1 loops carry a certificate: a common matrix or one per design."""
    return certificate.loop_lyapunov_matrix is not None or bool(certificate.loop_modes)


def design_key(design: ControllerDesign) -> str:
    """The name a certificate lists a design under: its labels joined by ``+`` (as
    ``simulate --labels`` reads them), or ``[C_lo, C_hi]`` (N/rad) for a regression design."""
    if design.labels:
        return "+".join(design.labels)
    return f"[{design.stiffness_lo_n_per_rad:.9g}, {design.stiffness_hi_n_per_rad:.9g}]"


def _synthesis(settings) -> SynthesisSettings:
    return settings.synthesis if isinstance(settings, Settings) else settings


def box_corners(design: ControllerDesign, speed_min_mps: float) -> list[tuple[float, float]]:
    """The four (C, V) corners (N/rad, m/s) of ``certified_interval x [speed_min,
    gain_speed_max]``."""
    lo, hi = design.certified_interval
    v_hi = max(design.gain_speed_max_mps, speed_min_mps)
    return [(c, v) for c in (lo, hi) for v in (speed_min_mps, v_hi)]


def corner_matrices(vehicle: VehicleParams, design: ControllerDesign,
                    speed_min_mps: float) -> list[np.ndarray]:
    """``A(C, V) - b(C) k_m`` (4 x 4, 1/s) at the four corners of the design's box."""
    out = []
    for c, v in box_corners(design, speed_min_mps):
        a, b, _ = lateral_error_dynamics(vehicle, c, v)
        out.append(a - np.outer(b, design.k_m_array))
    return out


def _modes(vehicle, designs, speed_min_mps):
    """Covered designs grouped by identical corner matrices: [(keys, matrices)]."""
    groups: dict = {}
    for d in designs:
        key = (tuple(d.k_m), d.certified_interval, max(d.gain_speed_max_mps, speed_min_mps))
        if key not in groups:
            groups[key] = ([], corner_matrices(vehicle, d, speed_min_mps))
        groups[key][0].append(design_key(d))
    return [(tuple(keys), mats) for keys, mats in groups.values()]


class _CommonProblem:
    """``P >= I``, ``P <= t I``, the decay LMI at every matrix; minimise t (the condition
    number bound). The decay rate is a cvxpy Parameter: compiled once, solved many times."""

    def __init__(self, matrices, margin):
        import cvxpy as cp

        self.matrices = list(matrices)
        self.decay = cp.Parameter(nonneg=True)
        self.p = cp.Variable((4, 4), symmetric=True)
        t = cp.Variable()
        constraints = [self.p >> np.eye(4), self.p << t * np.eye(4)]
        constraints += decay_constraints(self.p, matrices, self.decay, margin)
        self.problem = cp.Problem(cp.Minimize(t), constraints)

    def solve(self, decay):
        """Normalised P (smallest eigenvalue 1) at this decay rate, or None. A solution Clarabel
        calls inaccurate is kept when the matrix itself proves the rate at every matrix
        (generalized eigenvalues): the status is not the certificate, the matrix is."""
        import cvxpy as cp

        from drake_cert.synthesis.gains import solve_sdp_status

        self.decay.value = decay
        status = solve_sdp_status(self.problem)
        if status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or self.p.value is None:
            return None
        p = _normalised(self.p.value)
        if status == cp.OPTIMAL_INACCURATE:
            proved = min(certified_rate(p, m) for m in self.matrices)
            if not (proved > 0.0 and proved >= decay):
                return None
        return p


def _normalised(p: np.ndarray) -> np.ndarray:
    p = 0.5 * (p + p.T)
    return p / float(np.linalg.eigvalsh(p).min())


def _as_rows(p: np.ndarray) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(x) for x in row) for row in p)


def with_loop_certificate(vehicle: VehicleParams, designs: list[ControllerDesign],
                          settings: Settings | SynthesisSettings,
                          certificate: SwitchingCertificate) -> SwitchingCertificate:
    """``certificate`` with the common Lyapunov matrix of the designs' L1 reference loops
    (:func:`drake_cert.synthesis.loop_switching.loop_lyapunov_matrix`) for the adaptation law of
    ``settings`` (a :class:`Settings`; with only its synthesis part, or without a design to
    switch among, the certificate is returned as it is)."""
    from drake_cert.synthesis.loop_switching import loop_lyapunov_matrix

    if not isinstance(settings, Settings) or certificate.method == NONE:
        return certificate
    law = settings.controller.adaptation_law
    found = loop_lyapunov_matrix(vehicle, designs, settings.synthesis.speed_min_mps, law,
                                 settings.synthesis.lmi_margin)
    if found is not None:
        p, rate = found
        return dataclasses.replace(certificate, loop_lyapunov_matrix=_as_rows(p),
                                   loop_decay_rate_per_s=rate, loop_law=law)
    from drake_cert.synthesis.loop_switching import loop_dwell_matrices

    covered = [d for d in designs if d.has_safe_speed]
    per_design = loop_dwell_matrices(vehicle, covered, settings.synthesis.speed_min_mps, law,
                                     settings.synthesis.lmi_margin)
    if per_design is None:
        return dataclasses.replace(certificate, loop_law=law)
    ps, rate, mu = per_design
    rate, mu = _round_down(rate), _round_up(mu)
    return dataclasses.replace(
        certificate, loop_decay_rate_per_s=rate, loop_law=law, loop_jump_factor=mu,
        loop_dwell_time_s=_round_up(math.log(mu) / (2.0 * rate)) if mu > 1.0 else 0.0,
        loop_modes=tuple(SwitchingMode((design_key(d),), _as_rows(p))
                         for d, p in zip(covered, ps, strict=True)))


def common_lyapunov_certificate(vehicle: VehicleParams, designs: list[ControllerDesign],
                                settings: Settings | SynthesisSettings,
                                family: str = TABLE_FAMILY) -> SwitchingCertificate:
    """Switching certificate for the designs with a safe speed among ``designs``.

    Looks for a common P first: bisection (to 1e-3/s, from ``settings.decay_rate`` when P
    exists there, as it does for jointly synthesized gains) for the largest decay lambda in
    ``[0, min over corners of -max Re eig]`` at which the corner LMIs (module docstring, with
    the margin ``settings.lmi_margin`` and ``P >= I``) are feasible, then the best-conditioned P
    at that lambda. If even lambda = 0 is infeasible, falls back to the dwell certificate
    (:func:`dwell_certificate`). Either way the L1 reference loops' matrix is added
    (:func:`with_loop_certificate`) when ``settings`` is a :class:`Settings`. The stored
    decay rate is the one the returned P proves at every corner (generalized eigenvalues),
    rounded down, so the check holds by construction.
    ``settings``: :class:`Settings` or its ``synthesis`` part (decay_rate, lmi_margin,
    speed_min_mps are used). Raises :class:`InfeasibleDesign` if no matrices are found for
    the modes at any trial rate (a solver failure: each mode's own gain LMI holds).
    """
    syn = _synthesis(settings)
    start = time.perf_counter()
    covered = [d for d in designs if d.has_safe_speed]
    keys = tuple(design_key(d) for d in covered)
    if not covered:
        return SwitchingCertificate(family, NONE, (), 0.0, 0.0)
    modes = _modes(vehicle, covered, syn.speed_min_mps)
    matrices = [m for _, mats in modes for m in mats]
    problem = _CommonProblem(matrices, syn.lmi_margin)
    p = problem.solve(0.0)
    if p is None:
        return with_loop_certificate(vehicle, covered, settings, dwell_certificate(
            vehicle, covered, settings, family, modes=modes, start=start))
    upper = min(-float(np.linalg.eigvals(m).real.max()) for m in matrices)
    good, bad = 0.0, upper
    if syn.decay_rate < upper:  # jointly synthesized gains hold there by construction
        trial = problem.solve(syn.decay_rate)
        if trial is not None:
            good, p = syn.decay_rate, trial
    while bad - good > DECAY_BISECTION_TOLERANCE:
        mid = 0.5 * (good + bad)
        trial = problem.solve(mid)
        if trial is None:
            bad = mid
        else:
            good, p = mid, trial
    decay = _round_down(min(certified_rate(p, m) for m in matrices))
    certificate = with_loop_certificate(vehicle, covered, settings, SwitchingCertificate(
        family, COMMON, keys, decay, 0.0, lyapunov_matrix=_as_rows(p),
        condition_number=float(f"{np.linalg.cond(p):.6g}")))
    return dataclasses.replace(certificate, solve_time_s=time.perf_counter() - start)


def dwell_certificate(vehicle: VehicleParams, designs: list[ControllerDesign],
                      settings: Settings | SynthesisSettings, family: str = TABLE_FAMILY,
                      modes=None, start: float | None = None) -> SwitchingCertificate:
    """Average-dwell-time certificate (module docstring) for the designs with a safe speed.

    For each lambda_0 in :data:`DWELL_DECAY_FRACTIONS` x ``settings.decay_rate`` (each mode's
    own gain LMI holds at decay_rate, so each mode has a P there): the joint solve at
    ``mu = 1e4`` gives matrices whose largest jump is a feasible mu, then bisection on mu
    (geometric, to a ratio 1.05) for the joint ``P_m <= mu P_n``; the pair (lambda_0, P_m)
    with the least ``ln(mu) / (2 lambda_0)`` is kept. lambda_0 and mu are then recomputed from
    the matrices (rounded down and up). A single mode gives ``mu = 1``, dwell 0.
    """
    syn = _synthesis(settings)
    start = time.perf_counter() if start is None else start
    covered = [d for d in designs if d.has_safe_speed]
    if not covered:
        return SwitchingCertificate(family, NONE, (), 0.0, 0.0)
    modes = modes if modes is not None else _modes(vehicle, covered, syn.speed_min_mps)
    problem = ModeProblem(modes, syn.lmi_margin)
    best = None
    for fraction in DWELL_DECAY_FRACTIONS:
        decay = fraction * syn.decay_rate
        ps = least_jump_matrices(problem, decay, JUMP_START, JUMP_BISECTION_RATIO)
        if ps is None:
            continue
        dwell = math.log(max(largest_jump(ps), 1.0)) / (2.0 * decay)
        if best is None or dwell < best[0]:
            best = (dwell, ps)
    if best is None:
        raise InfeasibleDesign(f"switching certificate ({family}): no Lyapunov matrix found "
                               "for some design at any trial decay rate (solver failure?)")
    scale = min(float(np.linalg.eigvalsh(p).min()) for p in best[1])  # one scale for all:
    ps = [p / scale for p in best[1]]  # the ratios P_n^-1 P_m are the jump factors
    decay = _round_down(min(certified_rate(p, m) for p, (_, mats) in zip(ps, modes, strict=True)
                            for m in mats))
    mu = _round_up(largest_jump(ps))
    dwell = _round_up(math.log(mu) / (2.0 * decay)) if decay > 0.0 else math.inf
    return SwitchingCertificate(
        family, DWELL, tuple(design_key(d) for d in covered), decay, dwell,
        modes=tuple(SwitchingMode(keys, _as_rows(p)) for p, (keys, _) in
                    zip(ps, modes, strict=True)),
        jump_factor=mu, condition_number=float(f"{max(np.linalg.cond(p) for p in ps):.6g}"),
        solve_time_s=time.perf_counter() - start)


def _round_down(x: float) -> float:
    """x rounded down to 6 significant digits (a claim never above what was proved)."""
    if x <= 0.0 or not math.isfinite(x):
        return float(x)
    scale = 10.0 ** (math.floor(math.log10(x)) - 5)
    return float(f"{math.floor(x / scale) * scale:.6g}")


def _round_up(x: float) -> float:
    if x <= 0.0 or not math.isfinite(x):
        return float(x)
    scale = 10.0 ** (math.floor(math.log10(x)) - 5)
    return float(f"{math.ceil(x / scale) * scale:.6g}")


def switching_families(designs: list[ControllerDesign], conditions: ConditionsTable | None
                       ) -> list[tuple[str, list[ControllerDesign]]]:
    """The sets the run time switches within: per preset of ``conditions`` (already scaled or
    not: only labels are used), the table's designs of its contiguous label ranges present in
    the table; without conditions one family ``"table"`` of all designs."""
    if conditions is None:
        return [(TABLE_FAMILY, list(designs))]
    by_labels = {tuple(d.labels): d for d in designs}
    out = []
    for preset in conditions.presets:
        members = [by_labels[tuple(r)] for r in conditions.contiguous_ranges(preset.name)
                   if tuple(r) in by_labels]
        out.append((preset.name, members))
    return out


def table_switching_certificates(vehicle: VehicleParams, designs: list[ControllerDesign],
                                 settings: Settings | SynthesisSettings,
                                 conditions: ConditionsTable | None = None
                                 ) -> tuple[SwitchingCertificate, ...]:
    """One :func:`common_lyapunov_certificate` per family of :func:`switching_families`."""
    return tuple(common_lyapunov_certificate(vehicle, members, settings, name)
                 for name, members in switching_families(designs, conditions))


# ----------------------------------------------------------------- a switching signal

def chatter_bound(switch_times_s, average_dwell_s: float) -> float:
    """The least ``N_0`` with ``N(t, T) <= N_0 + (T - t) / tau_a`` for every interval of a
    switching signal (the chatter bound of the average-dwell-time argument, module docstring).

    ``switch_times_s``: the switching instants (s), sorted; ``average_dwell_s``: tau_a (s).
    The worst interval starts at a switch and ends at one: ``max_{i <= j} (j - i + 1) -
    (t_j - t_i) / tau_a``; 0 for a signal without switches. With ``tau_a`` above the
    certificate's ``dwell_time_s`` the loop's ``V`` grows at most by ``mu^N_0`` beyond its
    exponential decay.
    """
    times = np.asarray(switch_times_s, dtype=float)
    if times.size == 0:
        return 0.0
    if not average_dwell_s > 0:
        raise ValueError(f"average_dwell_s = {average_dwell_s!r} must be > 0")
    # (j - i + 1) - (t_j - t_i)/tau = (j - t_j/tau) - (i - t_i/tau) + 1: a running minimum
    score = np.arange(times.size) - times / average_dwell_s
    return float(np.max(score - np.minimum.accumulate(score)) + 1.0)


def drive_switching_report(certificate: SwitchingCertificate, switch_times_s) -> dict:
    """What the certificate says about one drive's switching signal (the ``drive --json``
    fields): the method, the certified decay and average dwell, whether the signal met the
    certificate (``switching_certificate_met``: always for "common" and "none"; for "dwell"
    when the chatter bound at ``tau_a = dwell_time_s`` is at most 1, i.e. consecutive
    switches at least ``dwell_time_s`` apart; never when the designs switched and their L1
    loops have no common matrix, ``switching_note`` then says so), for "dwell" the chatter
    bound ``N_0`` at ``tau_a = 2 dwell_time_s`` (then the reference loops decay at
    ``lambda_0 / 2`` at least) with the growth factor ``mu^N_0`` it allows, and the L1
    reference loops' certificate (``loop_switching_decay_per_s``: lambda_z, 0 when there is
    none)."""
    times = list(switch_times_s)
    loop_missing = certificate.method != NONE and not has_loop_certificate(certificate)
    out = {"switching_method": certificate.method,
           "switching_decay_per_s": certificate.decay_rate_per_s,
           "certified_average_dwell_s": certificate.dwell_time_s,
           "loop_switching_decay_per_s": (certificate.loop_decay_rate_per_s
                                          if has_loop_certificate(certificate) else 0.0)}
    if certificate.method == DWELL and certificate.dwell_time_s > 0:
        n0 = chatter_bound(times, 2.0 * certificate.dwell_time_s)
        out.update(chatter_bound_n0=n0, lyapunov_growth_bound=certificate.jump_factor ** n0,
                   switching_certificate_met=chatter_bound(times,
                                                           certificate.dwell_time_s) <= 1.0)
    else:  # common P (or nothing switches): any switching signal is covered
        out.update(chatter_bound_n0=0.0, lyapunov_growth_bound=1.0,
                   switching_certificate_met=True)
    if loop_missing and times:  # the L1 loops that ran switched with no certificate for them
        out["switching_certificate_met"] = False
        out["switching_note"] = (GRADIENT_LOOP_NOTE if certificate.loop_law == "gradient"
                                 else LOOP_MISSING_NOTE)
    elif certificate.loop_modes and certificate.loop_dwell_time_s > 0:
        dwell = certificate.loop_dwell_time_s
        n0 = chatter_bound(times, 2.0 * dwell)
        out.update(loop_certified_average_dwell_s=dwell, loop_chatter_bound_n0=n0,
                   loop_growth_bound=certificate.loop_jump_factor ** n0)
        if chatter_bound(times, dwell) > 1.0:
            out["switching_certificate_met"] = False
            out["switching_note"] = (
                f"the L1 loops share no Lyapunov matrix; their per-design certificate needs an "
                f"average dwell of {dwell:.3g} s and the designs switched faster; they still decay "
                f"at half their rate after a growth of at most {out['loop_growth_bound']:.3g} "
                "(docs/design.md 5.6 (b))")
    return out


GRADIENT_LOOP_NOTE = ("the gradient law's L1 loops have no switching certificate (no common "
                      "Lyapunov matrix exists for its reference rows, docs/design.md 5.6): its "
                      "switching is not certified; the piecewise-constant law's is")
LOOP_MISSING_NOTE = ("the state-feedback loops share a certificate but the L1 loops with their "
                     "filter state share no Lyapunov matrix, so their switching is not certified "
                     "(docs/design.md 5.6)")


# ----------------------------------------------------------------- YAML mapping

def certificate_to_dict(certificate: SwitchingCertificate) -> dict:
    """Plain YAML-able mapping (lists, floats) of one certificate."""
    out = {
        "family": certificate.family,
        "method": certificate.method,
        "designs_covered": list(certificate.designs_covered),
        "decay_rate_per_s": float(certificate.decay_rate_per_s),
        "dwell_time_s": float(certificate.dwell_time_s),
        "jump_factor": float(certificate.jump_factor),
        "condition_number": float(certificate.condition_number),
    }
    if certificate.lyapunov_matrix is not None:
        out["lyapunov_matrix"] = [list(row) for row in certificate.lyapunov_matrix]
    if certificate.loop_lyapunov_matrix is not None:
        out["loop_lyapunov_matrix"] = [list(row) for row in certificate.loop_lyapunov_matrix]
    if has_loop_certificate(certificate):
        out["loop_decay_rate_per_s"] = float(certificate.loop_decay_rate_per_s)
        out["loop_state"] = LOOP_STATE
    if certificate.loop_modes:
        out["loop_modes"] = [{"designs": list(m.designs),
                              "lyapunov_matrix": [list(row) for row in m.lyapunov_matrix]}
                             for m in certificate.loop_modes]
        out["loop_jump_factor"] = float(certificate.loop_jump_factor)
        out["loop_dwell_time_s"] = float(certificate.loop_dwell_time_s)
    if certificate.loop_law:
        out["loop_law"] = certificate.loop_law
    if certificate.modes:
        out["modes"] = [{"designs": list(m.designs),
                         "lyapunov_matrix": [list(row) for row in m.lyapunov_matrix]}
                        for m in certificate.modes]
    return out


_CERT_REQUIRED = ("family", "method", "designs_covered", "decay_rate_per_s", "dwell_time_s")
_CERT_OPTIONAL = ("lyapunov_matrix", "modes", "jump_factor", "condition_number",
                  "loop_lyapunov_matrix", "loop_decay_rate_per_s", "loop_law", "loop_state",
                  "loop_modes", "loop_jump_factor", "loop_dwell_time_s")
OLD_LOOP_MATRIX = ("{where}.loop_lyapunov_matrix was written by an older drake-cert for the "
                   "state [s, u_ad], before a switch carried the L1 estimate over; run "
                   "drake-cert synthesize again")


def certificate_from_dict(data, where: str) -> SwitchingCertificate:
    """Parse one certificate mapping; :class:`ValueError` naming ``where`` and the key."""
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be a mapping")
    loop_keys = ("loop_lyapunov_matrix", "loop_modes", "loop_jump_factor")
    if any(k in data for k in loop_keys) and data.get("loop_state") != LOOP_STATE:
        raise ValueError(OLD_LOOP_MATRIX.format(where=where))
    unknown = sorted(set(data) - set(_CERT_REQUIRED) - set(_CERT_OPTIONAL))
    if unknown:
        raise ValueError(f"{where}: unknown key {unknown[0]!r}")
    for key in _CERT_REQUIRED:
        if key not in data:
            raise ValueError(f"{where}: missing key {key!r}")
    if not isinstance(data["family"], str):
        raise ValueError(f"{where}.family must be a string")
    if data["method"] not in METHODS:
        raise ValueError(f"{where}.method = {data['method']!r} must be one of "
                         f"{', '.join(METHODS)}")
    covered = data["designs_covered"]
    if not isinstance(covered, list) or not all(isinstance(x, str) for x in covered):
        raise ValueError(f"{where}.designs_covered must be a list of design names")
    numbers = {}
    for key, default in (("decay_rate_per_s", None), ("dwell_time_s", None),
                         ("jump_factor", 1.0), ("condition_number", 1.0),
                         ("loop_decay_rate_per_s", 0.0), ("loop_jump_factor", 1.0),
                         ("loop_dwell_time_s", 0.0)):
        value = data.get(key, default)
        if not isinstance(value, (int, float)) or isinstance(value, bool) or math.isnan(value):
            raise ValueError(f"{where}.{key} = {value!r} must be a number")
        numbers[key] = float(value)
    matrix = (_matrix(data["lyapunov_matrix"], f"{where}.lyapunov_matrix")
              if "lyapunov_matrix" in data else None)
    loop = (_matrix(data["loop_lyapunov_matrix"], f"{where}.loop_lyapunov_matrix", 5)
            if "loop_lyapunov_matrix" in data else None)
    loop_law = data.get("loop_law", "")
    if not isinstance(loop_law, str):
        raise ValueError(f"{where}.loop_law must be a string")
    parsed_modes = _modes_from(data.get("modes", []), f"{where}.modes", 4)
    loop_modes = _modes_from(data.get("loop_modes", []), f"{where}.loop_modes", 5)
    return SwitchingCertificate(
        family=data["family"], method=data["method"], designs_covered=tuple(covered),
        decay_rate_per_s=numbers["decay_rate_per_s"], dwell_time_s=numbers["dwell_time_s"],
        lyapunov_matrix=matrix, modes=tuple(parsed_modes), jump_factor=numbers["jump_factor"],
        condition_number=numbers["condition_number"], loop_lyapunov_matrix=loop,
        loop_decay_rate_per_s=numbers["loop_decay_rate_per_s"], loop_law=loop_law,
        loop_modes=loop_modes, loop_jump_factor=numbers["loop_jump_factor"],
        loop_dwell_time_s=numbers["loop_dwell_time_s"])


def _modes_from(modes, where: str, size: int) -> tuple[SwitchingMode, ...]:
    """Parse a list of ``{designs, lyapunov_matrix}`` (size x size); ValueError naming it."""
    if not isinstance(modes, list):
        raise ValueError(f"{where} must be a list")
    parsed = []
    for i, mode in enumerate(modes):
        here = f"{where}[{i}]"
        if not isinstance(mode, dict) or set(mode) != {"designs", "lyapunov_matrix"}:
            raise ValueError(f"{here} must be a mapping with designs and lyapunov_matrix")
        if not isinstance(mode["designs"], list) or not all(isinstance(x, str)
                                                            for x in mode["designs"]):
            raise ValueError(f"{here}.designs must be a list of design names")
        parsed.append(SwitchingMode(tuple(mode["designs"]),
                                    _matrix(mode["lyapunov_matrix"], f"{here}.lyapunov_matrix",
                                            size)))
    return tuple(parsed)


def _matrix(rows, where: str, size: int = 4) -> tuple[tuple[float, ...], ...]:
    ok = (isinstance(rows, list) and len(rows) == size
          and all(isinstance(r, list) and len(r) == size for r in rows)
          and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                  for r in rows for x in r))
    if not ok:
        raise ValueError(f"{where} must be a {size} x {size} list of finite numbers")
    return tuple(tuple(float(x) for x in r) for r in rows)
