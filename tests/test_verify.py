"""``drake-cert synthesize`` / ``verify`` (DESIGN 5.5): designs pass, tampered ones fail."""

import dataclasses
import json
import subprocess
import sys

import pytest
import yaml

from drake_cert import cli
from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.io import provenance
from synthesis.design_io import DesignTable, load_design_file, save_design_table
from synthesis.table import synthesize_design
from synthesis.verify import verify_design


@pytest.fixture(scope="module")
def table_file(default_design_table, tmp_path_factory):
    path = tmp_path_factory.mktemp("designs") / "designs.yaml"
    save_design_table(path, default_design_table)
    return path


def _tampered(table_file, tmp_path, edit, labels=None):
    """The saved table edited by ``edit(raw)``; with ``labels``, only that design is kept
    (``raw["designs"][0]``), so that verify has one design to check."""
    raw = yaml.safe_load(table_file.read_text())
    if labels is not None:
        raw["designs"] = [d for d in raw["designs"] if tuple(d["labels"]) == labels]
    edit(raw)
    path = tmp_path / "tampered.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def test_synthesized_table_round_trips_and_passes_verify(default_design_table, table_file, capsys):
    loaded = load_design_file(table_file)
    assert loaded.designs == default_design_table.designs
    assert loaded.provenance["schema_version"] == 1 and "git_revision" in loaded.provenance
    assert cli.main(["verify", str(table_file)]) == 0
    out = capsys.readouterr()
    assert "all 20 designs hold" in out.err
    assert "l1_condition=" in out.out and "steady_state_offset_m=" in out.out


def test_unstabilising_gain_fails_naming_gain_decay(table_file, tmp_path, capsys):
    def edit(raw):
        raw["designs"][0]["k_m"] = [0.0, 0.0, 0.0, 0.0]

    assert cli.main(["verify", str(_tampered(table_file, tmp_path, edit, ("snow",)))]) == 1
    assert "fails gain_decay" in capsys.readouterr().err


def test_speed_raised_above_what_the_conditions_allow_fails_naming_the_condition(
        table_file, tmp_path, capsys):
    def edit(raw):
        raw["designs"][0]["speed_mps"] = 22.0

    path = _tampered(table_file, tmp_path, edit, ("sunny",))
    assert cli.main(["verify", "--json", str(path)]) == 1
    out = capsys.readouterr()
    report = json.loads(out.out)
    failed = {f["condition"] for d in report["designs"] for f in d["failures"]}
    assert report["ok"] is False and "grip" in failed
    first = report["first_failure"]
    assert first["labels"] == ["sunny"]
    assert f"fails {first['condition']}" in out.err


def test_claiming_no_safe_speed_when_one_exists_fails(table_file, tmp_path, capsys):
    def edit(raw):
        d = raw["designs"][0]
        d["speed_mps"], d["failed_condition"] = 0.0, "grip"

    path = _tampered(table_file, tmp_path, edit, ("heavy_rain",))
    assert cli.main(["verify", str(path)]) == 1
    assert "no_safe_speed_claim" in capsys.readouterr().err


def test_overstated_margin_fails(table_file, tmp_path, capsys):
    def edit(raw):
        raw["designs"][0]["margins"]["l1_condition"] = 0.9

    path = _tampered(table_file, tmp_path, edit, ("rain", "snow"))
    assert cli.main(["verify", str(path)]) == 1
    assert "margin_claim" in capsys.readouterr().err


def test_interval_not_matching_the_labels_fails(table_file, tmp_path, capsys):
    def edit(raw):
        raw["designs"][0]["stiffness_lo_n_per_rad"] = 25000.0

    assert cli.main(["verify", str(_tampered(table_file, tmp_path, edit, ("snow",)))]) == 1
    assert "consistency" in capsys.readouterr().err


