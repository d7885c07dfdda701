"""``drake-cert synthesize`` / ``verify`` (DESIGN 5.5): designs pass, tampered ones fail, and a
table that lacks a label range's design fails."""

import dataclasses
import json
import subprocess
import sys

import pytest
import yaml

from drake_cert import cli
from drake_cert.config import load_conditions, load_settings, load_vehicle
from drake_cert.errors import ConfigError
from drake_cert.io import provenance
from drake_cert.synthesis.design import ControllerDesign
from drake_cert.synthesis.design_io import DesignTable, load_design_file, save_design_table
from drake_cert.synthesis.table import design_label_ranges, synthesize_design
from drake_cert.synthesis.verify import completeness_check, verify_design, verify_design_table


@pytest.fixture(scope="module")
def table_file(certified_design_table, tmp_path_factory):
    """The shipped table with its switching certificates, saved as synthesize --out saves it."""
    path = tmp_path_factory.mktemp("designs") / "designs.yaml"
    save_design_table(path, certified_design_table)
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
    assert yaml.safe_load(table_file.read_text())["schema_version"] == 3
    assert cli.main(["verify", str(table_file)]) == 0
    out = capsys.readouterr()
    assert "20 claims hold: 20 safe speeds, 0 ranges certified to have none" in out.err
    assert "l1_condition=" in out.out and "steady_state_lane_margin_m=" in out.out
    # no reference files: checked against the file's own inputs, completeness against the
    # conditions it embeds (a table missing a label range does not pass as a whole)
    assert "own embedded vehicle, settings and conditions" in out.err
    assert "complete: a design for each of the 20 label ranges of the embedded conditions" \
        in out.err


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no NaN arithmetic on the way
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
    failed = {f["condition"] for d in report["designs"] for f in d["reasons"]}
    assert report["ok"] is False and report["verdict"] == "fail" and "grip" in failed
    assert report["designs"][0]["holds"] is False and report["designs"][0]["speed_mps"] == 22.0
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


def _references():
    return ["--settings", _shipped("settings.yaml"), "--vehicle", _shipped("vehicle.yaml"),
            "--conditions", _shipped("conditions.yaml")]


def test_verify_against_reference_files_passes_an_untouched_table_and_reports_json(
        default_design_table, table_file, capsys):
    assert cli.main(["verify", str(table_file), "--json", *_references()]) == 0
    out = capsys.readouterr()
    assert "checked against the reference vehicle, settings, conditions" in out.err
    assert ("20 claims hold: 20 safe speeds, 0 ranges certified to have none; complete: a "
            "design for each of the 20 label ranges of the "
            "reference conditions") in out.err
    report = json.loads(out.out)
    assert report["verdict"] == "pass" and report["ok"] is True
    assert report["completeness"] == {"checked": True, "against": "reference conditions",
                                      "label_ranges": 20, "holds": True, "missing": [],
                                      "failures": []}
    assert report["switching"] == {"present": True, "holds": True, "failures": []}
    for entry, design in zip(report["designs"], default_design_table.designs, strict=True):
        assert entry["holds"] is True and entry["reasons"] == []
        assert entry["label_range"] == "+".join(design.labels)
        assert entry["interval_n_per_rad"] == list(design.interval)
        assert entry["speed_mps"] == design.speed_mps


def test_the_synthesized_table_without_the_snow_design_lacks_the_ranges_that_hold_snow(
        default_design_table):
    designs = [d for d in default_design_table.designs
               if d.labels not in (["snow"], ["heavy_rain", "snow"])]
    ranges, missing, failures, notes = completeness_check(designs, load_conditions())
    assert ranges == 20 and notes == []
    assert [(m.labels, m.presets) for m in missing] == [(["snow"], ["robotcar-like", "weather"]),
                                                        (["heavy_rain", "snow"], ["weather"])]
    assert [m for _, m in failures] == [
        "no design for label range snow (presets robotcar-like, weather)",
        "no design for label range heavy_rain+snow (preset weather)"]


def test_plain_verify_of_a_table_missing_one_label_range_fails(table_file, tmp_path, capsys):
    """Without reference files, a table is checked complete against the conditions it embeds:
    19 designs that all hold do not make a table that holds."""
    def drop(raw):
        raw["designs"] = [d for d in raw["designs"] if d["labels"] != ["heavy_rain", "snow"]]

    path = str(_tampered(table_file, tmp_path, drop))
    assert cli.main(["verify", path]) == 1
    err = capsys.readouterr().err
    assert "incomplete table: no design for label range heavy_rain+snow" in err
    assert "--no-complete verifies the designs it holds alone" in err
    assert "claims hold" not in err


def test_a_cut_table_fails_completeness_unless_told_not_to_check_it(table_file, tmp_path,
                                                                     capsys):
    path = str(_tampered(table_file, tmp_path, lambda raw: None, ("snow",)))
    assert cli.main(["verify", path, "--conditions", _shipped("conditions.yaml")]) == 1
    err = capsys.readouterr().err
    assert err.count("incomplete table: no design for label range") == 19
    assert ("drake-cert verify: incomplete table: no design for label range heavy_rain+snow "
            "(preset weather)\n") in err
    assert ("drake-cert verify: incomplete table: no design for label range sunny "
            "(presets carla-like, robotcar-like, weather)\n") in err
    assert "claims hold" not in err
    assert cli.main(["verify", path, "--conditions", _shipped("conditions.yaml"),
                     "--no-complete"]) == 0
    assert "1 claim holds: 1 safe speed, 0 ranges certified to have none\n" in \
        capsys.readouterr().err
    assert cli.main(["verify", path, "--complete"]) == 1  # against the embedded conditions
    assert capsys.readouterr().err.count("incomplete table: no design for label range") == 19


