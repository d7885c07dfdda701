"""Safe-speed and filter-gain search (DESIGN 5.3; paper eq. (prog)).

The design speed is the largest V in ``[V_min, V_hi]`` (V_hi: where ``k_m`` is certified) at
which every condition of :mod:`drake_cert.synthesis.conditions` holds for some filter gain
``k <= k_bar``; condition b must hold for every speed in ``[V_min, V]``.

Search: the conditions are evaluated at ``k = k_bar`` on the speed grid (step
``speed_grid_step_mps``; V_hi added as the last point). Condition a is not monotone in V
(1/V terms), so the grid is scanned rather than bisected. The largest grid speed where a, c, d
hold and the grid eigenvalues of b hold on ``[V_min, V]`` is certified for b by corner LMIs
(:func:`certify_reference_stability`); if that fails the next lower grid speed is tried. The
cell above it is then resolved to :data:`SPEED_RESOLUTION_MPS`: by bisection when every
condition that fails at the cell's top is monotone in V (grip: ``V^2 / R``; b: a growing speed
range), else by scanning the cell's points from the top down (the L1 condition); every point is
checked against all four conditions. Assumption (docs/design.md 5.3): no window of safe speeds
opens above a grid point where some condition fails and closes before the next grid point.
Filter gain: ``k_bar = filter_gain_max``, for the piecewise-constant law capped at the
sample-period limit ``k w_max T_s <= 1`` (:func:`sample_period_filter_gain_limit`); where the
L1 condition binds and that limit is higher, the search runs again at the limit and the faster
result is kept. Finally k is lowered to the smallest multiple of ``k_bar / 10`` that still meets
a and b at the chosen speed (more time-delay margin).
None qualifies: speed 0 and the first failing condition at the grid speed where the most
conditions held.
"""

import dataclasses
import functools

import numpy as np

from drake_cert.config import Settings, VehicleParams
from drake_cert.synthesis import conditions as cond
from drake_cert.synthesis.gains import closed_loop_spectral_abscissa

L1_MARGIN_MIN = 1.0e-3  # require ||G|| L <= 1 - 1e-3 (numerical slack for verification)
OFFSET_MARGIN_MIN_M = 1.0e-3
EIG_MARGIN_MIN_PER_S = 1.0e-6
SPEED_RESOLUTION_MPS = 1.0 / 64.0  # safe speeds are resolved to this within the grid cell
FILTER_GAIN_FRACTIONS = np.arange(1, 11) / 10.0
MIN_LMI_SEGMENT_MPS = 0.25
GAIN_CHECK_POINTS = (21, 26)
PC_REFERENCE_GRID = (9, 0.25)  # (C points, speed step m/s) of condition b for the pc law


@dataclasses.dataclass(frozen=True)
class SpeedSearchResult:
    """Design speed (m/s, 0: stop), filter gain k, failed condition ('' if none), margins."""

    speed_mps: float
    filter_gain: float
    failed_condition: str
    margins: dict
    limited_by: str = ""  # ControllerDesign.speed_limited_by


