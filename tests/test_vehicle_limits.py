"""Speeds that know the vehicle (DESIGN 5.3e): the rollover threshold of a vehicle that gives
its CG height and track, a comfort limit when the settings give one, and which limit binds
each speed, each rechecked by verify."""

import dataclasses
import math

import pytest

from drake_cert.config import (
    GRAVITY_MPS2,
    default_path,
    load_conditions,
    load_settings,
    load_vehicle,
)
from drake_cert.io import provenance
from drake_cert.synthesis.design_io import DesignTable, load_design_file, save_design_table
from drake_cert.synthesis.speed import SPEED_RESOLUTION_MPS
from drake_cert.synthesis.table import synthesize_label_range
from drake_cert.synthesis.verify import verify_design_table

CONDITIONS = load_conditions()
SETTINGS = load_settings()
CAR = load_vehicle()
VAN = load_vehicle(default_path("vehicles/vw_vanagon.yaml"))
RADIUS = SETTINGS.synthesis.design_radius_m
RESOLUTION = SPEED_RESOLUTION_MPS


@pytest.fixture(scope="module")
def van_sunny():
    return synthesize_label_range(VAN, CONDITIONS, ["sunny"], SETTINGS)


def _table(design, vehicle=VAN, settings=SETTINGS):
    return DesignTable([design], vehicle, settings, provenance(seed=None, command=["pytest"]))


def test_the_van_takes_the_dry_curve_slower_than_the_car_because_it_would_tip(van_sunny):
    ssf = VAN.track_width_m / (2 * VAN.cg_height_m)
    rollover_speed = math.sqrt(SETTINGS.synthesis.rollover_fraction * ssf * GRAVITY_MPS2 * RADIUS)
    car_sunny = synthesize_label_range(CAR, CONDITIONS, ["sunny"], SETTINGS)
    assert car_sunny.speed_limited_by == "grip"
    assert van_sunny.speed_limited_by == "rollover"
    assert rollover_speed - RESOLUTION <= van_sunny.speed_mps <= rollover_speed
    assert van_sunny.speed_mps < car_sunny.speed_mps - 0.3
    assert van_sunny.margins["rollover_lateral_accel_mps2"] >= 0.0


def test_where_grip_binds_first_the_van_is_as_fast_as_the_car():
    van = synthesize_label_range(VAN, CONDITIONS, ["rain"], SETTINGS)
    car = synthesize_label_range(CAR, CONDITIONS, ["rain"], SETTINGS)
    assert van.speed_limited_by == car.speed_limited_by == "grip"
    assert van.speed_mps == car.speed_mps


def test_a_comfort_limit_caps_every_speed_above_it_and_says_so():
    syn = dataclasses.replace(SETTINGS.synthesis, lateral_accel_limit_mps2=3.0)
    settings = dataclasses.replace(SETTINGS, synthesis=syn)
    comfort_speed = math.sqrt(3.0 * RADIUS)  # 12.25 m/s
    sunny = synthesize_label_range(CAR, CONDITIONS, ["sunny"], settings)
    assert sunny.speed_limited_by == "comfort"
    assert comfort_speed - RESOLUTION <= sunny.speed_mps <= comfort_speed
    snow = synthesize_label_range(CAR, CONDITIONS, ["snow"], settings)  # grip: 10.2 m/s < 12.25
    assert snow.speed_limited_by == "grip" and snow.speed_mps < comfort_speed - 1.0
    assert verify_design_table(_table(sunny, CAR, settings)).ok


def test_verify_rechecks_the_rollover_limit_from_the_vehicle(van_sunny):
    assert verify_design_table(_table(van_sunny)).ok
    taller = dataclasses.replace(VAN, cg_height_m=0.9)  # the same design on a taller van
    report = verify_design_table(_table(van_sunny, taller))
    assert not report.ok
    assert any(f["condition"] == "rollover" for d in report.to_dict()["designs"]
               for f in d["reasons"])