def test_complete_without_any_conditions_is_one_line_exit_2(default_design_table, tmp_path,
                                                            capsys):
    single = DesignTable(default_design_table.designs[:1], load_vehicle(), load_settings(),
                         provenance(command=["test"]))
    path = tmp_path / "one.yaml"
    save_design_table(path, single, single=True)
    assert cli.main(["verify", str(path), "--complete"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "embeds no conditions" in err
    with pytest.raises(ConfigError, match="embeds no conditions"):
        verify_design_table(path, complete=True)


def _labelled(*labels) -> ControllerDesign:
    return ControllerDesign(list(labels), 1.0, 2.0, 1.5, 0.5, [0.0] * 4, 0.0, 1.0, 0.0, "grip")


def test_completeness_counts_every_contiguous_label_range_of_every_preset_once():
    conditions = load_conditions()
    full = [_labelled(*r) for r in design_label_ranges(conditions)]
    assert completeness_check(full, conditions) == (20, [], [], [])
    # what is missing is named with the presets that define it; a range's second design and
    # a design for no range (sunny+snow skips rain) are found; a regression design is ignored
    designs = [d for d in full if d.labels != ["sunny", "rain"]]
    designs += [_labelled("snow"), _labelled("sunny", "snow"), _labelled()]
    ranges, missing, failures, notes = completeness_check(designs, conditions)
    assert ranges == 20
    assert [(m.labels, m.presets) for m in missing] == [(["sunny", "rain"], ["robotcar-like"])]
    assert [c for c, _ in failures] == ["completeness", "completeness"]
    assert "no design for label range sunny+rain (preset robotcar-like)" in failures[0][1]
    assert failures[1][1].startswith("2 designs for label range snow (designs ")
    assert len(notes) == 1 and "sunny+snow" in notes[0]


def test_changed_vehicle_is_named_when_verified_against_the_shipped_vehicle(
        table_file, tmp_path, capsys):
    def edit(raw):
        raw["vehicle"]["mass_kg"] = 1200.0

    tampered = str(_tampered(table_file, tmp_path, edit, ("snow",)))
    assert cli.main(["verify", tampered, "--vehicle", _shipped("vehicle.yaml")]) == 1
    assert "vehicle.mass_kg = 1200.0 differs from the reference 1573.0" in capsys.readouterr().err


def test_synthesize_exits_1_naming_the_binding_condition_when_no_design_is_safe(
        tmp_path, capsys):
    settings = dataclasses.asdict(load_settings())
    settings["synthesis"]["decay_rate"] = 50.0  # 1/s: no gain of the steering reaches it
    path = tmp_path / "settings_fast_decay.yaml"
    path.write_text(yaml.safe_dump(settings))
    out_file = tmp_path / "designs.yaml"
    code = cli.main(["synthesize", "--settings", str(path), "--conditions",
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


def test_a_schema_2_file_reads_its_offset_margin_as_the_lane_margin_left(table_file, tmp_path):
    def edit(raw):  # as the previous version wrote it
        raw["schema_version"] = 2
        for d in raw["designs"]:
            margins = d["margins"]
            if "steady_state_lane_margin_m" in margins:
                margins["steady_state_offset_m"] = margins.pop("steady_state_lane_margin_m")

    old = load_design_file(_tampered(table_file, tmp_path, edit))
    assert old.designs == load_design_file(table_file).designs
    lane_margin = load_vehicle().lane_margin_m
    kept = [d.margins["steady_state_lane_margin_m"] for d in old.designs if d.margins]
    assert kept and all(0.0 < m <= lane_margin for m in kept)


def test_the_old_margin_name_in_a_schema_3_file_is_one_line_exit_2(table_file, tmp_path,
                                                                  capsys):
    def edit(raw):
        margins = raw["designs"][0]["margins"]
        margins["steady_state_offset_m"] = margins.pop("steady_state_lane_margin_m")

    assert cli.main(["verify", str(_tampered(table_file, tmp_path, edit, ("snow",)))]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert ("margins: unknown key 'steady_state_offset_m' (schema 3 calls it "
            "'steady_state_lane_margin_m')") in err


def test_the_summary_separates_safe_speeds_from_ranges_certified_to_have_none():
    """A design with no safe speed is a claim that holds ("the car stops there"), but a reader
    must not take it for a usable design: the summary counts the two kinds apart."""
    from types import SimpleNamespace

    from drake_cert.cli.verify import claims_summary

    designs = [SimpleNamespace(labels=["sunny"], speed_mps=19.36),
               SimpleNamespace(labels=["sunny", "rain", "snow"], speed_mps=0.0)]
    text = claims_summary(designs)
    assert text.startswith("2 claims hold: 1 safe speed, 1 range certified to have none "
                           "(sunny+rain+snow: the car stops there")
