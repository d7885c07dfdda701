"""A vehicle file may give its front and rear tires separately (DESIGN 2.1): the design model,
both plants, synthesis and verify carry C_r = rho C with the vehicle's fixed ratio rho, and a
file with one scale reads as before."""

import dataclasses

import numpy as np
import pytest
import yaml

from drake_cert.config import default_path, load_conditions, load_settings, load_vehicle
from drake_cert.dynamics import lateral_error_dynamics
from drake_cert.errors import ConfigError
from drake_cert.synthesis.table import synthesize_label_range, synthesize_table
from drake_cert.synthesis.verify import cornering_slip_angles
from drake_cert.systems.plants import PlantInputs, single_track_derivatives

CONDITIONS = load_conditions()
SETTINGS = load_settings()
ESCORT = load_vehicle(default_path("vehicles/ford_escort.yaml"))
PUBLISHED = ("ford_escort", "bmw_320i", "vw_vanagon", "honda_civic")


def rajamani_matrices(m, iz, lf, lr, cf, cr, v):
    """Eq. 2.45 written out with one stiffness per axle (per tire, two tires an axle)."""
    a = np.array([
        [0, 1, 0, 0],
        [0, -2 * (cf + cr) / (m * v), 2 * (cf + cr) / m, 2 * (-cf * lf + cr * lr) / (m * v)],
        [0, 0, 0, 1],
        [0, -2 * (cf * lf - cr * lr) / (iz * v), 2 * (cf * lf - cr * lr) / iz,
         -2 * (cf * lf**2 + cr * lr**2) / (iz * v)]])
    b = np.array([0, 2 * cf / m, 0, 2 * cf * lf / iz])
    return a, b


def test_every_shipped_vehicle_file_loads_and_one_scale_means_both_axles():
    car = load_vehicle()
    assert car.rear_stiffness_ratio == 1.0 and car.static_stability_factor is None
    suv = load_vehicle(default_path("vehicles/suv.yaml"))  # one scale: both axles
    assert suv.rear_tire_stiffness_scale == suv.tire_stiffness_scale == 1.3
    assert suv.rear_stiffness_ratio == 1.0

    for name in PUBLISHED:
        v = load_vehicle(default_path(f"vehicles/{name}.yaml"))
        assert v.rear_tire_stiffness_scale is not None and v.rear_stiffness_ratio != 1.0


def test_a_vehicle_file_with_one_scale_is_the_vehicle_with_both_scales_equal(tmp_path):
    one = tmp_path / "one_scale.yaml"
    one.write_text("\n".join(line for line in default_path("vehicle.yaml").read_text()
                             .splitlines() if not line.startswith("rear_tire_stiffness_scale")))
    assert load_vehicle(one) == load_vehicle()


def test_the_design_model_takes_the_rear_tires_stiffness_from_the_rear_scale():
    c, v = 60_000.0, 15.0
    a, b, _ = lateral_error_dynamics(ESCORT, c, v)
    rho = ESCORT.rear_tire_stiffness_scale / ESCORT.tire_stiffness_scale
    a_ref, b_ref = rajamani_matrices(ESCORT.mass_kg, ESCORT.yaw_inertia_kg_m2, ESCORT.lf_m,
                                     ESCORT.lr_m, c, rho * c, v)
    np.testing.assert_allclose(a, a_ref, rtol=1e-12)
    np.testing.assert_allclose(b, b_ref, rtol=1e-12)
    one_scale = dataclasses.replace(ESCORT, rear_tire_stiffness_scale=None)
    a_one, _ = rajamani_matrices(ESCORT.mass_kg, ESCORT.yaw_inertia_kg_m2, ESCORT.lf_m,
                                 ESCORT.lr_m, c, c, v)
    np.testing.assert_allclose(lateral_error_dynamics(one_scale, c, v)[0], a_one, rtol=1e-12)


def test_load_proportional_tires_make_a_neutral_steer_car_and_equal_tires_an_understeering_one():
    """CommonRoad's tires are proportional to the axle load: both axles slip alike in a steady
    turn (understeer gradient 0). One stiffness on all four tires moves the slip to the front
    axle, which carries more load: the model's car understeers."""
    c = ESCORT.tire_stiffness_scale * 100_000.0
    a_f, a_r = cornering_slip_angles(ESCORT, c, 15.0, 50.0)
    assert a_f == pytest.approx(a_r, rel=2e-3)
    equal = dataclasses.replace(ESCORT, rear_tire_stiffness_scale=None)
    a_f, a_r = cornering_slip_angles(equal, c, 15.0, 50.0)
    a_y = 15.0**2 / 50.0
    understeer_gradient = (a_f - a_r) / a_y  # rad per m/s^2
    assert understeer_gradient > 1e-3