def test_verify_refuses_a_binding_limit_the_vehicle_does_not_have(van_sunny):
    car_design = dataclasses.replace(van_sunny, speed_limited_by="rollover")
    report = verify_design_table(_table(car_design, dataclasses.replace(
        VAN, cg_height_m=None, track_width_m=None)))
    assert not report.ok
    unknown = dataclasses.replace(van_sunny, speed_limited_by="tyres")
    assert not verify_design_table(_table(unknown)).ok


def test_the_binding_limit_is_saved_and_a_file_without_it_still_loads(van_sunny, tmp_path):
    path = tmp_path / "van.yaml"
    save_design_table(path, _table(van_sunny), switching=False)
    (loaded,) = load_design_file(path).designs
    assert loaded.speed_limited_by == "rollover"
    old = path.read_text().replace("speed_limited_by: rollover\n", "")
    assert "speed_limited_by" not in old
    path.write_text(old)
    (loaded,) = load_design_file(path).designs
    assert loaded.speed_limited_by == "" and loaded.speed_mps == van_sunny.speed_mps


def test_where_the_l1_condition_fails_at_k_bar_the_search_goes_on_to_the_sample_period_limit():
    """At k_bar = 200 the widest interval (20-120 kN/rad) has no safe speed: the L1 condition
    fails at every speed. The search then runs to the sample-period limit k w_max T_s <= 1
    (about 570 at T_s = 1 ms), finds a safe speed below it, and verify accepts the design; a
    longer sample period lowers the limit and leaves no way out."""
    from drake_cert.synthesis.speed import sample_period_filter_gain_limit
    from drake_cert.synthesis.table import synthesize_design

    slow = dataclasses.replace(SETTINGS, synthesis=dataclasses.replace(
        SETTINGS.synthesis, filter_gain_max=200.0))
    design = synthesize_design(CAR, (20e3, 120e3), 0.25, slow, ["wide"])
    assert design.has_safe_speed
    limit = sample_period_filter_gain_limit(slow, design.certified_interval)
    assert 200.0 < design.filter_gain <= limit
    assert limit * slow.controller.sample_period_s * (
        design.certified_interval[1] / design.nominal_stiffness_n_per_rad) == pytest.approx(1.0)
    assert verify_design_table(_table(design, CAR, slow)).ok
    coarse = dataclasses.replace(slow, controller=dataclasses.replace(
        slow.controller, sample_period_s=5e-3))  # limit about 115 < k_bar: no second scan
    stuck = synthesize_design(CAR, (20e3, 120e3), 0.25, coarse, ["wide"])
    assert not stuck.has_safe_speed and stuck.failed_condition == "l1_condition"


def test_a_scenario_whose_envelope_cannot_move_is_refused_naming_the_scenarios_that_can(
        default_design_table):
    from drake_cert.errors import ConfigError
    from drake_cert.systems.driving import moving_envelope

    stopped = [dataclasses.replace(d, speed_mps=0.0, failed_condition="l1_condition",
                                   speed_limited_by="")
               if d.labels == ["sunny", "rain", "snow"] else d
               for d in default_design_table.designs]
    with pytest.raises(ConfigError) as refused:
        moving_envelope(stopped, CONDITIONS, "robotcar-like")
    message = str(refused.value)
    assert "robotcar-like" in message and "l1_condition" in message
    assert "rain_route" in message and "road_surface" in message  # carla-like, rtk-like
    assert "dry_to_snow" not in message.split("can drive")[1].split(";")[0]
    assert "sample_period_s" in message


def test_synthesize_says_which_ranges_stop_and_what_to_change(van_sunny):
    from drake_cert.cli.synthesize import no_safe_speed_note

    stopped = dataclasses.replace(van_sunny, labels=["sunny", "rain", "snow"], speed_mps=0.0,
                                  failed_condition="l1_condition", speed_limited_by="")
    note = no_safe_speed_note([stopped])
    assert note.startswith("1 label range has no safe speed, the car stops there: "
                           "sunny+rain+snow (l1_condition)")
    assert "per axle" in note and "sample_period_s" in note
