"""Scenarios: shipped files load, are commented, fit their preset and last 15-30 s; typos fail."""

import re

import pytest
import yaml

from drake_cert.config import load_conditions
from drake_cert.errors import ConfigError
from drake_cert.perception.models import model_path
from drake_cert.systems.route import Route
from drake_cert.systems.scenario import (
    SHIPPED_SCENARIOS,
    load_scenario,
    scenario_path,
    scenarios_dir,
)


@pytest.mark.parametrize("name", SHIPPED_SCENARIOS)
def test_shipped_scenario_loads_and_its_route_fits_its_preset(name):
    scenario = load_scenario(name)
    assert scenario.name == name
    route = Route.build(scenario.route, load_conditions(), scenario.perception.preset,
                        scenario.seed, scenario.transition_m)
    assert route.total_length_m == pytest.approx(scenario.route_length_m)
    assert len({seg.condition for seg in route.segments}) >= 2
    for sigma in (scenario.perception.sigma, scenario.perception.base_sigma):
        assert model_path(scenario.perception.preset, scenario.perception.task, sigma).exists()


def test_at_least_four_scenarios_are_shipped_as_files():
    assert len(SHIPPED_SCENARIOS) >= 4
    assert sorted(p.stem for p in scenarios_dir().glob("*.yaml")) == sorted(SHIPPED_SCENARIOS)


@pytest.mark.parametrize("name", SHIPPED_SCENARIOS)
def test_every_field_of_a_shipped_scenario_carries_a_comment(name):
    for number, line in enumerate(scenario_path(name).read_text().splitlines(), 1):
        if re.match(r"^\s*(- )?[a-z_]+:", line):
            assert "#" in line, f"{name}.yaml line {number} has no comment: {line!r}"


def test_weather_change_in_curve_changes_condition_inside_the_curve():
    route = load_scenario("weather_change_in_curve").route
    changes = [i for i in range(1, len(route)) if route[i].condition != route[i - 1].condition]
    assert any(route[i].curvature_per_m != 0 and
               route[i].curvature_per_m == route[i - 1].curvature_per_m for i in changes)


@pytest.mark.parametrize("name", SHIPPED_SCENARIOS)
def test_a_drive_at_the_design_speeds_lasts_15_to_30_seconds(name, default_design_table):
    """Estimate: each segment at its own label's design speed (length / speed)."""
    scenario = load_scenario(name)
    speed = {tuple(d.labels): d.speed_mps for d in default_design_table.designs}
    seconds = sum(seg.length_m / speed[(seg.condition,)] for seg in scenario.route)
    assert 15.0 <= seconds <= 30.0, f"{name}: {seconds:.1f} s"


def _write_variant(tmp_path, edit) -> str:
    data = yaml.safe_load(scenario_path("dry_to_snow").read_text())
    edit(data)
    path = tmp_path / "variant.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


@pytest.mark.parametrize("edit, key", [
    (lambda d: d.update(wheather="snow"), "wheather"),
    (lambda d: d["camera"].update(shutter_s=0.01), "camera.shutter_s"),
    (lambda d: d["route"][1].update(grip=0.5), "route[1].grip"),
    (lambda d: d["simulator"].update(max_stepsize=0.1), "max_stepsize"),
])
def test_unknown_keys_raise_config_error_naming_the_key(tmp_path, edit, key):
    with pytest.raises(ConfigError, match=re.escape(key)):
        load_scenario(_write_variant(tmp_path, edit))


@pytest.mark.parametrize("edit, key", [
    (lambda d: d["perception"].pop("n"), "perception.n"),
    (lambda d: d["perception"].update(pipeline="robust"), "perception.pipeline"),
    (lambda d: d["attack"].update(kind="fgsm"), "attack.kind"),
    (lambda d: d["camera"].update(rate_hz=0.0), "camera.rate_hz"),
    (lambda d: d["route"][0].update(curvature_per_m=0.1), "route[0].curvature_per_m"),
    (lambda d: d.update(seed=-1), "seed"),
    (lambda d: d["perception"].update(conformal_alpha_c=1.5), "perception.conformal_alpha_c"),
    # 131 calibration frames a label, 4 bins: under the 33 a bin that a bound of 0.25 at
    # delta_cal / 12 needs for any threshold (132 is the edge): every set would be every label
    (lambda d: d["perception"].update(conformal_frames_per_class=131),
     "perception.conformal_frames_per_class = 131 gives fewer than the 33 calibration frames"),
    (lambda d: d["perception"].update(conformal_delta_cal=0.0), "perception.conformal_delta_cal"),
    (lambda d: d.update(tolerated_wrong_frames=20), "tolerated_wrong_frames = 20"),
    (lambda d: d.update(looks_per_side=0), "looks_per_side = 0"),
])
def test_missing_keys_and_bad_values_raise_config_error(tmp_path, edit, key):
    with pytest.raises(ConfigError, match=re.escape(key)):
        load_scenario(_write_variant(tmp_path, edit))


def test_an_unknown_scenario_name_lists_the_shipped_ones():
    with pytest.raises(ConfigError, match="dry_to_snow"):
        load_scenario("no_such_scenario")


def test_a_frame_size_that_cannot_fit_in_memory_says_how_much_it_needs(tmp_path):
    path = _write_variant(tmp_path, lambda d: d["camera"].update(frame_size=100_000))
    with pytest.raises(ConfigError, match=re.escape(
            "camera.frame_size = 100000 px: one 100000x100000 RGB frame takes 112 GiB in float32, "
            "a batch of 500 noisy copies 54.6 TiB; the limit is 1024 px")):
        load_scenario(path)


def test_a_speed_in_km_per_h_names_the_unit(tmp_path):
    path = _write_variant(tmp_path, lambda d: d["motion"].update(initial_speed_mps=108.0))
    with pytest.raises(ConfigError, match=re.escape("motion.initial_speed_mps = 108 m/s is "
                                                    "implausibly large for a road vehicle's speed, "
                                                    "above 100 m/s (km/h? write 30)")):
        load_scenario(path)


def test_sequential_decisions_are_named_for_either_classification_interval_not_for_regression():
    """`decision: auto` decides the robust conformal set sequentially (DESIGN 3.6), so naming
    `sequential` with it is the same drive, not an error; a drive's regression interval has no
    sequential form and says so."""
    import dataclasses

    from drake_cert.systems.driving import with_overrides

    shipped = load_scenario("dry_to_snow")
    for interval in ("safe_set", "conformal"):
        named = dataclasses.replace(shipped.perception, decision="sequential", interval=interval)
        auto = dataclasses.replace(named, decision="auto")
        named.validate("scenario")
        assert named.resolved_decision == auto.resolved_decision == "sequential"
    regress = dataclasses.replace(shipped.perception, decision="sequential", task="regress")
    with pytest.raises(ConfigError, match="perception.decision = sequential needs task classify"):
        with_overrides(dataclasses.replace(shipped, perception=regress))


def test_132_calibration_frames_a_label_are_the_least_the_shipped_target_accepts(tmp_path):
    load_scenario(_write_variant(tmp_path, lambda d: d["perception"].update(
        conformal_frames_per_class=132)))
