"""Typed YAML configuration: defaults load, bad files give one ConfigError naming key and file."""

import re
import shutil

import pytest

from drake_cert import config
from drake_cert.errors import ConfigError


def test_shipped_defaults_load_and_match_design():
    vehicle = config.load_vehicle()
    assert vehicle.mass_kg == 1573.0 and vehicle.lf_m == 1.1 and vehicle.lr_m == 1.58
    assert vehicle.lane_margin_m == pytest.approx(0.85)
    table = config.load_conditions()
    assert table.condition("snow").interval == (20000.0, 40000.0)
    assert table.preset("carla-like").labels == ["sunny", "light_rain", "heavy_rain"]
    settings = config.load_settings()
    assert settings.synthesis.filter_gain_max == 500.0


def test_safe_sets_reproduce_the_papers_safety_class_table():
    table = config.load_conditions()
    assert table.safe_set("weather", "sunny") == ["sunny", "light_rain", "heavy_rain", "snow"]
    assert table.safe_set("weather", "light_rain") == ["light_rain", "heavy_rain", "snow"]
    assert table.safe_set("weather", "heavy_rain") == ["heavy_rain", "snow"]
    assert table.safe_set("weather", "snow") == ["snow"]
    assert table.safe_set("rtk-like", "asphalt") == ["asphalt", "cobblestone", "sand"]
    assert table.safe_set("rtk-like", "cobblestone") == ["cobblestone", "sand"]
    assert table.safe_set("rtk-like", "sand") == ["sand"]


def test_contiguous_ranges_and_hulls():
    table = config.load_conditions()
    ranges = table.contiguous_ranges("robotcar-like")
    assert len(ranges) == 6 and ["sunny", "rain", "snow"] in ranges
    assert ["sunny", "snow"] not in ranges
    assert table.hull(["rain", "snow"]) == (20000.0, 80000.0)
    assert table.envelope("carla-like") == (40000.0, 120000.0)
    assert table.least_friction(["sunny", "rain"]) == 0.6


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


def _vehicle_text(**overrides):
    fields = {"mass_kg": 1573.0, "yaw_inertia_kg_m2": 2873.0, "lf_m": 1.1, "lr_m": 1.58,
              "steering_limit_rad": 0.5, "lane_width_m": 3.5, "car_width_m": 1.8}
    fields.update(overrides)
    return "".join(f"{k}: {v}\n" for k, v in fields.items() if v is not None)


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        ({"mass_kg": -1.0}, "mass_kg"),
        ({"mass_kg": 0.0}, "mass_kg"),
        ({"mass_kg": "heavy"}, "mass_kg"),
        ({"lf_m": None}, "missing key 'lf_m'"),
        ({"masss_kg": 3.0}, "unknown key 'masss_kg'"),
        ({"car_width_m": 4.0}, "car_width_m"),
    ],
)
def test_bad_vehicle_file_names_key_and_file(tmp_path, overrides, expected):
    path = _write(tmp_path, "car.yaml", _vehicle_text(**overrides))
    with pytest.raises(ConfigError) as info:
        config.load_vehicle(path)
    assert expected in str(info.value)
    assert str(path) in str(info.value)


def test_unreadable_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        config.load_vehicle(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="not valid YAML"):
        config.load_vehicle(_write(tmp_path, "bad.yaml", "mass_kg: [1,\n"))
    with pytest.raises(ConfigError, match="mapping"):
        config.load_vehicle(_write(tmp_path, "list.yaml", "- 1\n- 2\n"))


def test_stiffness_interval_must_be_ordered(tmp_path):
    src = config.default_path("conditions.yaml").read_text()
    bad = src.replace("stiffness_lo_n_per_rad: 20000.0", "stiffness_lo_n_per_rad: 50000.0")
    with pytest.raises(ConfigError, match="snow.*stiffness_lo_n_per_rad"):
        config.load_conditions(_write(tmp_path, "c.yaml", bad))


def test_preset_labels_must_be_grippiest_first(tmp_path):
    src = config.default_path("conditions.yaml").read_text()
    bad = src.replace("labels: [sunny, rain, snow]", "labels: [snow, rain, sunny]")
    with pytest.raises(ConfigError, match="grippiest first"):
        config.load_conditions(_write(tmp_path, "c.yaml", bad))


def test_speed_range_must_be_ordered(tmp_path):
    src = config.default_path("settings.yaml").read_text()
    bad = src.replace("speed_min_mps: 5.0", "speed_min_mps: 40.0")
    with pytest.raises(ConfigError, match="speed_min_mps"):
        config.load_settings(_write(tmp_path, "s.yaml", bad))


def test_unknown_nested_key_is_named_with_its_path(tmp_path):
    src = config.default_path("settings.yaml").read_text()
    bad = src.replace("  decay_rate: 0.2", "  decay_rate: 0.2\n  decay_rat: 0.3")
    with pytest.raises(ConfigError, match=r"synthesis\.decay_rat"):
        config.load_settings(_write(tmp_path, "s.yaml", bad))


def test_unknown_adaptation_law_is_rejected(tmp_path):
    src = config.default_path("settings.yaml").read_text()
    bad = src.replace("adaptation_law: piecewise_constant", "adaptation_law: magic")
    with pytest.raises(ConfigError, match="adaptation_law"):
        config.load_settings(_write(tmp_path, "s.yaml", bad))


def test_a_copy_of_the_defaults_loads(tmp_path):
    for name in ("vehicle.yaml", "conditions.yaml", "settings.yaml"):
        shutil.copy(config.default_path(name), tmp_path / name)
    config.load_vehicle(tmp_path / "vehicle.yaml")
    config.load_conditions(tmp_path / "conditions.yaml")
    config.load_settings(tmp_path / "settings.yaml")


