"""`drake-cert drive` runs every shipped scenario, certified and base, under no attack, SA and
EA (a short drive each), prints one JSON object with the documented keys, and answers bad
input with one line and exit code 2."""

import dataclasses
import json

import pytest

from drake_cert.cli import main
from drake_cert.config import load_vehicle
from drake_cert.systems.scenario import SHIPPED_SCENARIOS, scenario_path

KEYS = {"left_lane", "peak_abs_e1_m", "time_left_lane_s", "mean_speed_mps", "min_speed_mps",
        "distance_m", "simulated_s", "wall_s", "interval_covers_true_fraction",
        "envelope_fraction", "design_switches", "seed"}


@pytest.fixture(scope="module")
def designs(tmp_path_factory, certified_design_table):
    """The file `drake-cert synthesize --out` writes for the shipped inputs (the session's
    table and certificates; the command itself is tested in test_verify.py)."""
    from drake_cert.synthesis.design_io import save_design_table

    path = tmp_path_factory.mktemp("designs") / "designs.yaml"
    save_design_table(path, certified_design_table)
    return str(path)


# every pipeline and attack on the first five, the certified car with the paper's safe-set
# interval; the shipped default (the robust conformal interval, which calibrates first: at
# most 100 samples a frame here, the suite's time budget) certified with and without SA on
# dry_to_snow and on the two routes added for the combined decisions (their full drives, as
# shipped, are slow tests in test_driving.py), and the base car under SA
DRIVE_CASES = ([(s, p, a, "safe_set") for s in SHIPPED_SCENARIOS[:5]
                for p in ("certified", "base") for a in ("none", "sa", "ea")]
               + [(s, p, a, "conformal") for s in ("dry_to_snow", *SHIPPED_SCENARIOS[5:])
                  for p, a in (("certified", "none"), ("certified", "sa"), ("base", "sa"))])


@pytest.mark.parametrize("scenario, pipeline, attack, interval", DRIVE_CASES)
def test_every_shipped_scenario_drives_under_every_attack(designs, scenario, pipeline, attack,
                                                          interval, capsys):
    budget = ["--n", "100"] if interval == "conformal" else []
    code = main(["drive", "--scenario", scenario, "--pipeline", pipeline, "--attack", attack,
                 "--duration", "0.5", "--designs", designs, "--json", "--interval", interval,
                 *budget])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert KEYS <= set(summary)
    assert summary["pipeline"] == pipeline and summary["attack"] == attack
    assert not summary["left_lane"]
    assert summary["vehicle"] == dataclasses.asdict(load_vehicle())  # the design file's
    if pipeline == "certified":
        assert summary["interval"] == interval
        assert summary["standing_assumption"] is (interval == "safe_set")


