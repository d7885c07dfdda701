"""Convergence of the piecewise-constant law in its sample period T_s (DESIGN 4).

For two designs of the shipped table (joint gains, as the car drives them: heavy rain, a narrow
filter, and the weather envelope, whose k w_max T_s is the largest), simulate 20 s on a curve of
the design radius at the design speed with the true stiffness at both interval ends, halving
T_s; print peak |e1| and the final offset, and the change from the previous T_s. The default
T_s is justified when its peak |e1| is within a small fraction of the finest one.

Run: ``.venv/bin/python benchmarks/bench_sample_period.py [--plant nonlinear]``
(default plant: ``linear_sampled``, the exact discretisation; ``nonlinear`` is slower).
"""

import dataclasses
import sys
import time

import numpy as np

from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.systems.closed_loop import EpisodeOptions, simulate
from drake_cert.systems.road import Road

PERIODS = (2e-3, 1e-3, 5e-4, 2.5e-4, 1.25e-4, 6.25e-5)


def main() -> None:
    from drake_cert.synthesis.table import synthesize_label_range

    plant = sys.argv[sys.argv.index("--plant") + 1] if "--plant" in sys.argv else "linear_sampled"
    periods = PERIODS if plant == "linear_sampled" else PERIODS[1:-1]
    vehicle, settings, conditions = load_vehicle(), load_settings(), load_conditions()
    print(f"plant {plant}; default T_s = {settings.controller.sample_period_s:g} s")
    for labels in (["heavy_rain"], ["sunny", "light_rain", "heavy_rain", "snow"]):
        design = synthesize_label_range(vehicle, conditions, labels, settings)
        road = Road.episode_curve(radius_m=settings.synthesis.design_radius_m,
                                  length_m=design.speed_mps * 20.0)
        w_hi = design.certified_interval[1] / design.nominal_stiffness_n_per_rad
        print(f"\n{'+'.join(labels)}: k = {design.filter_gain:g}, largest k w = "
              f"{design.filter_gain * w_hi:.0f} rad/s, V = {design.speed_mps:.2f} m/s")
        print(f"{'C_true':>8} {'T_s s':>9} {'k w T_s':>8} {'peak|e1| m':>11} {'change':>9} "
              f"{'final e1 m':>11} {'wall s':>7}")
        for stiffness in design.interval:
            previous = None
            for ts in periods:
                s = dataclasses.replace(settings, controller=dataclasses.replace(
                    settings.controller, sample_period_s=ts))
                start = time.perf_counter()
                tape = simulate(vehicle=vehicle, design=design, settings=s,
                                stiffness_n_per_rad=stiffness, friction_mu=design.friction_mu_lo,
                                speed_mps=design.speed_mps, road=road,
                                episode=EpisodeOptions(plant=plant, law="piecewise_constant",
                                                       t_final_s=20.0))
                wall = time.perf_counter() - start
                peak = float(np.abs(tape.states[:, 0]).max())
                change = "" if previous is None else f"{(peak - previous) / peak:+.2%}"
                kw = design.filter_gain * stiffness / design.nominal_stiffness_n_per_rad * ts
                print(f"{stiffness:>8.0f} {ts:>9.3g} {kw:>8.3f} {peak:>11.5f} {change:>9} "
                      f"{tape.states[-1, 0]:>11.5f} {wall:>7.2f}", flush=True)
                previous = peak


if __name__ == "__main__":
    main()