@dataclasses.dataclass
class IntervalEvaluator:
    """Evaluates the interval-only conditions (a, b, c) at given speeds, with caches.

    One evaluator per (interval, k_m): designs that share an interval (labels with equal
    stiffness ranges but different friction) reuse its evaluations.
    """

    vehicle: VehicleParams
    settings: Settings
    interval: tuple[float, float]
    k_m: np.ndarray
    gain_speed_max_mps: float

    def __post_init__(self):
        self._cache: dict = {}

    def _memo(self, key, fn):
        if key not in self._cache:
            self._cache[key] = fn()
        return self._cache[key]

    def l1_margin(self, speed, k) -> float:
        syn = self.settings.synthesis
        return self._memo(("a", speed, k), lambda: cond.l1_condition_margin(
            self.vehicle, self.k_m, self.interval, speed, k, syn.w_grid_points,
            syn.stiffness_grid_points))

    def reference_margin_at(self, speed, k) -> float:
        """Grid eigenvalue margin of b at this single speed (C grid)."""
        syn = self.settings.synthesis
        return self._memo(("b", speed, k), lambda: cond.reference_stability_margin(
            self.vehicle, self.k_m, cond.OperatingBox(self.interval, speed, speed), k,
            (syn.stiffness_grid_points, 2), self.law))

    def offset_margin(self, speed) -> float:
        syn = self.settings.synthesis
        return self._memo(("c", speed), lambda: cond.steady_state_offset_margin(
            self.vehicle, self.k_m, self.interval, speed, syn.design_radius_m,
            self.settings.controller.q_ad_diag, syn.stiffness_grid_points, self.law))

    @property
    def law(self) -> str:
        """The adaptation law conditions b and c are stated for (the law that runs)."""
        return self.settings.controller.adaptation_law

    def reference_certified(self, speed, k) -> bool:
        """Condition b on ``[V_min, speed]`` (cached).

        Gradient law: corner LMIs on speed segments (a certificate). Piecewise-constant law:
        its filter row ``theta + U' r`` is not affine in ``(C, C/V, 1/V)`` (``r`` depends on
        ``A_m(V)``), so the corner argument does not apply; the reference system's eigenvalues
        are checked on a fine grid instead (:data:`PC_REFERENCE_GRID`), not a certificate.
        """
        syn = self.settings.synthesis
        if self.law == cond.GRADIENT:
            return self._memo(("b-lmi", speed, k), lambda: certify_reference_stability(
                self.vehicle, self.k_m, cond.OperatingBox(self.interval, syn.speed_min_mps, speed),
                k, syn.lmi_margin))
        points_c, step_v = PC_REFERENCE_GRID
        points_v = max(2, int(np.ceil((speed - syn.speed_min_mps) / step_v)) + 1)
        return self._memo(("b-grid", speed, k), lambda: cond.reference_stability_margin(
            self.vehicle, self.k_m, cond.OperatingBox(self.interval, syn.speed_min_mps, speed),
            k, (points_c, points_v), self.law) >= EIG_MARGIN_MIN_PER_S)


def certify_reference_stability(vehicle, k_m, box: cond.OperatingBox, k,
                                lmi_margin) -> bool:
    """Condition b for every (C, V) in ``box`` (``interval x [speed_lo, speed_hi]``), certified.

    The corner LMI (:func:`drake_cert.synthesis.conditions.reference_stability_lmi`) is tried on
    the whole speed range, and on failure on its two halves, recursively down to 0.25 m/s segments:
    each frozen (C, V) is then covered by some certified segment.
    """
    @functools.cache
    def ok(lo, hi):
        if cond.reference_stability_lmi(vehicle, k_m, cond.OperatingBox(box.interval, lo, hi),
                                        k, lmi_margin):
            return True
        if hi - lo <= MIN_LMI_SEGMENT_MPS:
            return False
        mid = 0.5 * (lo + hi)
        return ok(lo, mid) and ok(mid, hi)

    return ok(float(box.speed_lo_mps), float(box.speed_mps))


def speed_grid(settings: Settings, speed_hi_mps: float) -> np.ndarray:
    """``V_min, V_min + step, ...`` up to ``speed_hi`` (added when off the grid)."""
    syn = settings.synthesis
    count = int(np.floor((speed_hi_mps - syn.speed_min_mps) / syn.speed_grid_step_mps + 1e-9))
    grid = syn.speed_min_mps + syn.speed_grid_step_mps * np.arange(count + 1)
    if speed_hi_mps - grid[-1] > 1e-9:
        grid = np.append(grid, speed_hi_mps)
    return grid


def failed_conditions(margins: dict) -> list[str]:
    """Names of the conditions whose margins are violated, in the order a, b, c, d, e."""
    failed = []
    if margins["l1_condition"] < L1_MARGIN_MIN:
        failed.append(cond.L1_CONDITION)
    if margins["reference_stability_per_s"] < EIG_MARGIN_MIN_PER_S:
        failed.append(cond.REFERENCE_STABILITY)
    if margins["steady_state_lane_margin_m"] < OFFSET_MARGIN_MIN_M:
        failed.append(cond.STEADY_STATE_OFFSET)
    if min(margins["grip_normalised_slip"], margins["grip_lateral_accel_mps2"]) < 0.0:
        failed.append(cond.GRIP)
    for name in (cond.ROLLOVER, cond.COMFORT):
        if margins.get(f"{name}_lateral_accel_mps2", 0.0) < 0.0:
            failed.append(name)
    return failed


