"""Closed-loop simulation speed ((i) of the benchmark table in docs/results.md): prints measured
figures, with baselines.

Default configuration: the synthesized heavy-rain design at its safe speed, true stiffness
at the interval's lower end, friction of the label, a 20 s episode on a curve of the design
radius (``Road.episode_curve``), T_s from the shipped settings. For each adaptation law and
plant it prints simulated seconds per wall second of ``Simulator.AdvanceTo`` (diagram build
time listed apart) and the peak |e1|. Baselines measured in the same run, on the same
equations evaluated in Python (the float path of ``drake_cert.systems.l1_law`` /
``drake_cert.systems.plants``):

* gradient law: ``scipy.integrate.solve_ivp`` with a stiff method (LSODA and BDF) on the
  continuous plant + controller equations, over the first ``BASELINE_S`` seconds of the same
  episode (straight, then the clothoid into the curve; Python needs minutes for 20 s), next to
  Drake on the same window;
* piecewise-constant law: a NumPy loop over the samples with the same exact
  discretisation as ``plant="linear_sampled"`` (20 s), and ``solve_ivp`` (LSODA) on the
  nonlinear plant between samples (0.2 s entering the curve; the rate is stated as measured
  on that window).

Run: ``.venv/bin/python benchmarks/bench_closed_loop.py [--quick]`` (``--quick``: 5 s episodes).
"""

import dataclasses
import os
import sys
import time

import numpy as np
from scipy.integrate import solve_ivp

from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.systems import l1_law
from drake_cert.systems.closed_loop import (
    EpisodeOptions,
    TrueCondition,
    build_closed_loop,
    simulate,
)
from drake_cert.systems.plants import (
    PlantInputs,
    body_state_from_error,
    error_state_from_body,
    exact_discretisation,
    linear_error_derivatives,
    single_track_derivatives,
)
from drake_cert.systems.road import Road

BASELINE_S = 4.0  # window of the solve_ivp baselines (s)

def default_case():
    from drake_cert.synthesis.table import synthesize_design

    vehicle, settings, conditions = load_vehicle(), load_settings(), load_conditions()
    labels = ["heavy_rain"]
    design = synthesize_design(vehicle, conditions.hull(labels),
                               conditions.least_friction(labels), settings, labels)
    return vehicle, settings, design, conditions.condition("heavy_rain").friction_mu


def drake_run(vehicle, settings, design, mu, plant, law, t_final, episode_s=None):
    condition = TrueCondition(design.stiffness_lo_n_per_rad, mu, design.speed_mps)
    kw = dict(vehicle=vehicle, design=design, settings=settings,
              episode=EpisodeOptions(plant=plant, law=law, t_final_s=t_final),
              road=Road.episode_curve(radius_m=settings.synthesis.design_radius_m,
                                      length_m=design.speed_mps * (episode_s or t_final)))
    start = time.perf_counter()
    build_closed_loop(condition=condition, **kw)
    build = time.perf_counter() - start
    start = time.perf_counter()
    tape = simulate(**dataclasses.asdict(condition), **kw)
    total = time.perf_counter() - start
    return tape, build, total - build


def python_rhs(vehicle, p, plant, stiffness, mu, road):
    """Plant + gradient-law controller, float path, state [plant state (4), controller (11)]."""
    speed = p.speed_mps
    limit = vehicle.steering_limit_rad

    def rhs(t, y):
        kappa = float(road.curvature_at(speed * t))
        x, z = y[:4], y[4:]
        s = x if plant == "linear" else error_state_from_body(x, speed, kappa).astype(float)
        u = float(np.clip(l1_law.steering_command(p, s, z[10], kappa), -limit, limit))
        if plant == "linear":
            x_dot = linear_error_derivatives(vehicle, s, u, stiffness, speed, kappa)
        else:
            x_dot = single_track_derivatives(vehicle, x,
                                             PlantInputs(u, stiffness, mu, speed, kappa))
        z_dot = l1_law.gradient_controller_derivatives(p, z, s, kappa)
        return np.concatenate([np.asarray(x_dot, float), np.asarray(z_dot, float)])

    return rhs


def scipy_gradient_baseline(vehicle, settings, design, mu, plant, method, t_final, episode_s):
    p = l1_law.l1_parameters(vehicle, design, settings, design.speed_mps)
    road = Road.episode_curve(radius_m=settings.synthesis.design_radius_m,
                              length_m=design.speed_mps * episode_s)
    rhs = python_rhs(vehicle, p, plant, design.stiffness_lo_n_per_rad, mu, road)
    y0 = np.concatenate([np.zeros(4), l1_law.gradient_initial_state(p, np.zeros(4))])
    calls = [0]

    def counted(t, y):
        calls[0] += 1
        return rhs(t, y)

    start = time.perf_counter()
    sol = solve_ivp(counted, (0.0, t_final), y0, method=method, rtol=1e-6, atol=1e-9,
                    max_step=0.01)
    wall = time.perf_counter() - start
    return wall, calls[0], float(np.abs(sol.y[0]).max()), sol.success


