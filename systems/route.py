"""A driving route: segments of given length, curvature and road condition (DESIGN 6).

Each segment draws its true cornering stiffness per tire uniformly in its condition's
interval ``[C_lo, C_hi]`` (N/rad; deterministic by seed, stream ``route`` (segment) of the
seed, :mod:`drake_cert.certification.seeds`)
and takes its condition's friction coefficient mu from the conditions table. Curvature
(1/m, > 0 left turn) is constant on a segment and ramps linearly over ``transition_m``
centred at each boundary where it changes (a clothoid); the ramp is shortened to half of
the shorter neighbouring segment when a segment is short. Positions beyond the end belong
to the last segment; positions before 0 to the first.

:class:`RouteSource` is the Drake system that reads the route at the car's arc length.
"""


import bisect
import dataclasses
import math
from collections.abc import Sequence

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from drake_cert.certification.seeds import Purpose, child_rng
from drake_cert.config import ConditionsTable
from drake_cert.errors import ConfigError

POSE_STEP_M = 0.5  # arc-length step of the centre-line integration (m)


@dataclasses.dataclass
class SegmentSpec:
    """One segment as written in a scenario (YAML). Not frozen: ``yaml_load_typed`` assigns
    fields one by one."""

    length_m: float = 0.0  # segment length along the lane centre (m), > 0
    curvature_per_m: float = 0.0  # curvature (1/m), > 0 left turn; |kappa| <= 1/50 m
    condition: str = ""  # road-condition label of the scenario's perception preset


@dataclasses.dataclass(frozen=True)
class RouteSegment:
    """A built segment with its true (drawn) stiffness and friction."""

    start_m: float  # arc length of the segment's start (m)
    length_m: float  # length (m)
    curvature_per_m: float  # curvature (1/m), > 0 left
    condition: str  # road-condition label
    label_index: int  # index of the condition in the preset's label order (grippiest first)
    stiffness_n_per_rad: float  # true cornering stiffness per tire (N/rad), in the interval
    friction_mu: float  # the condition's friction coefficient

    @property
    def end_m(self) -> float:
        return self.start_m + self.length_m


