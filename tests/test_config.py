"""Typed YAML configuration: defaults load, bad files give one ConfigError naming key and file."""

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