def binding_condition(margins_above: dict) -> str:
    """The condition that stops the speed rising, from the margins just above the design
    speed: of the lateral-acceleration limits that fail there (grip, rollover, comfort), the
    one exceeded most; else the first failing condition; none failing: the speed range."""
    failed = failed_conditions(margins_above)
    accel = {cond.GRIP: margins_above["grip_lateral_accel_mps2"],
             **{name: margins_above[f"{name}_lateral_accel_mps2"]
                for name in (cond.ROLLOVER, cond.COMFORT)
                if f"{name}_lateral_accel_mps2" in margins_above}}
    limits = [name for name in failed if name in accel]
    if cond.GRIP in limits and margins_above["grip_lateral_accel_mps2"] >= 0.0:
        return cond.GRIP  # the slip bound, not the friction fraction, is what binds
    if limits:
        return min(limits, key=accel.get)
    return failed[0] if failed else cond.SPEED_RANGE


def sample_period_filter_gain_limit(settings: Settings, interval) -> float:
    """Largest filter gain k with ``k w_max T_s <= 1`` (1/s): the filter's fastest time constant
    ``1 / (k w_max)`` spans at least one sample period of the piecewise-constant law, the range
    in which the sampled loop was measured to match its continuous analysis (DESIGN 5.3a).
    ``w_max = C_hi / C_hat`` of the certified interval."""
    lo, hi = interval
    return 1.0 / ((hi / (0.5 * (lo + hi))) * settings.controller.sample_period_s)


def search_speed(evaluator: IntervalEvaluator, friction_mu_lo: float,
                 slip_bound: float | None = None,
                 filter_gain_cap: float | None = None) -> SpeedSearchResult:
    """Largest safe speed with its filter gain and margins (module docstring).

    ``slip_bound``: the design's normalised tire slip bound z_b (default
    ``normalised_slip_max``); the evaluator's interval must be the one widened for it.
    The scan runs at ``k_bar = filter_gain_max`` (for the piecewise-constant law at most its
    sample-period limit, :func:`sample_period_filter_gain_limit`); where the L1 condition binds
    and that law runs, it runs again at the sample-period limit when that is higher, and the
    faster of the two results is returned. ``filter_gain_cap`` (1/s): no filter gain above it,
    the sample-period raise included (the table's L1 loops, :mod:`drake_cert.synthesis.table`).
    """
    settings = evaluator.settings
    k_bar = settings.synthesis.filter_gain_max
    limit = sample_period_filter_gain_limit(settings, evaluator.interval)
    if filter_gain_cap is not None:
        k_bar, limit = min(k_bar, filter_gain_cap), min(limit, filter_gain_cap)
    sampled = evaluator.law == cond.PIECEWISE_CONSTANT
    if sampled:
        k_bar = min(k_bar, limit)
    result = _search_at(evaluator, friction_mu_lo, slip_bound, k_bar)
    l1_binds = cond.L1_CONDITION in (result.failed_condition, result.limited_by)
    if sampled and l1_binds and limit > k_bar:
        wider = _search_at(evaluator, friction_mu_lo, slip_bound, float(limit))
        if wider.speed_mps > result.speed_mps:
            return wider
    return result