def test_the_nonlinear_plant_uses_the_rear_tires_stiffness():
    """At a small rear slip (no steering, no yaw), the rear axle force is 2 C_r tan(a_r)."""
    c, speed, vy = 60_000.0, 15.0, -1.0e-4
    rho = ESCORT.rear_stiffness_ratio
    x = np.array([0.0, vy, 0.0, 0.0])
    front_and_rear = single_track_derivatives(ESCORT, x, PlantInputs(0.0, c, 1.0, speed, 0.0))
    # with r = 0 and u = 0 both axles see tan a = vy / V; vy_dot = (F_f + F_r) / m
    tan_a = vy / speed
    linear = -(2 * c + 2 * rho * c) * tan_a / ESCORT.mass_kg
    assert front_and_rear[1] == pytest.approx(linear, rel=1e-4)
    moment = -(ESCORT.lf_m * 2 * c - ESCORT.lr_m * 2 * rho * c) * tan_a / ESCORT.yaw_inertia_kg_m2
    assert front_and_rear[3] == pytest.approx(moment, rel=1e-4)


def test_the_api_gives_the_cli_design_for_a_per_axle_vehicle():
    """synthesize_label_range (the README example's call) equals the table's design for the
    range on a vehicle with per-axle tires, as it does for a scaled one."""
    conditions = dataclasses.replace(CONDITIONS, presets=[dataclasses.replace(
        CONDITIONS.preset("carla-like"), labels=["heavy_rain"])])
    (from_table,) = synthesize_table(ESCORT, conditions, SETTINGS)
    design = synthesize_label_range(ESCORT, conditions, ["heavy_rain"], SETTINGS)
    assert dataclasses.asdict(design) == dataclasses.asdict(from_table)
    lo, hi = CONDITIONS.condition("heavy_rain").interval
    assert design.interval == pytest.approx((ESCORT.tire_stiffness_scale * lo,
                                             ESCORT.tire_stiffness_scale * hi))
    assert design.has_safe_speed


@pytest.mark.parametrize("bad, message", [
    ({"rear_tire_stiffness_scale": 0.0}, "rear_tire_stiffness_scale"),
    ({"rear_tire_stiffness_scale": "0.5"}, "must be a number"),
    ({"rear_tire_stiffness_scale": 48_700.0}, "implausibly large"),
    ({"cg_height_m": 0.55}, "without track_width_m"),
    ({"cg_height_m": 550.0, "track_width_m": 1.4}, "mm"),
    ({"cg_height_m": 0.55, "track_width_m": 1.9}, "less than car_width_m"),
])
def test_bad_tire_and_roll_fields_are_named(tmp_path, bad, message):
    data = yaml.safe_load(default_path("vehicle.yaml").read_text())
    data.update(bad)
    path = tmp_path / "vehicle.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=message):
        load_vehicle(path)


@pytest.mark.slow
@pytest.mark.parametrize("name", PUBLISHED)
def test_every_label_range_of_a_published_vehicle_has_a_safe_speed_that_verify_accepts(name):
    from drake_cert.io import provenance
    from drake_cert.synthesis.design_io import DesignTable
    from drake_cert.synthesis.verify import verify_design_table

    vehicle = load_vehicle(default_path(f"vehicles/{name}.yaml"))
    designs = synthesize_table(vehicle, CONDITIONS, SETTINGS)
    assert len(designs) == 20 and all(d.has_safe_speed for d in designs)
    table = DesignTable(designs, vehicle, SETTINGS, provenance(seed=None, command=["pytest"]),
                        CONDITIONS)
    report = verify_design_table(table, conditions=CONDITIONS)
    assert report.ok, report.to_dict()


def test_a_drives_text_summary_names_both_axles_tires():
    from drake_cert.cli.drive import format_summaries

    summary = {"scenario": "dry_to_snow", "seed": 1, "pipeline": "certified",
               "vehicle": dataclasses.asdict(ESCORT)}
    text = format_summaries([summary])
    assert "tire stiffness front x0.8311, rear x0.4869" in text
    one = {**summary, "vehicle": dataclasses.asdict(load_vehicle())}
    assert "tire stiffness x1\n" in format_summaries([one]) + "\n"
    assert "per axle" not in format_summaries([one])


def test_a_per_axle_drive_shows_each_design_interval_for_both_tires():
    """Every interval of a drive is the front tire's C; for a per-axle vehicle the text and
    the plot show the rear tire's too (rho C, rho = rear scale / front scale)."""
    from drake_cert.cli.drive import format_summaries
    from drake_cert.systems.drive_plot import rear_ratio

    summary = {"scenario": "dry_to_snow", "seed": 1, "pipeline": "certified",
               "vehicle": dataclasses.asdict(ESCORT),
               "design_intervals_n_per_rad": [[83_112.0, 99_734.4], [16_622.4, 99_734.4]]}
    rho = 0.4869 / 0.8311
    assert rear_ratio(summary) == pytest.approx(rho)
    text = format_summaries([summary])
    assert f"the rear tire's is {rho:.4g} C" in text
    assert "design [83.1, 99.7] kN/rad front, [48.7, 58.4] rear" in text
    assert "design [16.6, 99.7] kN/rad front, [9.7, 58.4] rear" in text
    assert rear_ratio({"vehicle": dataclasses.asdict(load_vehicle())}) == 1.0