@pytest.mark.parametrize("argv, message", [
    (["--scenario", "mars"], "neither a file nor a shipped scenario"),
    (["--plot", "x.txt"], "expected a .png"),
    (["--eps", "-1"], "--eps"),
    (["--eps", "1e9"], "is the budget of an attack, and the drive has none"),
    (["--duration", "0"], "--duration"),
    (["--n", "0"], "--n"),
])
def test_bad_drive_input_is_one_line_and_exit_2(argv, message, capsys):
    assert main(["drive", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_an_unknown_preset_in_a_scenario_file_names_the_file_at_once(tmp_path, capsys):
    text = scenario_path("dry_to_snow").read_text()
    path = tmp_path / "kitti.yaml"
    path.write_text(text.replace("  preset: robotcar-like", "  preset: kitti"))
    assert main(["drive", "--scenario", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{path}: perception.preset: unknown preset 'kitti'" in err[0]


def test_an_initial_speed_in_km_per_h_is_one_line(designs, tmp_path, capsys):
    """72 (km/h meant) would start the car at 3.7x the fastest safe speed of its designs."""
    text = scenario_path("dry_to_snow").read_text()
    old = "  initial_speed_mps: 0.0  #"
    assert old in text
    path = tmp_path / "fast.yaml"
    path.write_text(text.replace(old, "  initial_speed_mps: 72.0  #"))
    assert main(["drive", "--scenario", str(path), "--designs", designs]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "initial_speed_mps = 72 m/s is above the fastest safe speed" in err[0]
    assert "72 km/h is 20.00 m/s" in err[0]


def test_seed_none_draws_fresh_noise_and_records_the_seed_to_replay_it(designs, capsys):
    # (n: the suite's budget; the drives share one conformal calibration, DESIGN 3.6, so the
    # replay is exact)
    runs = []
    for _ in range(2):
        assert main(["drive", "--scenario", "dry_to_snow", "--seed", "none", "--duration",
                     "0.3", "--designs", designs, "--json", "--n", "100"]) == 0
        runs.append(json.loads(capsys.readouterr().out))
    assert all(r["seed_source"] == "os-entropy" for r in runs)
    assert runs[0]["seed"] != runs[1]["seed"]
    assert main(["drive", "--scenario", "dry_to_snow", "--seed", str(runs[0]["seed"]),
                 "--duration", "0.3", "--designs", designs, "--json", "--n", "100"]) == 0
    replay = json.loads(capsys.readouterr().out)
    assert replay["seed_source"] == "scenario"
    assert replay["mean_samples_per_tick"] == runs[0]["mean_samples_per_tick"]
    assert replay["peak_abs_e1_m"] == runs[0]["peak_abs_e1_m"]


def test_drive_uses_the_design_files_vehicle_and_refuses_another(designs, tmp_path, capsys):
    from pathlib import Path

    shipped = Path(__file__).resolve().parents[1] / "drake_cert" / "data" / "vehicle.yaml"
    assert main(["drive", "--scenario", "dry_to_snow", "--duration", "0.3", "--designs",
                 designs, "--vehicle", str(shipped), "--json"]) == 0  # the same vehicle
    capsys.readouterr()
    van = tmp_path / "van.yaml"
    van.write_text(shipped.read_text().replace("mass_kg: 1573.0", "mass_kg: 2600.0"))
    assert main(["drive", "--scenario", "dry_to_snow", "--duration", "0.3", "--designs",
                 designs, "--vehicle", str(van)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "mass_kg = 2600.0" in err[0] and "1573.0" in err[0]


def test_a_table_whose_envelope_has_no_safe_speed_is_refused_not_driven(designs, tmp_path,
                                                                         capsys):
    import dataclasses

    from drake_cert.config import load_conditions
    from drake_cert.synthesis.design_io import load_design_file, save_design_table

    table = load_design_file(designs)
    family = tuple(load_conditions().preset("robotcar-like").labels)
    stuck = [dataclasses.replace(d, speed_mps=0.0, failed_condition="l1_condition")
             if tuple(d.labels) == family else d for d in table.designs]
    path = tmp_path / "stuck.yaml"
    save_design_table(path, dataclasses.replace(table, designs=stuck))
    assert main(["drive", "--scenario", "dry_to_snow", "--duration", "0.3", "--designs",
                 str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no safe speed for the envelope" in err[0]


def test_a_sample_budget_that_can_never_certify_eps_is_refused_before_driving(designs, tmp_path,
                                                                             capsys):
    from pathlib import Path

    shipped = Path(__file__).resolve().parents[1] / "drake_cert" / "data" / "scenarios"
    text = (shipped / "dry_to_snow.yaml").read_text()
    wide = tmp_path / "wide.yaml"  # eps/sigma = 3 needs thousands of unanimous samples
    wide.write_text(text.replace("\n  eps: 1.0  # L2 budget (pixel units) the run-time",
                                 "\n  eps: 3.0  # L2 budget (pixel units) the run-time"))
    # (the safe-set interval's sequential decision; the conformal set at such a budget is the
    # envelope without a sample, DESIGN 3.6)
    assert main(["drive", "--scenario", str(wide), "--duration", "0.3", "--designs",
                 designs, "--interval", "safe_set"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "can never certify" in err[0] and "n_max = 1000" in err[0]


def _shipped_text(name: str) -> str:
    from pathlib import Path

    shipped = Path(__file__).resolve().parents[1] / "drake_cert" / "data" / "scenarios"
    return (shipped / f"{name}.yaml").read_text()


def _refusal(designs, tmp_path, capsys, text: str) -> str:
    path = tmp_path / "patched.yaml"
    path.write_text(text)
    assert main(["drive", "--scenario", str(path), "--duration", "0.3", "--designs",
                 designs]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_a_condition_stretch_shorter_than_the_assumed_shortest_is_refused(designs, tmp_path,
                                                                          capsys):
    text = _shipped_text("dry_to_snow")
    patch = "  - {length_m: 12.0, curvature_per_m: 0.0, condition: snow}\n"
    rain = "  - {length_m: 30.0, curvature_per_m: 0.0, condition: rain}"
    assert rain in text  # 12 m of snow between sunny and rain: two boundaries in 80 m
    err = _refusal(designs, tmp_path, capsys, text.replace(rain, patch + rain))
    assert "route segment 3 (snow, 12 m" in err and "min_condition_length_m = 80 m" in err


def test_an_assumed_shortest_stretch_within_the_road_between_two_frames_is_refused(
        designs, tmp_path, capsys):
    text = _shipped_text("dry_to_snow").replace("\nmin_condition_length_m: 80.0",
                                                "\nmin_condition_length_m: 1.5")
    err = _refusal(designs, tmp_path, capsys, text)
    assert "min_condition_length_m = 1.5 m" in err and "10 Hz" in err and "1.94 m" in err


def test_a_look_ahead_too_short_for_the_top_speed_is_refused_naming_what_it_supports(
        designs, tmp_path, capsys):
    # 40 m at 10 Hz: braking at 3.6 m/s^2 from v to the envelope's 8.28 m/s, 2 m margin and
    # 0.175 s on an unmoved frontier plus 14 periods (the decided road trails the newest look
    # point by the 14 tolerated wrong looks, docs/design.md 6.3) carry
    # v^2 + 11.34 v = 8.28^2 + 7.2 * 38, v = 13.68 m/s; the sunny design's 19.36 m/s needs 75.0 m
    text = _shipped_text("dry_to_snow").replace("  look_ahead_m: 80.0", "  look_ahead_m: 40.0")
    err = _refusal(designs, tmp_path, capsys, text)
    assert "supports at most 13.68 m/s" in err and "19.36 m/s" in err and "75.0 m" in err
    # tolerating no wrong look: v^2 + 1.26 v = 8.28^2 + 7.2 * 38, 17.88 m/s and 47.9 m
    text = text.replace("tolerated_wrong_frames: 14", "tolerated_wrong_frames: 0")
    err = _refusal(designs, tmp_path, capsys, text)
    assert "supports at most 17.88 m/s" in err and "47.9 m" in err


def test_drive_help_names_every_shipped_scenario(capsys):
    from drake_cert.systems.scenario import SHIPPED_SCENARIOS

    with pytest.raises(SystemExit):
        main(["drive", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert all(name in text for name in SHIPPED_SCENARIOS), text
