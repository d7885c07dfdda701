"""Synthesis that keeps the certificates it can hold on held-out vehicles (docs/design.md 5.6).

Claims, on published CommonRoad parameter sets (vehicles/*.yaml):
- the BMW 320i with one tire scale for both axles: Clarabel calls the carla-like certificate's
  common-matrix program inaccurate; the matrix still proves its rate at every corner, so the
  certificate is "common", not a dwell the car does not enforce;
- the BMW 320i (per-axle file): where a fast filter in the envelope leaves a preset's L1 loops
  with no common matrix, the synthesis caps that filter gain (a slower envelope) until they
  share one (weather); where no cap helps (robotcar-like) each design gets its own loop matrix
  with the average dwell they need, which a drive checks; verify rechecks every certificate.
"""

import dataclasses
import math

import pytest
import yaml

from drake_cert.config import default_path, load_conditions, load_settings, load_vehicle
from drake_cert.io import provenance
from drake_cert.synthesis.design_io import (
    DesignTable,
    load_design_file,
    save_design_table,
    with_switching_certificates,
)
from drake_cert.synthesis.table import DesignCache, synthesize_table
from drake_cert.synthesis.verify import verify_design_table

VEHICLES = default_path("vehicles")


def _table(vehicle):
    conditions, settings = load_conditions(), load_settings()
    cache = DesignCache()
    designs = synthesize_table(vehicle, conditions, settings, cache=cache)
    table = with_switching_certificates(DesignTable(
        designs, vehicle, settings, provenance(seed=None, command=["pytest"]), conditions))
    return table, cache


def _certificates(table):
    return {c.family: c for c in table.switching}


def test_an_inaccurate_solve_whose_matrix_proves_the_rate_keeps_the_common_certificate(
        tmp_path):
    raw = yaml.safe_load((VEHICLES / "bmw_320i.yaml").read_text())
    del raw["rear_tire_stiffness_scale"]  # one scale: both axles' tires alike
    path = tmp_path / "bmw_single_scale.yaml"
    path.write_text(yaml.safe_dump(raw))
    table, _ = _table(load_vehicle(path))
    certificates = _certificates(table)
    assert {c.method for c in certificates.values()} == {"common"}
    assert certificates["carla-like"].decay_rate_per_s >= 0.2
    assert verify_design_table(table, require_switching=True).ok


@pytest.fixture(scope="module")
def bmw():
    return _table(load_vehicle(VEHICLES / "bmw_320i.yaml"))


def test_a_filter_gain_is_capped_where_that_gives_the_l1_loops_a_common_matrix(bmw):
    table, cache = bmw
    certificates = _certificates(table)
    limit = table.settings.synthesis.filter_gain_max
    capped = {tuple(labels): (k0, k1, v0, v1) for labels, k0, k1, v0, v1 in cache.capped}
    assert ("sunny", "light_rain", "heavy_rain", "snow") in capped
    for labels, (k0, k1, v0, v1) in capped.items():
        assert k0 > limit >= k1 and v1 < v0  # raised past k_bar before; slower now
        design = next(d for d in table.designs if tuple(d.labels) == labels)
        assert design.filter_gain == k1 and design.speed_mps == v1
    assert certificates["weather"].loop_lyapunov_matrix is not None
    assert certificates["weather"].loop_decay_rate_per_s > 0.0
    report = verify_design_table(table, require_switching=True)
    assert report.ok, report


def test_without_the_cap_those_loops_share_no_matrix(bmw):
    """The cap is what gives the BMW's weather loops their matrix: with its envelope's filter
    gain and safe speed as the speed search alone gives them, the program has none."""
    from drake_cert.synthesis.loop_switching import loop_lyapunov_matrix
    from drake_cert.synthesis.switching import switching_families

    table, cache = bmw
    before = {tuple(labels): (k0, v0) for labels, k0, _, v0, _ in cache.capped}
    designs = [dataclasses.replace(d, filter_gain=before[tuple(d.labels)][0],
                                   speed_mps=before[tuple(d.labels)][1])
               if tuple(d.labels) in before else d for d in table.designs]
    members = [d for d in dict(switching_families(designs, table.conditions))["weather"]
               if d.has_safe_speed]
    syn = table.settings.synthesis
    assert any(d.filter_gain > syn.filter_gain_max for d in members)
    assert loop_lyapunov_matrix(table.vehicle, members, syn.speed_min_mps, "piecewise_constant",
                                syn.lmi_margin) is None


def test_where_no_cap_helps_each_design_gets_its_own_loop_matrix_and_a_dwell(bmw):
    """robotcar-like on the BMW: no common matrix at any cap (at 0.95 the envelope has no safe
    speed left); one matrix per design proves lambda_0 with jumps of at most mu_z at a switch
    (zeta is continuous there), so an average dwell of ln(mu_z) / (2 lambda_0) keeps the loops
    stable; a drive reports whether its switching kept it."""
    from drake_cert.synthesis import switching

    table, _ = bmw
    c = _certificates(table)["robotcar-like"]
    assert c.loop_lyapunov_matrix is None and len(c.loop_modes) == len(c.designs_covered)
    assert c.loop_decay_rate_per_s > 0.0 and c.loop_jump_factor > 1.0
    assert c.loop_dwell_time_s == pytest.approx(
        math.log(c.loop_jump_factor) / (2 * c.loop_decay_rate_per_s), rel=1e-4)
    slow = switching.drive_switching_report(c, [3.0, 6.5, 10.0])
    assert slow["switching_certificate_met"] is True and "switching_note" not in slow
    fast = switching.drive_switching_report(c, [10.0 + 0.05 * i for i in range(8)])
    assert fast["switching_certificate_met"] is False
    assert "average dwell" in fast["switching_note"] and fast["loop_chatter_bound_n0"] > 1


def test_verify_rejects_an_understated_loop_jump_factor(bmw, tmp_path):
    table, _ = bmw
    path = tmp_path / "bmw.yaml"
    save_design_table(path, table)
    raw = yaml.safe_load(path.read_text())
    robotcar = next(c for c in raw["switching"] if c["family"] == "robotcar-like")
    robotcar["loop_jump_factor"], robotcar["loop_dwell_time_s"] = 1.0, 0.0
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    report = verify_design_table(load_design_file(path), require_switching=True)
    assert not report.ok
    assert any("jump by" in str(f) for f in report.switching_failures), report.switching_failures