def _search_at(evaluator: IntervalEvaluator, friction_mu_lo: float, slip_bound: float | None,
               k_bar: float) -> SpeedSearchResult:
    vehicle, settings = evaluator.vehicle, evaluator.settings
    syn = settings.synthesis
    grid = speed_grid(settings, evaluator.gain_speed_max_mps)
    decay_margin = -closed_loop_spectral_abscissa(
        vehicle, evaluator.k_m, evaluator.interval, syn.speed_min_mps,
        evaluator.gain_speed_max_mps, GAIN_CHECK_POINTS) - syn.decay_rate

    def margins_at(speed, k, ref_floor=np.inf):
        slip, accel = cond.grip_margins(
            friction_mu_lo, speed, syn.design_radius_m,
            syn.normalised_slip_max if slip_bound is None else slip_bound,
            syn.lateral_accel_fraction)
        return {
            "gain_decay_per_s": decay_margin,
            "l1_condition": evaluator.l1_margin(speed, k),
            "reference_stability_per_s": min(ref_floor, evaluator.reference_margin_at(speed, k)),
            "steady_state_lane_margin_m": evaluator.offset_margin(speed),
            "grip_normalised_slip": slip,
            "grip_lateral_accel_mps2": accel,
            **cond.vehicle_limit_margins(vehicle, settings, speed),
        }

    # grid scan at k_bar; b's grid margin over [V_min, V] is the running minimum
    scan, floor = [], np.inf
    for v in grid:
        m = margins_at(v, k_bar, floor)
        floor = m["reference_stability_per_s"]
        scan.append(m)

    chosen = None
    for i in range(len(grid) - 1, -1, -1):
        if not failed_conditions(scan[i]) and evaluator.reference_certified(grid[i], k_bar):
            chosen = i
            break
    if chosen is None:
        held = [len(cond.CONDITIONS) - len(failed_conditions(m)) for m in scan]
        best = int(np.argmax(held))  # first (lowest) speed among those with the most conditions
        failed = failed_conditions(scan[best]) or [cond.REFERENCE_STABILITY]
        return SpeedSearchResult(0.0, float(k_bar), failed[0], scan[best])

    speed, limited_by = float(grid[chosen]), cond.SPEED_RANGE
    if chosen + 1 < len(grid):
        speed, limited_by = refine_cell(evaluator, margins_at, scan, grid, chosen, k_bar)
    result = lowest_filter_gain(evaluator, margins_at, grid, speed, k_bar)
    return dataclasses.replace(result, limited_by=limited_by)


def refine_cell(evaluator: IntervalEvaluator, margins_at, scan, grid, chosen: int,
                k_bar: float) -> tuple[float, str]:
    """The highest point of the grid cell above ``grid[chosen]``, on a lattice of step at most
    :data:`SPEED_RESOLUTION_MPS`, that meets every condition (b certified by its LMI).

    When what fails at the cell's top is monotone in V (grip ``V^2 / R``, rollover, comfort, b
    on a growing speed range) the lattice is bisected; otherwise (the L1 condition, the
    offset) it is scanned from the top down. Returns that speed (m/s) and the condition that
    failed at the lattice point just above it (:func:`binding_condition`; a point whose
    margins all hold failed the certificate of b).
    """
    lo, hi = float(grid[chosen]), float(grid[chosen + 1])
    floor = scan[chosen]["reference_stability_per_s"]
    points = max(1, int(np.ceil((hi - lo) / SPEED_RESOLUTION_MPS - 1e-9)))
    step = (hi - lo) / points

    def check(i: int) -> tuple[bool, str]:
        m = margins_at(lo + i * step, k_bar, floor)
        failed = failed_conditions(m)
        if failed:
            return False, binding_condition(m)
        if not evaluator.reference_certified(lo + i * step, k_bar):
            return False, cond.REFERENCE_STABILITY
        return True, ""

    binding = binding_condition(scan[chosen + 1])
    if binding == cond.SPEED_RANGE:  # every margin held at the top: b's certificate failed
        binding = cond.REFERENCE_STABILITY
    monotone = {cond.GRIP, cond.ROLLOVER, cond.COMFORT, cond.REFERENCE_STABILITY}
    top_failures = set(failed_conditions(scan[chosen + 1])) or {cond.REFERENCE_STABILITY}
    if top_failures <= monotone:
        good, bad = 0, points  # lattice indices: good passes, bad fails
        while bad - good > 1:
            mid = (good + bad) // 2
            ok, why = check(mid)
            if ok:
                good = mid
            else:
                bad, binding = mid, why
        return lo + good * step, binding
    for i in range(points - 1, 0, -1):
        ok, why = check(i)
        if ok:
            return lo + i * step, binding
        binding = why
    return lo, binding


def lowest_filter_gain(evaluator: IntervalEvaluator, margins_at, grid, speed: float,
                       k_bar: float) -> SpeedSearchResult:
    """The smallest multiple of ``k_bar / 10`` meeting every condition at ``speed``."""
    for frac in FILTER_GAIN_FRACTIONS:
        k = float(frac * k_bar)
        grid_below = [v for v in grid if v <= speed] + [speed]
        floor = min(evaluator.reference_margin_at(v, k) for v in grid_below)
        m = margins_at(speed, k, floor)
        if not failed_conditions(m) and evaluator.reference_certified(speed, k):
            return SpeedSearchResult(speed, k, "", m)
    raise AssertionError("k_bar qualified during the scan but not in the final check")
