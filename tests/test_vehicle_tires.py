"""A vehicle file may scale the conditions table's per-tire stiffness (DESIGN 2.1)."""

import dataclasses

import pytest

from drake_cert.config import default_path, load_conditions, load_settings, load_vehicle
from drake_cert.io import provenance
from synthesis.design_io import DesignTable
from synthesis.table import synthesize_table
from synthesis.verify import verify_design_table

CONDITIONS = load_conditions()
SETTINGS = load_settings()
SUV = load_vehicle(default_path("vehicles/suv.yaml"))


def _heavy_rain_only(conditions):
    preset = dataclasses.replace(conditions.presets[0], labels=["heavy_rain"])
    return dataclasses.replace(conditions, presets=[preset])


def test_the_shipped_car_keeps_the_table_and_the_suv_scales_it():
    assert load_vehicle().tire_stiffness_scale == 1.0  # the key is optional; default 1
    assert SUV.tire_stiffness_scale > 1.0
    assert SUV.mass_kg > load_vehicle().mass_kg


def test_designs_are_synthesized_and_verified_on_the_scaled_intervals():
    conditions = _heavy_rain_only(CONDITIONS)
    (design,) = synthesize_table(SUV, conditions, SETTINGS)
    lo, hi = CONDITIONS.condition("heavy_rain").interval
    scale = SUV.tire_stiffness_scale
    assert design.interval == pytest.approx((scale * lo, scale * hi))
    assert design.has_safe_speed
    table = DesignTable([design], SUV, SETTINGS, provenance(seed=None, command=["pytest"]),
                        conditions)
    assert verify_design_table(table).ok
    # The same design checked as if the vehicle had the table's tires: interval != hull.
    unscaled = DesignTable([design], dataclasses.replace(SUV, tire_stiffness_scale=1.0),
                           SETTINGS, provenance(seed=None, command=["pytest"]), conditions)
    assert not verify_design_table(unscaled).ok
