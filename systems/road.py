"""Road description: curvature as a piecewise-linear function of arc length.

``Road(knots_m, curvature_per_m)``: curvature kappa (1/m, > 0 left turn) at arc lengths
(m), linear in between (a clothoid between knots), constant after the last knot. At the
constant speed V of an episode the car is at arc length V t, and the curvature signal is a
``TrajectorySource`` of a first-order-hold ``PiecewisePolynomial`` (evaluated in C++).
"""

import dataclasses

import numpy as np
from pydrake.trajectories import PiecewisePolynomial

from drake_cert.errors import ConfigError

ROAD_KINDS = ("curve", "s_curve", "curvature_step", "straight")  # names for Road.for_episode
STEP_RAMP_M = 0.01  # a curvature step ramps over this arc length (m): knots increase strictly


@dataclasses.dataclass(frozen=True)
class Road:
    """Piecewise-linear curvature profile along the lane centre."""

    knots_m: tuple[float, ...]  # arc lengths (m), strictly increasing, first is 0
    curvature_per_m: tuple[float, ...]  # curvature at each knot (1/m)

    def __post_init__(self):
        k = np.asarray(self.knots_m, float)
        if len(k) < 1 or len(k) != len(self.curvature_per_m):
            raise ConfigError(f"road: {len(self.knots_m)} knots and "
                              f"{len(self.curvature_per_m)} curvatures must match (>= 1)")
        if k[0] != 0.0 or np.any(np.diff(k) <= 0):
            raise ConfigError(f"road: knots_m = {list(self.knots_m)} must start at 0 and "
                              "increase strictly")

    @staticmethod
    def straight() -> "Road":
        """A straight road."""
        return Road((0.0,), (0.0,))

    @staticmethod
    def curve(*, radius_m: float, straight_m: float = 40.0, transition_m: float = 20.0,
              curve_m: float = 150.0, left: bool = True) -> "Road":
        """Straight, clothoid into a circular arc of ``radius_m``, clothoid out, straight."""
        if not radius_m > 0:
            raise ConfigError(f"road: radius_m = {radius_m!r} must be positive")
        kappa = (1.0 if left else -1.0) / radius_m
        a = straight_m
        b = a + transition_m
        c = b + curve_m
        d = c + transition_m
        return Road((0.0, a, b, c, d), (0.0, 0.0, kappa, kappa, 0.0))

    @staticmethod
    def episode_curve(*, radius_m: float, length_m: float, left: bool = True) -> "Road":
        """A curve placed in an episode of ``length_m`` (m): 10% straight, 10% clothoid in,
        50% arc of ``radius_m``, 10% clothoid out, straight to the end."""
        if not length_m > 0:
            raise ConfigError(f"road: length_m = {length_m!r} must be positive")
        return Road.curve(radius_m=radius_m, straight_m=0.1 * length_m,
                          transition_m=0.1 * length_m, curve_m=0.5 * length_m, left=left)

    @staticmethod
    def s_curve(*, radius_m: float, straight_m: float = 40.0, transition_m: float = 20.0,
                curve_m: float = 75.0) -> "Road":
        """Straight, left arc of ``radius_m``, a clothoid of twice ``transition_m`` through
        zero curvature into a right arc of the same radius and length, clothoid out, straight."""
        if not radius_m > 0:
            raise ConfigError(f"road: radius_m = {radius_m!r} must be positive")
        kappa = 1.0 / radius_m
        knots = np.cumsum([0.0, straight_m, transition_m, curve_m, 2 * transition_m, curve_m,
                           transition_m])
        return Road(tuple(float(k) for k in knots), (0.0, 0.0, kappa, kappa, -kappa, -kappa, 0.0))

    @staticmethod
    def curvature_step(*, radius_m: float, straight_m: float = 40.0, left: bool = True
                       ) -> "Road":
        """Straight for ``straight_m``, then a step to the curvature of a ``radius_m`` arc that
        lasts to the end (the step ramps over ``STEP_RAMP_M``; no clothoid)."""
        if not radius_m > 0:
            raise ConfigError(f"road: radius_m = {radius_m!r} must be positive")
        kappa = (1.0 if left else -1.0) / radius_m
        return Road((0.0, straight_m, straight_m + STEP_RAMP_M), (0.0, 0.0, kappa))

    @staticmethod
    def for_episode(kind: str, *, radius_m: float, length_m: float) -> "Road":
        """A road of ``kind`` (one of ``ROAD_KINDS``) laid out over an episode of ``length_m``:
        curve: :meth:`episode_curve`; s_curve: 10% straight, 5% clothoid, 25% left arc, 10%
        clothoid, 25% right arc, 5% clothoid, straight; curvature_step: 10% straight, then the
        arc; straight: no curvature."""
        if kind not in ROAD_KINDS:
            raise ConfigError(f"road kind {kind!r}; expected one of {', '.join(ROAD_KINDS)}")
        if not length_m > 0:
            raise ConfigError(f"road: length_m = {length_m!r} must be positive")
        if kind == "curve":
            return Road.episode_curve(radius_m=radius_m, length_m=length_m)
        if kind == "s_curve":
            return Road.s_curve(radius_m=radius_m, straight_m=0.1 * length_m,
                                transition_m=0.05 * length_m, curve_m=0.25 * length_m)
        if kind == "curvature_step":
            return Road.curvature_step(radius_m=radius_m, straight_m=0.1 * length_m)
        return Road.straight()

    def curvature_at(self, arc_length_m) -> np.ndarray:
        """Curvature (1/m) at the given arc lengths (m)."""
        return np.interp(arc_length_m, self.knots_m, self.curvature_per_m)

    def curvature_trajectory(self, speed_mps: float, t_final_s: float) -> PiecewisePolynomial:
        """kappa(t) = kappa(V t) on [0, t_final] as a first-order-hold PiecewisePolynomial."""
        if not speed_mps > 0:
            raise ConfigError(f"road: speed_mps = {speed_mps!r} must be positive")
        times = [k / speed_mps for k in self.knots_m if k / speed_mps < t_final_s]
        times.append(max(t_final_s, times[-1] + 1e-6))
        values = self.curvature_at(np.asarray(times) * speed_mps)
        return PiecewisePolynomial.FirstOrderHold(np.asarray(times),
                                                  values.reshape(1, -1))

    def curvature_integral(self, arc_length_m) -> np.ndarray:
        """``int_0^s kappa`` (rad) at the given arc lengths (m; kappa(s < 0) = kappa(0), so the
        integral is negative-signed there); exact for the piecewise-linear profile."""
        k = np.asarray(self.knots_m, float)
        c = np.asarray(self.curvature_per_m, float)
        at_knots = np.concatenate([[0.0], np.cumsum(0.5 * (c[1:] + c[:-1]) * np.diff(k))])
        s = np.asarray(arc_length_m, float)
        i = np.clip(np.searchsorted(k, s, side="right") - 1, 0, len(k) - 1)
        ds = s - k[i]
        kappa_s = self.curvature_at(s)
        # from knot i to s the curvature is linear (constant before 0 and after the last knot)
        return at_knots[i] + 0.5 * (c[i] + kappa_s) * ds

    def preview_curvature_at(self, arc_length_m, ahead_m: float, window_m: float) -> np.ndarray:
        """Mean curvature (1/m) over ``[s + ahead_m - window_m, s + ahead_m]`` (m): the road
        preview the curvature feedforward may use (``window_m > 0``; ``ahead_m`` may be less
        than ``window_m``, a window that straddles the car)."""
        s = np.asarray(arc_length_m, float)
        hi = s + ahead_m
        return (self.curvature_integral(hi) - self.curvature_integral(hi - window_m)) / window_m

    def preview_curvature_trajectory(self, speed_mps: float, t_final_s: float, *,
                                     ahead_s: float, window_s: float,
                                     subdivisions: int = 8) -> PiecewisePolynomial:
        """:meth:`preview_curvature_at` as a first-order-hold trajectory of time (s) at speed V,
        ahead and window in seconds of travel. The mean is piecewise quadratic with breaks
        where a window end crosses a knot; each piece is sampled ``subdivisions`` times
        (error <= max |kappa''| (V dt)^2 / 8, zero for piecewise-constant curvature)."""
        if not speed_mps > 0:
            raise ConfigError(f"road: speed_mps = {speed_mps!r} must be positive")
        if not window_s > 0:
            raise ConfigError(f"road: preview window_s = {window_s!r} must be positive")
        knots_t = np.asarray(self.knots_m, float) / speed_mps
        breaks = np.concatenate([[0.0, t_final_s], knots_t - ahead_s,
                                 knots_t - ahead_s + window_s])
        breaks = np.unique(breaks[(breaks >= 0.0) & (breaks <= t_final_s)])
        if len(breaks) < 2:
            breaks = np.array([0.0, max(t_final_s, 1e-6)])
        pieces = [np.linspace(a, b, subdivisions + 1)[:-1] for a, b in zip(breaks[:-1], breaks[1:],
                                                                            strict=True)]
        times = np.unique(np.concatenate(pieces + [breaks[-1:]]))
        times = times[np.concatenate([[True], np.diff(times) > 1e-9])]  # FOH needs distinct
        values = self.preview_curvature_at(times * speed_mps, ahead_s * speed_mps,
                                           window_s * speed_mps)
        return PiecewisePolynomial.FirstOrderHold(times, values.reshape(1, -1))
