"""A vehicle file may scale the conditions table's per-tire stiffness (DESIGN 2.1)."""

import dataclasses

import pytest

from drake_cert.config import default_path, load_conditions, load_settings, load_vehicle
from drake_cert.errors import ConfigError
from drake_cert.io import provenance
from drake_cert.synthesis.design_io import DesignTable
from drake_cert.synthesis.table import synthesize_label_range, synthesize_table
from drake_cert.synthesis.verify import verify_design_table

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


def test_the_api_designs_a_label_range_for_the_vehicles_own_tires_as_the_cli_does():
    """synthesize_label_range on a scaled vehicle gives the design table's design (what
    `drake-cert synthesize` writes) for that range, not the design of the table's tires."""
    conditions = _heavy_rain_only(CONDITIONS)
    (from_table,) = synthesize_table(SUV, conditions, SETTINGS)
    design = synthesize_label_range(SUV, conditions, ["heavy_rain"], SETTINGS)
    assert dataclasses.asdict(design) == dataclasses.asdict(from_table)
    separate = synthesize_label_range(SUV, CONDITIONS, ["heavy_rain"], SETTINGS,
                                      gains="separate")  # the range's own LMI: no table needed
    (separate_table,) = synthesize_table(SUV, conditions, SETTINGS, gains="separate")
    assert dataclasses.asdict(separate) == dataclasses.asdict(separate_table)
    lo, _ = CONDITIONS.condition("heavy_rain").interval
    assert design.stiffness_lo_n_per_rad == pytest.approx(SUV.tire_stiffness_scale * lo)
    with pytest.raises(ConfigError, match=r"sunny\+snow is not one the conditions table"):
        synthesize_label_range(SUV, CONDITIONS, ["sunny", "snow"], SETTINGS)


@pytest.fixture(scope="module")
def suv_carla_designs():
    """The SUV's designs for the carla-like label ranges (synthesized on scaled intervals;
    its envelope has a safe speed there, not in robotcar-like's, whose snow it cannot take
    with sunny's gains)."""
    conditions = dataclasses.replace(CONDITIONS, presets=[CONDITIONS.preset("carla-like")])
    return conditions, synthesize_table(SUV, conditions, SETTINGS)


def test_the_suv_drives_on_its_own_tires(suv_carla_designs):
    """The truth under the car is the road's stiffness as the SUV's tires feel it (scaled),
    the same stiffness its designs were synthesized for; the road's friction is unchanged."""
    from drake_cert.systems.driving import build_certified_driving_diagram
    from drake_cert.systems.route import Route
    from drake_cert.systems.scenario import load_scenario

    conditions, designs = suv_carla_designs
    scenario = load_scenario("rain_route")
    scenario = dataclasses.replace(scenario, perception=dataclasses.replace(
        scenario.perception, pipeline="base"))
    built = build_certified_driving_diagram(scenario, vehicle=SUV, settings=SETTINGS,
                                            conditions=conditions, designs=designs)
    reference = Route.build(scenario.route, conditions, "carla-like", scenario.seed,
                            transition_m=scenario.transition_m)
    scale = SUV.tire_stiffness_scale
    for seg, ref in zip(built.route.segments, reference.segments, strict=True):
        lo, hi = conditions.condition(seg.condition).interval
        assert scale * lo <= seg.stiffness_n_per_rad <= scale * hi
        assert seg.stiffness_n_per_rad == pytest.approx(scale * ref.stiffness_n_per_rad)
        assert seg.friction_mu == ref.friction_mu  # friction is the road's, not the tire's
    # and the drive says which vehicle drove
    from drake_cert.systems.driving import drive

    short = dataclasses.replace(scenario, t_final_s=0.2)
    result = drive(build_certified_driving_diagram(short, vehicle=SUV, settings=SETTINGS,
                                                   conditions=conditions, designs=designs))
    assert result.summary["vehicle"] == dataclasses.asdict(SUV)


def test_a_regressed_stiffness_is_scaled_to_the_vehicle_before_a_design_is_chosen(
        suv_carla_designs):
    """A regressor estimates the reference tire's stiffness: the SUV's is scale times it."""
    from drake_cert.errors import ConfigError
    from drake_cert.systems.certified_interval import CertifiedInterval, IntervalInputs
    from drake_cert.systems.perception_smoothing import PerceptionResult
    from drake_cert.systems.scenario import PerceptionSettings

    conditions, designs = suv_carla_designs
    scale = SUV.tire_stiffness_scale
    tires = conditions.with_stiffness_scale(scale)
    base = PerceptionSettings(preset="carla-like", eps=0.0, pipeline="base", task="regress")
    block = CertifiedInterval(designs, tires, base, inputs=IntervalInputs(stiffness_scale=scale))
    wet_lo, _ = conditions.condition("heavy_rain").interval  # reference tire
    p = dataclasses.replace(PerceptionResult.no_frame("base", "regress"), frame_ok=True,
                            base_value_n_per_rad=wet_lo)  # below every scaled interval
    decision = block.request(p)
    assert decision.status == "base"
    assert designs[decision.design_index].labels == ["heavy_rain"]
    unscaled = CertifiedInterval(designs, tires, base)
    assert unscaled.request(p).status == "envelope"  # no SUV design holds the raw value
    with pytest.raises(ConfigError, match="stiffness_scale"):
        CertifiedInterval(designs, tires, PerceptionSettings(preset="carla-like", eps=0.0),
                          inputs=IntervalInputs(stiffness_scale=0.0))
