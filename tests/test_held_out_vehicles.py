"""Synthesis that keeps the certificates it can hold on held-out vehicles (docs/design.md 5.6).

Claims, on published CommonRoad parameter sets (vehicles/*.yaml):
- the BMW 320i with one tire scale for both axles: Clarabel calls the carla-like certificate's
  common-matrix program inaccurate; the matrix still proves its rate at every corner, so the
  certificate is "common", not a dwell the car does not enforce;
- the Ford Escort: where a fast filter in the envelope leaves a preset's L1 loops with no
  common matrix, the synthesis caps that filter gain (a slower envelope) until they share one,
  says so, and verify rechecks every certificate.
"""

import dataclasses

import pytest
import yaml

from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.io import provenance
from drake_cert.synthesis.design_io import DesignTable, with_switching_certificates
from drake_cert.synthesis.table import DesignCache, synthesize_table
from drake_cert.synthesis.verify import verify_design_table
from drake_cert.data import __file__ as data_init

VEHICLES = __import__("pathlib").Path(data_init).parent / "vehicles"


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
def ford():
    return _table(load_vehicle(VEHICLES / "ford_escort.yaml"))


def test_a_filter_gain_is_capped_where_that_gives_the_l1_loops_a_common_matrix(ford):
    table, cache = ford
    certificates = _certificates(table)
    limit = table.settings.synthesis.filter_gain_max
    capped = {tuple(labels): (k0, k1, v0, v1) for labels, k0, k1, v0, v1 in cache.capped}
    assert capped, "no filter gain was capped"
    for labels, (k0, k1, v0, v1) in capped.items():
        assert k0 > limit >= k1 and v1 < v0  # raised past k_bar before; slower now
        design = next(d for d in table.designs if tuple(d.labels) == labels)
        assert design.filter_gain == k1 and design.speed_mps == v1
    for family in ("robotcar-like", "weather"):
        assert certificates[family].loop_lyapunov_matrix is not None, family
        assert certificates[family].loop_decay_rate_per_s > 0.0
    report = verify_design_table(table, require_switching=True)
    assert report.ok, report


def test_without_the_cap_those_loops_share_no_matrix(ford):
    """The cap is what gives the Ford's robotcar-like loops their matrix: with its envelope's
    filter gain and safe speed as the speed search alone gives them, the program has none."""
    from drake_cert.synthesis.loop_switching import loop_lyapunov_matrix
    from drake_cert.synthesis.switching import switching_families

    table, cache = ford
    before = {tuple(labels): (k0, v0) for labels, k0, _, v0, _ in cache.capped}
    designs = [dataclasses.replace(d, filter_gain=before[tuple(d.labels)][0],
                                   speed_mps=before[tuple(d.labels)][1])
               if tuple(d.labels) in before else d for d in table.designs]
    members = [d for d in dict(switching_families(designs, table.conditions))["robotcar-like"]
               if d.has_safe_speed]
    syn = table.settings.synthesis
    assert any(d.filter_gain > syn.filter_gain_max for d in members)
    assert loop_lyapunov_matrix(table.vehicle, members, syn.speed_min_mps, "piecewise_constant",
                                syn.lmi_margin) is None