def numpy_sampled_baseline(vehicle, settings, design, t_final):
    """Piecewise-constant law on the exactly discretised linear plant, a Python loop."""
    p = l1_law.l1_parameters(vehicle, design, settings, design.speed_mps)
    ad, bd = exact_discretisation(vehicle, design.stiffness_lo_n_per_rad, design.speed_mps,
                                  p.sample_period_s)
    road = Road.episode_curve(radius_m=settings.synthesis.design_radius_m,
                              length_m=design.speed_mps * t_final)
    n = int(round(t_final / p.sample_period_s))
    kappas = road.curvature_at(design.speed_mps * p.sample_period_s * np.arange(n))
    limit = vehicle.steering_limit_rad
    s, s_hat, u_ad, peak = np.zeros(4), np.zeros(4), 0.0, 0.0
    start = time.perf_counter()
    for k in range(n):
        kappa = kappas[k]
        # As in the Drake diagram, plant and controller update at t_k from the same inputs.
        u = min(max(float(l1_law.steering_command(p, s, u_ad, kappa)), -limit), limit)
        s_hat, u_ad = l1_law.piecewise_constant_update(p, s_hat, u_ad, s, kappa)
        s = ad @ s + bd @ np.array([u, kappa])
        peak = max(peak, abs(s[0]))
    return time.perf_counter() - start, peak


def scipy_sampled_nonlinear_baseline(vehicle, settings, design, mu, horizon):
    """Piecewise-constant law with solve_ivp(LSODA) on the Fiala plant between samples."""
    p = l1_law.l1_parameters(vehicle, design, settings, design.speed_mps)
    speed, ts = design.speed_mps, p.sample_period_s
    # The episode's clothoid starts at once, so the measured window has the car turning.
    road = Road.curve(radius_m=settings.synthesis.design_radius_m, straight_m=0.01,
                      transition_m=0.1 * speed * 20, curve_m=0.5 * speed * 20)
    limit = vehicle.steering_limit_rad
    x, s_hat, u_ad = body_state_from_error(np.zeros(4), speed, 0.0), np.zeros(4), 0.0
    n = int(round(horizon / ts))
    start = time.perf_counter()
    for k in range(n):
        kappa = float(road.curvature_at(speed * k * ts))
        s = error_state_from_body(x, speed, kappa).astype(float)
        s_hat, u_ad = l1_law.piecewise_constant_update(p, s_hat, u_ad, s, kappa)

        def rhs(t, xx, u_ad=u_ad, kappa=kappa):
            ss = error_state_from_body(xx, speed, kappa).astype(float)
            u = min(max(float(l1_law.steering_command(p, ss, u_ad, kappa)), -limit), limit)
            return np.asarray(single_track_derivatives(
                vehicle, xx, PlantInputs(u, design.stiffness_lo_n_per_rad, mu, speed, kappa)),
                float)

        x = solve_ivp(rhs, (0.0, ts), x, method="LSODA", rtol=1e-6, atol=1e-9).y[:, -1]
    return time.perf_counter() - start


def main() -> None:
    t_final = 5.0 if "--quick" in sys.argv else 20.0
    vehicle, settings, design, mu = default_case()
    ts = settings.controller.sample_period_s
    print(f"closed loop: design {design.labels} k={design.filter_gain:g}, V={design.speed_mps:.2f} "
          f"m/s, C_true={design.stiffness_lo_n_per_rad:g} N/rad, mu={mu}, T_s={ts:g} s, "
          f"{t_final:g} s episode on a {settings.synthesis.design_radius_m:g} m curve")
    print(f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; Drake rows "
          "are the best of 3 runs")
    print(f"{'law':<19} {'plant':<15} {'sim s / wall s':>14} {'build s':>8} {'peak|e1| m':>11}")
    rows = [("piecewise_constant", "linear_sampled"), ("piecewise_constant", "linear"),
            ("piecewise_constant", "nonlinear"), ("gradient", "linear"), ("gradient", "nonlinear")]
    for law, plant in rows:
        runs = [drake_run(vehicle, settings, design, mu, plant, law, t_final) for _ in range(3)]
        tape, build, wall = min(runs, key=lambda r: r[2])  # best of 3 (shared machine)
        print(f"{law:<19} {plant:<15} {t_final / wall:>14.1f} {build:>8.2f} "
              f"{np.abs(tape.states[:, 0]).max():>11.4f}", flush=True)

    window = BASELINE_S
    print(f"\nbaselines (Python evaluation of the same equations), first {window:g} s:")
    for plant in ("linear", "nonlinear"):
        tape, _, wall = drake_run(vehicle, settings, design, mu, plant, "gradient", window,
                                  episode_s=t_final)
        print(f"gradient           {plant:<15} Drake radau3    {window / wall:>8.2f} sim s / wall s"
              f", peak|e1| {np.abs(tape.states[:, 0]).max():.4f} m", flush=True)
        for method in ("LSODA", "BDF"):
            wall, calls, peak, ok = scipy_gradient_baseline(vehicle, settings, design, mu, plant,
                                                            method, window, t_final)
            print(f"gradient           {plant:<15} solve_ivp {method:<5} {window / wall:>8.2f} "
                  f"sim s / wall s, {calls} rhs calls, peak|e1| {peak:.4f} m"
                  f"{'' if ok else ' (FAILED)'}", flush=True)
    wall, peak = numpy_sampled_baseline(vehicle, settings, design, t_final)
    print(f"piecewise_constant linear_sampled NumPy loop {t_final / wall:>8.2f} sim s / wall s, "
          f"peak|e1| {peak:.4f} m", flush=True)
    horizon = 0.2
    wall = scipy_sampled_nonlinear_baseline(vehicle, settings, design, mu, horizon)
    print(f"piecewise_constant nonlinear solve_ivp LSODA per sample {horizon / wall:>8.3f} "
          f"sim s / wall s (measured on {horizon:g} s entering the curve)", flush=True)


if __name__ == "__main__":
    main()