def test_true_no_safe_speed_claim_holds():
    vehicle, settings = load_vehicle(), load_settings()
    settings = dataclasses.replace(
        settings, synthesis=dataclasses.replace(settings.synthesis, normalised_slip_max=1e-4))
    design = synthesize_design(vehicle, (20e3, 40e3), 0.25, settings, ["snow"])
    assert design.speed_mps == 0.0 and design.failed_condition == "grip"
    check = verify_design(design, vehicle, settings, load_conditions())
    assert check.ok, check.failures


def test_single_design_file_verifies(default_design_table, tmp_path):
    single = DesignTable(default_design_table.designs[:1], load_vehicle(), load_settings(),
                         provenance(command=["test"]))
    path = tmp_path / "one.yaml"
    save_design_table(path, single, single=True)
    assert "design:" in path.read_text() and "designs:" not in path.read_text()
    assert cli.main(["verify", str(path)]) == 0


@pytest.mark.parametrize("edit,message", [
    (lambda raw: raw.pop("designs"), "expected exactly one of 'designs'"),
    (lambda raw: raw.update(schema_version=99), "schema_version"),
    (lambda raw: raw["designs"][0].update(k_m=[1.0, 2.0]), "k_m must be a list of 4"),
    (lambda raw: raw["designs"][0].pop("speed_mps"), "missing key 'speed_mps'"),
    (lambda raw: raw["designs"][0].update(speed_mps="fast"), "speed_mps = 'fast'"),
    (lambda raw: raw["vehicle"].update(mass_kg=-1.0), "mass_kg"),
    (lambda raw: raw.update(extra=1), "unknown top-level key 'extra'"),
])
def test_malformed_design_file_exits_2_naming_the_problem(table_file, tmp_path, capsys, edit,
                                                          message):
    assert cli.main(["verify", str(_tampered(table_file, tmp_path, edit))]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_unreadable_design_file_exits_2(tmp_path, capsys):
    assert cli.main(["verify", str(tmp_path / "missing.yaml")]) == 2
    assert "cannot read file" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("designs: [unclosed\n")
    assert cli.main(["verify", str(bad)]) == 2
    assert "not valid YAML" in capsys.readouterr().err


def _small_conditions(tmp_path):
    table = dataclasses.asdict(load_conditions())
    table["presets"] = [{"name": "two", "labels": ["heavy_rain", "snow"], "frames_per_class": 1}]
    path = tmp_path / "conditions.yaml"
    path.write_text(yaml.safe_dump(table))
    return path


def test_synthesize_json_then_verify_the_written_table(tmp_path, capsys):
    out_file = tmp_path / "out" / "designs.yaml"
    code = cli.main(["synthesize", "--conditions", str(_small_conditions(tmp_path)),
                     "--out", str(out_file), "--json"])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert [d["labels"] for d in report["designs"]] == [["heavy_rain"], ["heavy_rain", "snow"],
                                                        ["snow"]]
    for d in report["designs"]:
        assert d["stiffness_interval"] == [d["stiffness_lo_n_per_rad"],
                                           d["stiffness_hi_n_per_rad"]]
        assert d["speed_mps"] > 0 and len(d["k_m"]) == 4
    assert cli.main(["verify", str(out_file)]) == 0


def test_synthesize_prints_a_readable_table_without_writing(tmp_path, capsys):
    assert cli.main(["synthesize", "--conditions", str(_small_conditions(tmp_path))]) == 0
    out = capsys.readouterr().out
    assert "speed (m/s)" in out and "heavy_rain+snow" in out
    assert list(tmp_path.iterdir()) == [tmp_path / "conditions.yaml"]


def test_synthesize_with_a_bad_vehicle_file_exits_2(tmp_path, capsys):
    bad = tmp_path / "vehicle.yaml"
    bad.write_text("mass_kg: 1573.0\n")
    assert cli.main(["synthesize", "--vehicle", str(bad)]) == 2
    assert "missing key" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["synthesize", "verify"])