class Route:
    """Segments end to end, with vectorised look-ups by arc length ``s`` (m)."""

    def __init__(self, segments: Sequence[RouteSegment], transition_m: float = 10.0):
        if not segments:
            raise ConfigError("route: at least one segment is required")
        if not (math.isfinite(transition_m) and transition_m > 0):
            raise ConfigError(f"route: transition_m = {transition_m!r} must be positive")
        self.segments: tuple[RouteSegment, ...] = tuple(segments)
        self.transition_m = float(transition_m)
        self._starts = [seg.start_m for seg in self.segments]
        self._starts_array = np.asarray(self._starts, dtype=float)
        self._stiffness = np.array([seg.stiffness_n_per_rad for seg in self.segments])
        self._friction = np.array([seg.friction_mu for seg in self.segments])
        self._knots, self._kappa = self._curvature_knots()
        self._integral_at_knots = np.concatenate(  # int_0^knot kappa (rad), trapezoids exact
            [[0.0], np.cumsum(0.5 * (self._kappa[1:] + self._kappa[:-1]) * np.diff(self._knots))])
        self._knots_list, self._kappa_list = self._knots.tolist(), self._kappa.tolist()
        self._integral_list = self._integral_at_knots.tolist()

    @staticmethod
    def build(specs: Sequence[SegmentSpec], conditions: ConditionsTable, preset: str,
              seed: int, transition_m: float = 10.0) -> "Route":
        """Lay the segments end to end and draw each one's true stiffness.

        Raises :class:`ConfigError` for an empty route, a non-positive length, a curvature
        radius below 50 m, or a condition that is not a label of ``preset``.
        """
        labels = list(conditions.preset(preset).labels)
        if not specs:
            raise ConfigError("route: at least one segment is required")
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(f"route: seed = {seed!r} must be a non-negative integer")
        segments, start = [], 0.0
        for i, spec in enumerate(specs):
            where = f"route[{i}]"
            if not (math.isfinite(spec.length_m) and spec.length_m > 0):
                raise ConfigError(f"{where}.length_m = {spec.length_m!r} must be positive")
            if not (math.isfinite(spec.curvature_per_m) and abs(spec.curvature_per_m) <= 0.02):
                raise ConfigError(f"{where}.curvature_per_m = {spec.curvature_per_m!r}: the "
                                  "radius must be at least 50 m (|kappa| <= 0.02 1/m)")
            if spec.condition not in labels:
                raise ConfigError(f"{where}.condition = {spec.condition!r} is not a label of "
                                  f"preset {preset!r} ({', '.join(labels)})")
            cond = conditions.condition(spec.condition)
            lo, hi = cond.interval
            u = child_rng(seed, Purpose.ROUTE, i).uniform()
            segments.append(RouteSegment(
                start_m=start, length_m=float(spec.length_m),
                curvature_per_m=float(spec.curvature_per_m), condition=spec.condition,
                label_index=labels.index(spec.condition),
                stiffness_n_per_rad=float(lo + (hi - lo) * u), friction_mu=cond.friction_mu))
            start += float(spec.length_m)
        return Route(segments, transition_m)

    @property
    def total_length_m(self) -> float:
        return self.segments[-1].end_m

    def _curvature_knots(self) -> tuple[np.ndarray, np.ndarray]:
        """Knots of the piecewise-linear curvature: constant on segments, ramps at changes."""
        segs = self.segments
        knots, kappa = [0.0], [segs[0].curvature_per_m]
        for prev, nxt in zip(segs, segs[1:], strict=False):
            if nxt.curvature_per_m == prev.curvature_per_m:
                continue
            half = min(0.5 * self.transition_m, 0.5 * prev.length_m, 0.5 * nxt.length_m)
            knots += [nxt.start_m - half, nxt.start_m + half]
            kappa += [prev.curvature_per_m, nxt.curvature_per_m]
        return np.asarray(knots), np.asarray(kappa)

    # ------------------------------------------------------------------ look-ups
    def segment_index_at(self, s_m) -> np.ndarray:
        """Index of the segment holding each arc length (int array, shape of ``s_m``)."""
        idx = np.searchsorted(self._starts_array, np.asarray(s_m, dtype=float), side="right") - 1
        return np.clip(idx, 0, len(self.segments) - 1)

    def index_of(self, s_m: float) -> int:
        """Index of the segment holding one arc length (scalar, no numpy overhead)."""
        i = bisect.bisect_right(self._starts, float(s_m)) - 1
        return min(max(i, 0), len(self.segments) - 1)

    def segment_at(self, s_m: float) -> RouteSegment:
        """The segment holding one arc length (scalar)."""
        return self.segments[self.index_of(s_m)]

    def curvature_at(self, s_m) -> np.ndarray:
        """Curvature (1/m) at the arc lengths, with the clothoid ramps at boundaries."""
        return np.interp(s_m, self._knots, self._kappa)

    def curvature_integral(self, s_m) -> np.ndarray:
        """``int_0^s kappa`` (rad) at the arc lengths (m), exact for the piecewise-linear
        curvature (constant before 0 and past the last ramp, so negative-signed for s < 0)."""
        k, c = self._knots, self._kappa
        s = np.asarray(s_m, dtype=float)
        i = np.clip(np.searchsorted(k, s, side="right") - 1, 0, len(k) - 1)
        # from knot i to s the curvature is linear (constant before 0 and after the last knot)
        return self._integral_at_knots[i] + 0.5 * (c[i] + self.curvature_at(s)) * (s - k[i])

    def preview_curvature_at(self, s_m, ahead_m, window_m) -> np.ndarray:
        """Mean curvature (1/m) over ``[s + ahead_m - window_m, s + ahead_m]`` (m), from
        :meth:`curvature_integral` (exact on segments and clothoid ramps; as
        ``drake_cert.systems.road.Road.preview_curvature_at``). ``ahead_m``, ``window_m`` >= 0 may
        be arrays (they scale with the speed); where ``window_m`` is 0 (the car at rest) the
        mean is its limit, the curvature at ``s + ahead_m``."""
        if _scalars(s_m, ahead_m, window_m):  # one point: no numpy
            hi, w = float(s_m) + float(ahead_m), float(window_m)
            if w <= 1e-9:
                return np.float64(self._integral_and_curvature(hi)[1])
            return np.float64((self._integral_and_curvature(hi)[0]
                               - self._integral_and_curvature(hi - w)[0]) / w)
        s = np.asarray(s_m, dtype=float)
        hi = s + np.asarray(ahead_m, dtype=float)
        w = np.asarray(window_m, dtype=float)
        wide = w > 1e-9
        safe = np.where(wide, w, 1.0)
        mean = (self.curvature_integral(hi) - self.curvature_integral(hi - w)) / safe
        return np.where(wide, mean, self.curvature_at(hi))

    def _integral_and_curvature(self, s: float) -> tuple[float, float]:
        """``(int_0^s kappa, kappa(s))`` at one arc length, in plain Python (the per-step path
        of :class:`RouteSource`; :meth:`curvature_integral` and :meth:`curvature_at` agree)."""
        k, c = self._knots_list, self._kappa_list
        i = min(max(bisect.bisect_right(k, s) - 1, 0), len(k) - 1)
        if s < k[0] or i == len(k) - 1:  # constant before the first and after the last knot
            kappa = c[i]
        else:  # k[i] <= s < k[i + 1]
            kappa = c[i] + (c[i + 1] - c[i]) * (s - k[i]) / (k[i + 1] - k[i])
        return self._integral_list[i] + 0.5 * (c[i] + kappa) * (s - k[i]), kappa

    def stiffness_at(self, s_m) -> np.ndarray:
        """True cornering stiffness per tire (N/rad) of the segment at each arc length."""
        return self._stiffness[self.segment_index_at(s_m)]

    def friction_at(self, s_m) -> np.ndarray:
        """Friction coefficient of the segment at each arc length."""
        return self._friction[self.segment_index_at(s_m)]

    def pose_at(self, s_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centre-line pose ``(x_m, y_m, heading_rad)`` at the arc lengths (start at the
        origin heading +x): ``heading' = kappa(s)``, ``x' = cos(heading)``,
        ``y' = sin(heading)``, integrated by the trapezoid rule on a 0.5 m grid."""
        s = np.asarray(s_m, dtype=float)
        end = max(self.total_length_m, float(np.max(s, initial=0.0)))
        grid = np.linspace(0.0, end, max(2, int(math.ceil(end / POSE_STEP_M)) + 1))
        ds = np.diff(grid)
        k = self.curvature_at(grid)
        heading = np.concatenate(([0.0], np.cumsum(0.5 * (k[1:] + k[:-1]) * ds)))
        c, sn = np.cos(heading), np.sin(heading)
        x = np.concatenate(([0.0], np.cumsum(0.5 * (c[1:] + c[:-1]) * ds)))
        y = np.concatenate(([0.0], np.cumsum(0.5 * (sn[1:] + sn[:-1]) * ds)))
        sc = np.clip(s, 0.0, end)
        return np.interp(sc, grid, x), np.interp(sc, grid, y), np.interp(sc, grid, heading)


def _scalars(*values) -> bool:
    """Every value a single number (the per-step path), checked without numpy's dispatch."""
    return all(isinstance(v, float | int) or np.ndim(v) == 0 for v in values)


class RouteSource(LeafSystem):
    """The road under the car: reads the route at the car's arc length.

    Input ``arc_length_m`` (1, m). Outputs (direct feedthrough): ``curvature_per_m`` (1, 1/m,
    with the clothoid ramps), ``stiffness_n_per_rad`` (1, N/rad, the true cornering stiffness
    per tire of the segment the car is on, for the plant), ``friction_mu`` (1) and
    ``segment_index`` (1) of that segment.

    Road preview (``preview_window_s > 0``; settings ``controller.preview_ahead_s``,
    ``preview_window_s``): a second input ``speed_mps`` (1, m/s, the car's current speed V)
    and the output ``curvature_preview_per_m`` (1, 1/m), the mean curvature over
    ``[s + V ahead_s - V window_s, s + V ahead_s]`` (:meth:`Route.preview_curvature_at`): the
    road the car covers in the window at its current speed, for the curvature feedforward
    (:mod:`drake_cert.systems.l1_law`, "Road preview"). At V = 0 it is the curvature under the car.
    """

    def __init__(self, route: Route, *, preview_ahead_s: float = 0.0,
                 preview_window_s: float = 0.0):
        super().__init__()
        for name, value in (("preview_ahead_s", preview_ahead_s),
                            ("preview_window_s", preview_window_s)):
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"route source: {name} = {value!r} must be a finite number "
                                  ">= 0 (s)")
        self.route = route
        self.preview_ahead_s = float(preview_ahead_s)
        self.preview_window_s = float(preview_window_s)
        self._s = self.DeclareVectorInputPort("arc_length_m", 1)
        self.DeclareVectorOutputPort("curvature_per_m", 1, self._calc_curvature)
        self.DeclareVectorOutputPort("stiffness_n_per_rad", 1, self._calc_stiffness)
        self.DeclareVectorOutputPort("friction_mu", 1, self._calc_friction)
        self.DeclareVectorOutputPort("segment_index", 1, self._calc_index)
        if self.preview_window_s > 0:
            self._speed = self.DeclareVectorInputPort("speed_mps", 1)
            self.DeclareVectorOutputPort("curvature_preview_per_m", 1, self._calc_preview)

    def _arc(self, context) -> float:
        return float(self._s.Eval(context)[0])

    def _calc_preview(self, context, output: BasicVector) -> None:
        v = max(float(self._speed.Eval(context)[0]), 0.0)
        output.SetAtIndex(0, float(self.route.preview_curvature_at(
            self._arc(context), v * self.preview_ahead_s, v * self.preview_window_s)))

    def _calc_curvature(self, context, output: BasicVector) -> None:
        output.SetAtIndex(0, float(self.route.curvature_at(self._arc(context))))

    def _calc_stiffness(self, context, output: BasicVector) -> None:
        output.SetAtIndex(0, self.route.segment_at(self._arc(context)).stiffness_n_per_rad)

    def _calc_friction(self, context, output: BasicVector) -> None:
        output.SetAtIndex(0, self.route.segment_at(self._arc(context)).friction_mu)

    def _calc_index(self, context, output: BasicVector) -> None:
        output.SetAtIndex(0, float(self.route.index_of(self._arc(context))))