# --------------------------------------------------------------------------- units

@pytest.mark.parametrize(("overrides", "expected"), [
    ({"mass_kg": 1.573}, "mass_kg = 1.573 kg is implausibly small for a vehicle mass, below "
                         "100 kg (tonnes? write 1573)"),
    ({"mass_kg": 1_573_000}, "(g? write 1573)"),
    ({"yaw_inertia_kg_m2": 2.873}, "(t m^2? write 2873)"),
    ({"lf_m": 1100}, "lf_m = 1100 m is implausibly large for a CG-to-axle distance, above 10 m "
                     "(mm? write 1.1)"),
    ({"lr_m": 158}, "(cm? write 1.58)"),
    ({"lane_width_m": 350}, "(cm? write 3.5)"),
    ({"car_width_m": 1800}, "(mm? write 1.8)"),
    ({"lane_width_m": 25.0}, "lane_width_m = 25 m is implausibly large for a lane width, above "
                             "20 m"),
    ({"tire_stiffness_scale": 130000}, "not a stiffness"),
])
def test_a_vehicle_value_in_the_wrong_unit_names_the_likely_unit(tmp_path, overrides, expected):
    path = _write(tmp_path, "car.yaml", _vehicle_text(**overrides))
    with pytest.raises(ConfigError) as info:
        config.load_vehicle(path)
    assert str(info.value).startswith(f"{path}: ") and expected in str(info.value)
    assert len(str(info.value).splitlines()) == 1


@pytest.mark.parametrize(("name", "old", "new", "expected"), [
    ("conditions.yaml", "stiffness_lo_n_per_rad: 20000.0", "stiffness_lo_n_per_rad: 20.0",
     "conditions[4].stiffness_lo_n_per_rad = 20 N/rad is implausibly small for a cornering "
     "stiffness per tire, below 1000 N/rad (kN/rad? write 20000)"),
    ("conditions.yaml", "friction_mu: 0.9}", "friction_mu: 90}",
     "conditions[0].friction_mu = 90 is implausibly large for a friction coefficient, above 2 "
     "(percent? write 0.9)"),
    ("settings.yaml", "speed_max_mps: 30.0", "speed_max_mps: 108.0",
     "synthesis.speed_max_mps = 108 m/s is implausibly large for a road vehicle's speed, above "
     "100 m/s (km/h? write 30)"),
])
def test_conditions_and_settings_in_the_wrong_unit_name_the_likely_unit(tmp_path, name, old, new,
                                                                         expected):
    src = config.default_path(name).read_text()
    assert old in src
    path = _write(tmp_path, name, src.replace(old, new))
    load = config.load_conditions if name == "conditions.yaml" else config.load_settings
    with pytest.raises(ConfigError, match=re.escape(expected)):
        load(path)


def test_the_plausible_ranges_accept_every_shipped_vehicle_and_a_2600_kg_van(tmp_path):
    for path in [config.default_path("vehicle.yaml"),
                 *sorted(config.default_path("vehicles").glob("*.yaml"))]:
        config.load_vehicle(path)
    van = _write(tmp_path, "van.yaml", _vehicle_text(mass_kg=2600.0, yaw_inertia_kg_m2=5200.0,
                                                     lf_m=1.6, lr_m=1.9, car_width_m=2.05))
    assert config.load_vehicle(van).mass_kg == 2600.0


def test_validate_applies_the_ranges_to_a_vehicle_built_in_code():
    import dataclasses

    with pytest.raises(ConfigError, match=re.escape("tonnes? write 1500")):
        dataclasses.replace(config.load_vehicle(), mass_kg=1.5).validate("my car")


def test_a_binary_file_is_one_config_error_naming_the_file(tmp_path):
    path = tmp_path / "vehicle.yaml"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR")
    with pytest.raises(ConfigError, match=re.escape(f"{path}: not a text file (byte 0x89 at "
                                                    "offset 0 is not UTF-8); expected YAML")):
        config.load_vehicle(path)


def test_check_frame_size_says_how_much_memory_and_the_limit():
    config.check_frame_size(config.FRAME_SIZE_MAX, "--size", 500)  # the limit itself passes
    with pytest.raises(ConfigError) as info:
        config.check_frame_size(100_000, "--size", 500)
    assert str(info.value) == (
        "--size 100000 px: one 100000x100000 RGB frame takes 112 GiB in float32, a batch of "
        "500 noisy copies 54.6 TiB; the limit is 1024 px (12 MiB a frame; the shipped models "
        "take 64 px)")


@pytest.mark.parametrize("schema, name", [
    (config.VehicleParams, "vehicle.yaml"), (config.VehicleParams, "vehicles/suv.yaml"),
    (config.ConditionsTable, "conditions.yaml"), (config.Settings, "settings.yaml")])
def test_the_loader_without_drake_builds_what_pydrake_builds(schema, name):
    """A machine with torch but not Drake (a GPU box training models) loads the same files
    into the same objects."""
    import yaml

    path = config.default_path(name)
    raw = yaml.safe_load(path.read_text())
    built = config.build_without_drake(schema, raw, "", name)
    built = built.with_defaults() if hasattr(built, "with_defaults") else built  # as load_typed
    assert built == config.load_typed(schema, path)


def test_the_loader_without_drake_names_a_fraction_where_an_integer_belongs():
    with pytest.raises(ConfigError, match="frames_per_class = 2.5 must be an integer"):
        config.build_without_drake(config.Preset, {"name": "x", "labels": [],
                                                   "frames_per_class": 2.5}, "", "f.yaml")
