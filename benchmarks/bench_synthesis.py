"""Synthesis benchmarks ((ii) and (iii) of the benchmark table in docs/results.md): prints
measured figures, with baselines from the same run.

(ii)  wall time to synthesize the default design table (target < 30 s on 2 cores), with the
      joint gains (the default) and the separate ones (the baseline), their switching
      certificates' time and method, and the safe speeds that differ;
(iii) ``l1_norm`` evaluations per second on the 5-state system G = H (1 - C_w) of the L1
      condition (target <= 1 ms each), the shared-pole batch over w that the speed search
      uses, and two baselines computed in this run on the same
      system: a naive ``scipy.integrate.quad`` of |c_i' expm(A t) b| per output, and the
      graded-grid trapezoid quadrature of ``drake_cert.synthesis.verify`` (the independent checker).

Run: ``.venv/bin/python benchmarks/bench_synthesis.py``.
"""

import os
import time

import numpy as np
import scipy.integrate
import scipy.linalg

from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.synthesis import l1_norm
from drake_cert.synthesis.conditions import filtered_plant_realisation, high_passed_plant_l1_norms
from drake_cert.synthesis.switching import design_key, table_switching_certificates
from drake_cert.synthesis.table import synthesize_table
from drake_cert.synthesis.uncertainty import nominal_model
from drake_cert.synthesis.verify import l1_norm_by_quadrature


def naive_quad_l1_norm(a, b, c) -> float:
    """Baseline: adaptive quadrature of |c_i' expm(A t) b| on [0, 36 / decay], each output."""
    t_end = 36.0 / -np.linalg.eigvals(a).real.max()
    best = 0.0
    for row in c:
        value, _ = scipy.integrate.quad(lambda t, row=row: abs(row @ scipy.linalg.expm(a * t) @ b),
                                        0.0, t_end, limit=2000, epsrel=1e-6)
        best = max(best, value)
    return best


def bench_table() -> None:
    """(ii) for the joint gains (the default) beside the separate ones (the baseline), with
    what each costs in switching certificates and what it gives in speed (DESIGN 5.6)."""
    vehicle, conditions, settings = load_vehicle(), load_conditions(), load_settings()
    tables = {}
    for gains in ("joint", "separate"):
        times = []
        for _ in range(2):
            start = time.perf_counter()
            designs = synthesize_table(vehicle, conditions, settings, gains=gains)
            times.append(time.perf_counter() - start)
        start = time.perf_counter()
        certificates = table_switching_certificates(vehicle, designs, settings, conditions)
        t_cert = time.perf_counter() - start
        tables[gains] = designs
        methods = ", ".join(f"{c.family} {c.method}" for c in certificates)
        print(f"(ii) default design table, {gains} gains: {len(designs)} designs in "
              f"{min(times):.2f} s (best of 2; runs {', '.join(f'{t:.2f}' for t in times)} s; "
              f"target < 30 s); switching certificates {t_cert:.2f} s ({methods})")
    faster = [(design_key(a), b.speed_mps, a.speed_mps)
              for a, b in zip(tables["joint"], tables["separate"], strict=True)
              if abs(a.speed_mps - b.speed_mps) > 0.02]
    print("     safe speeds that differ (separate -> joint, m/s): "
          + (", ".join(f"{k} {s:.2f} -> {j:.2f}" for k, s, j in faster) or "none"))
    print(f"     os.cpu_count() = {os.cpu_count()}, load average {os.getloadavg()[0]:.2f}")


def bench_l1_norm() -> None:
    vehicle = load_vehicle()
    k_m = [0.0101, 0.0031, 0.215, 0.0172]  # corner-LMI gain of the snow interval
    nom = nominal_model(vehicle, 30e3, 8.0, k_m)
    a, b, c = filtered_plant_realisation(nom, 0.8, 500.0)
    l1_norm(a, b, c)  # warm-up
    reps = 2000
    start = time.perf_counter()
    for _ in range(reps):
        fast = l1_norm(a, b, c)
    t_fast = (time.perf_counter() - start) / reps

    w_values = np.linspace(20e3, 40e3, 5) / 30e3
    reps_b = 400
    start = time.perf_counter()
    for _ in range(reps_b):
        high_passed_plant_l1_norms(nom, w_values, 500.0)
    t_batch = (time.perf_counter() - start) / (reps_b * len(w_values))

    reps_q = 20
    start = time.perf_counter()
    for _ in range(reps_q):
        quad_verify = l1_norm_by_quadrature(a, b.ravel(), c)
    t_verify = (time.perf_counter() - start) / reps_q

    start = time.perf_counter()
    naive = naive_quad_l1_norm(a, b.ravel(), c)
    t_naive = time.perf_counter() - start

    print(f"(iii) l1_norm, 5-state G (V = 8 m/s, w = 0.8, k = 500): {t_fast * 1e3:.3f} ms per "
          f"evaluation = {1.0 / t_fast:,.0f} evaluations/s (target <= 1 ms); value {fast:.6f}")
    print(f"      shared-pole batch over 5 w (what the speed search calls): {t_batch * 1e3:.3f} ms "
          f"per evaluation = {1.0 / t_batch:,.0f} evaluations/s")
    print(f"      baseline scipy.integrate.quad + expm: {t_naive * 1e3:.1f} ms per evaluation "
          f"({t_naive / t_fast:,.0f}x slower); value {naive:.6f}, rel. diff "
          f"{abs(naive - fast) / fast:.1e}")
    print(f"      verify's graded trapezoid quadrature: {t_verify * 1e3:.2f} ms per evaluation "
          f"({t_verify / t_fast:,.1f}x slower); value {quad_verify:.6f}, rel. diff "
          f"{abs(quad_verify - fast) / fast:.1e}")


if __name__ == "__main__":
    bench_table()
    bench_l1_norm()
