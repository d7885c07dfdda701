"""Certified speed against the measured in-lane limit on the Fiala plant (DESIGN 5.3d).

For every single-label design of the shipped table: the highest speed at which the car stays
in its lane on the default curve (radius ``design_radius_m``, clothoid entry) with the true
stiffness at the label's C_lo and the label's friction, found by bisection on the nonlinear
(Fiala) plant with the law that runs (``drake_cert.systems.closed_loop.simulate``,
plant="nonlinear");
then lane departures at the certified speed for C_lo, the midpoint and C_hi on four roads:
the default curve, an S-curve (left arc, 40 m transition, right arc), a curvature step from
straight to the design radius, and a 40 m curve (with the design synthesized for a 40 m
design radius, the speed compared with that curve's own measured limit).

Run: ``.venv/bin/python benchmarks/grip_limits.py`` (about 3-5 minutes on one core).
"""

import dataclasses
import sys
import time

import numpy as np

from drake_cert import metrics
from drake_cert.config import GRAVITY_MPS2, load_conditions, load_settings, load_vehicle
from drake_cert.synthesis.table import synthesize_design
from drake_cert.systems.closed_loop import EpisodeOptions, simulate
from drake_cert.systems.road import Road

BISECTIONS = 8
STRAIGHT_M = 40.0


def roads(radius_m: float) -> dict[str, Road]:
    """The evaluation roads for a design radius (1/m curvature, left turns first)."""
    k = 1.0 / radius_m
    return {
        "curve": Road.curve(radius_m=radius_m),
        "s_curve": Road((0.0, STRAIGHT_M, 60.0, 120.0, 160.0, 220.0, 240.0),
                        (0.0, 0.0, k, k, -k, -k, 0.0)),
        "step": Road((0.0, STRAIGHT_M, STRAIGHT_M + 1e-3), (0.0, 0.0, k)),
    }


def road_length_m(road: Road) -> float:
    return float(road.knots_m[-1]) + 150.0


def stays_in_lane(vehicle, design, settings, stiffness, mu, speed, road) -> tuple[bool, float]:
    """(in lane for the whole episode, peak |e1| in m) on the Fiala plant."""
    tape = simulate(vehicle=vehicle, design=design, settings=settings,
                    stiffness_n_per_rad=stiffness, friction_mu=mu, speed_mps=speed, road=road,
                    episode=EpisodeOptions(plant="nonlinear",
                                           t_final_s=road_length_m(road) / speed))
    inside = not tape.stopped_early and not metrics.left_lane(tape)
    return inside, metrics.peak_lateral_offset(tape)


def in_lane_limit_mps(vehicle, design, settings, stiffness, mu, road, radius_m) -> float:
    """Highest in-lane speed (m/s): bisection from the certified speed to 1.1 sqrt(mu g R)."""
    lo = design.speed_mps
    hi = 1.1 * np.sqrt(mu * GRAVITY_MPS2 * radius_m)
    if not stays_in_lane(vehicle, design, settings, stiffness, mu, lo, road)[0]:
        return float("nan")  # departs at the certified speed already
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if stays_in_lane(vehicle, design, settings, stiffness, mu, mid,
                                            road)[0] else (lo, mid)
    return lo


def evaluate(vehicle, conditions, settings, radius_m: float, road_names) -> list[dict]:
    syn = dataclasses.replace(settings.synthesis, design_radius_m=radius_m)
    settings = dataclasses.replace(settings, synthesis=syn)
    rows = []
    seen = set()
    for preset in conditions.presets:
        for label in preset.labels:
            if label in seen:
                continue
            seen.add(label)
            cond = conditions.condition(label)
            d = synthesize_design(vehicle, cond.interval, cond.friction_mu, settings, [label])
            all_roads = roads(radius_m)
            limit = in_lane_limit_mps(vehicle, d, settings, cond.stiffness_lo_n_per_rad,
                                      cond.friction_mu, all_roads["curve"], radius_m)
            departures, peak = 0, 0.0
            runs = 0
            lo, hi = cond.interval
            for name in road_names:
                for stiffness in (lo, 0.5 * (lo + hi), hi):
                    inside, p = stays_in_lane(vehicle, d, settings, stiffness, cond.friction_mu,
                                              d.speed_mps, all_roads[name])
                    departures += not inside
                    peak = max(peak, p)
                    runs += 1
            rows.append({"label": label, "radius_m": radius_m, "mu": cond.friction_mu,
                         "certified_mps": d.speed_mps, "limit_mps": limit,
                         "ratio": d.speed_mps / limit, "departures": departures, "runs": runs,
                         "peak_e1_m": peak, "slip_bound": d.tire_slip_bound})
            print(f"{label:12s} R={radius_m:4.0f} mu={cond.friction_mu:4.2f} certified "
                  f"{d.speed_mps:6.2f} limit {limit:6.2f} ratio {d.speed_mps / limit:5.3f} "
                  f"departures {departures}/{runs} peak |e1| {peak:.3f} m "
                  f"(z_b {d.tire_slip_bound:.2f}; roads {','.join(road_names)})", flush=True)
    return rows


def main() -> int:
    vehicle, conditions, settings = load_vehicle(), load_conditions(), load_settings()
    start = time.perf_counter()
    rows = evaluate(vehicle, conditions, settings, settings.synthesis.design_radius_m,
                    ("curve", "s_curve", "step"))
    rows += evaluate(vehicle, conditions, settings, 40.0, ("curve",))
    worst = min(r["ratio"] for r in rows)
    departures = sum(r["departures"] for r in rows)
    print(f"worst certified/limit {worst:.3f}; departures {departures}; "
          f"{time.perf_counter() - start:.0f} s", flush=True)
    return 0 if worst >= 0.9 and departures == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