def test_help_exits_0(command):
    out = subprocess.run([sys.executable, "-m", "drake_cert.cli", command, "--help"],
                         capture_output=True, text=True)
    assert out.returncode == 0 and "--json" in out.stdout


def _shipped(name):
    from drake_cert.config import default_path

    return str(default_path(name))


def test_self_consistently_raised_speed_is_rejected_against_the_shipped_settings(
        table_file, tmp_path, capsys):
    def edit(raw):  # raise the friction fraction and the speed together, as a forger would
        raw["settings"]["synthesis"]["lateral_accel_fraction"] = 0.99
        raw["designs"][0]["speed_mps"] *= 1.3

    tampered = str(_tampered(table_file, tmp_path, edit, ("heavy_rain",)))
    assert cli.main(["verify", tampered, "--settings", _shipped("settings.yaml"),
                     "--vehicle", _shipped("vehicle.yaml"),
                     "--conditions", _shipped("conditions.yaml")]) == 1
    err = capsys.readouterr().err
    assert "fails reference_inputs" in err
    assert "settings.synthesis.lateral_accel_fraction = 0.99" in err


def test_verify_against_reference_files_passes_an_untouched_table(table_file, capsys):
    assert cli.main(["verify", str(table_file), "--settings", _shipped("settings.yaml"),
                     "--vehicle", _shipped("vehicle.yaml"),
                     "--conditions", _shipped("conditions.yaml")]) == 0
    err = capsys.readouterr().err
    assert "checked against the reference vehicle, settings, conditions" in err


def test_verify_without_reference_files_says_it_used_the_embedded_inputs(table_file, capsys):
    assert cli.main(["verify", str(table_file)]) == 0
    assert "own embedded vehicle, settings and conditions" in capsys.readouterr().err


def test_changed_vehicle_is_named_when_verified_against_the_shipped_vehicle(
        table_file, tmp_path, capsys):
    def edit(raw):
        raw["vehicle"]["mass_kg"] = 1200.0

    tampered = str(_tampered(table_file, tmp_path, edit, ("snow",)))
    assert cli.main(["verify", tampered, "--vehicle", _shipped("vehicle.yaml")]) == 1
    assert "vehicle.mass_kg = 1200.0 differs from the reference 1573.0" in capsys.readouterr().err


def test_synthesize_exits_1_naming_the_binding_condition_when_no_design_is_safe(
        tmp_path, capsys):
    vehicle = dataclasses.asdict(load_vehicle())
    vehicle["lf_m"] *= 1000.0  # millimetres typed as metres
    vehicle["lr_m"] *= 1000.0
    path = tmp_path / "vehicle_mm.yaml"
    path.write_text(yaml.safe_dump(vehicle))
    out_file = tmp_path / "designs.yaml"
    code = cli.main(["synthesize", "--vehicle", str(path), "--conditions",
                     str(_small_conditions(tmp_path)), "--out", str(out_file)])
    err = capsys.readouterr().err
    assert code == 1 and "no design has a safe speed; binding condition: gain_lmi" in err
    assert not out_file.exists()


def test_each_design_records_the_law_it_certifies_and_a_mismatch_fails(table_file, tmp_path,
                                                                       capsys):
    loaded = load_design_file(table_file)
    assert {d.certified_law for d in loaded.designs} == {load_settings().controller.adaptation_law}

    def edit(raw):
        raw["designs"][0]["certified_law"] = "gradient"

    assert cli.main(["verify", str(_tampered(table_file, tmp_path, edit, ("snow",)))]) == 1
    assert "certified for the gradient law" in capsys.readouterr().err


def test_a_schema_1_design_file_is_refused_with_a_clear_message(table_file, tmp_path, capsys):
    def edit(raw):
        raw["schema_version"] = 1

    assert cli.main(["verify", str(_tampered(table_file, tmp_path, edit))]) == 2
    assert "old slip-angle grip rule" in capsys.readouterr().err
