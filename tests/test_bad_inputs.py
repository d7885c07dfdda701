"""Every bad input gets one readable line and exit code 2 from the CLI (or a typed exception
from the API) and leaves no partial file (DESIGN 1).

In-process ``cli.main`` calls with ``capsys``; a subprocess only where the test needs a fresh
interpreter (is torch imported by ``--help``?) or a signal (Ctrl-C while torch is imported).
"""

import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from design_fixtures import lqr_design

from drake_cert import cli
from drake_cert.certification.classifier import (
    SmoothedClassifier,
    check_enough_samples,
    min_certifying_samples,
)
from drake_cert.certification.statistics import conformal_beta, min_calibration_frames
from drake_cert.config import load_settings, load_vehicle
from drake_cert.errors import CertificationError, ConfigError
from drake_cert.io import provenance
from drake_cert.perception.models import (
    SmallResNet,
    StiffnessRegressor,
    file_sha256,
    load_model_file,
    model_path,
    save_model,
)
from drake_cert.synthesis.design_io import DesignTable, save_design_table
from drake_cert.synthesis.table import synthesize_design
from drake_cert.systems.closed_loop import EpisodeOptions, simulate
from drake_cert.systems.road import Road

ROOT = Path(__file__).resolve().parents[1]
VEHICLE = load_vehicle()
SETTINGS = load_settings()
DESIGN = lqr_design(VEHICLE, 40_000.0, 60_000.0, 12.0, labels=("heavy_rain",))
CERTIFY = ["certify", "--preset", "rtk-like", "--frames", "3", "--n0", "10", "--n", "200",
           "--batch-size", "100", "--compile", "off", "--attack-steps", "2"]


def one_line_exit_2(capsys, argv) -> str:
    """Run the CLI; assert exit code 2 and exactly one stderr line; return that line."""
    code = cli.main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.fixture(scope="module")
def designs_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("designs") / "designs.yaml"
    save_design_table(path, DesignTable([DESIGN], VEHICLE, SETTINGS, provenance(0)))
    return str(path)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """Untrained 16x16 rtk-like classifier and regressor files (sigma 0.25)."""
    root = tmp_path_factory.mktemp("models")
    torch.manual_seed(0)
    classifier = SmallResNet(3, width=4).eval()
    cpath = save_model(classifier, model_path("rtk-like", "classify", 0.25, root),
                       meta={"image_size": 16})
    head = torch.nn.Linear(16, 1)
    save_model(StiffnessRegressor(classifier.backbone, head),
               model_path("rtk-like", "regress", 0.25, root),
               meta={"image_size": 16, "classifier_file": cpath.name,
                     "classifier_sha256": file_sha256(cpath)})
    return str(root)


@pytest.fixture
def regular_file(tmp_path) -> Path:
    path = tmp_path / "a_file"
    path.write_text("not a folder")
    return path


# --------------------------------------------------------------------------- output paths

@pytest.mark.parametrize("option, name, message", [
    ("--plot", "sub/e1.png", "is a file, not a folder"),
    ("--out", "sub/tape.csv", "is a file, not a folder"),
    ("--out", "tape.txt", "written as .csv or .npz"),
])
def test_simulate_refuses_an_unwritable_output_before_simulating(
        designs_file, regular_file, capsys, option, name, message):
    target = regular_file / name if name.startswith("sub/") else regular_file.parent / name
    start = time.perf_counter()
    err = one_line_exit_2(capsys, ["simulate", "--designs", designs_file, option, str(target)])
    assert message in err and option in err
    assert time.perf_counter() - start < 5  # failed before the episode, not after it
    assert not target.exists()


def test_simulate_refuses_a_folder_as_output(designs_file, tmp_path, capsys):
    folder = tmp_path / "tape.csv"
    folder.mkdir()
    assert "is a folder" in one_line_exit_2(
        capsys, ["simulate", "--designs", designs_file, "--out", str(folder)])


@pytest.mark.parametrize("option", ["--out", "--export"])
def test_generate_refuses_an_unwritable_output_before_rendering(regular_file, capsys, option):
    target = regular_file / ("grid.png" if option == "--out" else "frames")
    err = one_line_exit_2(capsys, ["generate", "--preset", "rtk-like", "--per-class", "2",
                                   "--frames-per-class", "2", option, str(target)])
    assert "is a file, not a folder" in err and option in err
    assert regular_file.read_text() == "not a folder"


@pytest.mark.skipif(not Path("/proc/self").is_dir(),
                    reason="needs Linux's /proc, a folder that refuses new files even to root; "
                           "other systems have no such folder to test with")
def test_reproduce_refuses_a_folder_it_cannot_write_in_before_any_work(capsys):
    # /proc refuses new files even to root, who passes every permission-bit check.
    start = time.perf_counter()
    err = one_line_exit_2(capsys, ["reproduce", "--quick", "--out", "/proc/drake-cert-results"])
    assert "--out" in err and "is not writable" in err
    assert time.perf_counter() - start < 5  # before the calibration, not after it


def test_synthesize_out_under_a_regular_file_fails_before_synthesis(regular_file, capsys):
    start = time.perf_counter()
    err = one_line_exit_2(capsys, ["synthesize", "--out", str(regular_file / "d.yaml")])
    assert "is a file, not a folder" in err and "File exists" not in err
    assert time.perf_counter() - start < 5


# --------------------------------------------------------------------------- simulate numbers

@pytest.mark.parametrize("argv, message", [
    (["--speed", "1e6"], "outside the design speed range [5, 30] m/s"),
    (["--speed", "2"], "outside the design speed range"),
    (["--speed", "nan"], "--speed nan must be a positive number"),
    (["--friction", "3"], "--friction 3 is outside (0, 2]"),
    (["--friction", "-0.5"], "--friction -0.5 must be a positive number"),
    (["--radius", "2"], "--radius 2 m must exceed 5 m"),
    (["--radius", "50000"], "implausibly large for a road curve, above 10000 m (mm? write 50"),
    (["--duration", "1e9"], "exceeds 3600 s"),
    (["--initial-offset", "7"], "|e1(0)| < 5 m"),
    (["--labels", "heavy_rain+"], "label range 'heavy_rain+'"),
    (["--labels", "sunny+heavy_rain"], "known: heavy_rain"),
])
def test_simulate_numbers_out_of_range_give_one_line(designs_file, capsys, argv, message):
    err = one_line_exit_2(capsys, ["simulate", "--designs", designs_file, *argv])
    assert message in err


def test_simulate_api_rejects_an_initial_state_of_the_wrong_shape():
    road = Road.straight()
    for bad in ([0.0, 0.0, 0.0], np.zeros((2, 2)), [0.0, math.nan, 0.0, 0.0], "abcd"):
        with pytest.raises(ConfigError, match="initial_state"):
            simulate(vehicle=VEHICLE, design=DESIGN, settings=SETTINGS, stiffness_n_per_rad=45e3,
                     friction_mu=0.5, speed_mps=12.0, road=road,
                     episode=EpisodeOptions(t_final_s=0.1, initial_state=bad))


# --------------------------------------------------------------------------- synthesis inputs

@pytest.mark.parametrize("interval, mu, message", [
    ((60_000.0, 40_000.0), 0.5, "0 < C_lo <= C_hi"),  # reversed
    ((0.0, 40_000.0), 0.5, "0 < C_lo <= C_hi"),
    ((-1.0, 40_000.0), 0.5, "0 < C_lo <= C_hi"),
    ((math.nan, 40_000.0), 0.5, "0 < C_lo <= C_hi"),
    ((40_000.0,), 0.5, "two numbers"),
    ((40_000.0, 60_000.0), 0.0, "friction_mu_lo"),
    ((40_000.0, 60_000.0), math.nan, "friction_mu_lo"),
    ((40_000.0, 60_000.0), 5.0, "friction_mu_lo"),
])
def test_synthesize_design_rejects_bad_intervals_and_friction(interval, mu, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        synthesize_design(VEHICLE, interval, mu, SETTINGS)


def test_steering_limit_at_or_above_half_pi_is_a_config_error(tmp_path, capsys):
    text = (ROOT / "drake_cert/data/vehicle.yaml").read_text()
    bad = tmp_path / "vehicle.yaml"
    lines = [("steering_limit_rad: 1.5708" if line.startswith("steering_limit_rad:") else line)
             for line in text.splitlines()]
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match="below pi/2"):
        load_vehicle(bad)
    assert "below pi/2" in one_line_exit_2(capsys, ["synthesize", "--vehicle", str(bad)])


def test_a_sample_period_of_one_second_is_refused_naming_the_unit(tmp_path, capsys):
    """controller.sample_period_s: 1.0 (1 s written for 1 ms) would synthesize filter gains
    hundreds of times past k w_max T_s <= 1 (docs/design.md 5.3a)."""
    text = (ROOT / "drake_cert/data/settings.yaml").read_text()
    bad = tmp_path / "settings.yaml"
    bad.write_text(text.replace("sample_period_s: 0.001 ", "sample_period_s: 1.0   "))
    assert "sample_period_s: 1.0" in bad.read_text()
    with pytest.raises(ConfigError, match="1 ms is 0.001"):
        load_settings(bad)
    line = one_line_exit_2(capsys, ["synthesize", "--settings", str(bad)])
    assert "controller.sample_period_s = 1 s" in line



def test_a_named_pipe_as_the_vehicle_file_is_refused_without_waiting(tmp_path, capsys):
    import os

    pipe = tmp_path / "vehicle.yaml"
    os.mkfifo(pipe)  # reading it would wait for a writer forever
    err = one_line_exit_2(capsys, ["synthesize", "--vehicle", str(pipe)])
    assert "a named pipe or socket, not a file" in err
    assert "a folder, not a file" in one_line_exit_2(capsys, ["verify", str(tmp_path)])


@pytest.mark.parametrize("argv", [["synthesize", "--vehicle", ""],
                                  ["verify", "designs.yaml", "--vehicle", " "],
                                  ["drive", "--scenario", ""], ["drive", "--designs", ""],
                                  [*CERTIFY, "--sigma", "1", "--models", ""]])
def test_an_empty_option_value_is_refused_not_taken_for_the_default(argv, capsys):
    """``--vehicle "$CAR"`` with CAR unset must not synthesize the shipped car's table."""
    err = one_line_exit_2(capsys, argv)
    assert f"argument {argv[-2]}: empty value" in err


def test_drive_compare_with_a_pipeline_is_refused(capsys):
    err = one_line_exit_2(capsys, ["drive", "--compare", "--pipeline", "base"])
    assert "--compare drives both pipelines" in err


def test_train_models_naming_a_file_is_refused_before_any_training(regular_file, capsys):
    start = time.perf_counter()
    err = one_line_exit_2(capsys, ["train", "--models", str(regular_file), "--preset",
                                   "rtk-like", "--sigma", "1"])
    assert "is a file; give a folder" in err
    assert time.perf_counter() - start < 10.0  # refused at the check, not after an epoch


# --------------------------------------------------------------------------- certify inputs

def test_certify_rejects_a_frame_size_other_than_the_models(models, capsys):
    err = one_line_exit_2(capsys, [*CERTIFY, "--models", models, "--sigma", "0.25",
                                   "--size", "32"])
    assert "trained on 16x16 frames" in err
    smooth = SmoothedClassifier(load_model_file(model_path("rtk-like", "classify", 0.25,
                                                           models)), 3, 0.25)
    with pytest.raises(CertificationError, match="frame is 32x32 pixels but the model was "
                                                 "trained on 16x16"):
        smooth.certify(torch.full((3, 32, 32), 0.5), 10, 200, 0.001, 100, seed=0)


def test_certify_regress_with_too_few_calibration_frames_says_how_many(models, capsys):
    err = one_line_exit_2(capsys, [*CERTIFY, "--models", models, "--sigma", "0.25",
                                   "--task", "regress", "--calibration-per-class", "3"])
    assert "needs at least 99 calibration frames per label" in err


def test_min_calibration_frames_is_the_smallest_count_with_a_finite_beta():
    for alpha_c in (0.01, 0.05, 0.1, 0.2, 0.001):
        need = min_calibration_frames(alpha_c)
        assert math.isfinite(conformal_beta(np.ones(need), np.zeros(need), alpha_c)[0])
        assert conformal_beta(np.ones(need - 1), np.zeros(need - 1), alpha_c)[0] == math.inf


@pytest.mark.parametrize("alpha, classes", [(0.25, 2), (0.5, 4), (1 / 64, 2), (0.125, 1),
                                            (0.001, 3), (0.01, 3)])
def test_check_enough_samples_names_the_smallest_n_that_works(alpha, classes):
    need = min_certifying_samples(alpha, classes)
    check_enough_samples(need, alpha, classes)  # the n the message names certifies
    with pytest.raises(CertificationError, match=f"use n >= {need}$"):
        check_enough_samples(need - 1, alpha, classes)


def test_certify_frames_dir_that_does_not_exist(models, tmp_path, capsys):
    err = one_line_exit_2(capsys, [*CERTIFY, "--models", models, "--sigma", "0.25",
                                   "--frames-dir", str(tmp_path / "missing")])
    assert "does not exist" in err


def test_a_malformed_stiffness_csv_is_a_config_error(tmp_path, capsys):
    from PIL import Image

    from drake_cert.perception.datasets import load_image_folder

    (tmp_path / "sand").mkdir()
    Image.new("RGB", (8, 8)).save(tmp_path / "sand" / "a.png")
    (tmp_path / "stiffness.csv").write_text("file,label,stiffness_n_per_rad\n"
                                            "sand/a.png,sand,grippy\n")
    with pytest.raises(ConfigError, match="stiffness.csv:2"):
        load_image_folder(tmp_path, preset="rtk-like")
    (tmp_path / "stiffness.csv").write_text("file,label,stiffness_n_per_rad\n"
                                            "sand/a.png,sand,35\n")  # kN/rad
    with pytest.raises(ConfigError, match=r"stiffness.csv:2: stiffness_n_per_rad = 35 N/rad is "
                                          r"implausibly small .* \(kN/rad\? write 35000\)"):
        load_image_folder(tmp_path, preset="rtk-like")


# --------------------------------------------------------------------------- start-up

def _fresh_python(code: str, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=ROOT, timeout=60, **kwargs)


def test_certify_help_does_not_import_torch():
    out = _fresh_python("import sys\nfrom drake_cert import cli\ntry:\n"
                        "    cli.main(['certify', '--help'])\nexcept SystemExit:\n    pass\n"
                        "print('TORCH', 'torch' in sys.modules)")
    assert "--frames-dir" in out.stdout and "TORCH False" in out.stdout


def test_ctrl_c_while_a_command_imports_torch_prints_one_line(models):
    proc = subprocess.Popen([sys.executable, "-m", "drake_cert.cli", *CERTIFY, "--models",
                             models, "--sigma", "0.25"], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    time.sleep(0.6)  # inside main; torch's import takes seconds on this machine
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert err.strip().splitlines() == ["drake-cert certify: interrupted"]


def test_version_prints_the_package_version(capsys):
    import drake_cert

    with pytest.raises(SystemExit) as exit_info:
        cli.main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"drake-cert {drake_cert.__version__}"



# --------------------------------------------------------------------------- units and files

def _vehicle_with(tmp_path, old: str, new: str) -> str:
    text = (ROOT / "drake_cert/data/vehicle.yaml").read_text()
    assert old in text
    path = tmp_path / "vehicle.yaml"
    path.write_text(text.replace(old, new))
    return str(path)


def test_a_vehicle_mass_in_tonnes_is_one_line(tmp_path, capsys):
    err = one_line_exit_2(capsys, ["synthesize", "--vehicle",
                                   _vehicle_with(tmp_path, "mass_kg: 1573.0", "mass_kg: 1.573")])
    assert "mass_kg = 1.573 kg is implausibly small for a vehicle mass" in err
    assert "(tonnes? write 1573)" in err


def test_a_conditions_file_in_kn_per_rad_is_one_line(tmp_path, capsys):
    text = (ROOT / "drake_cert/data/conditions.yaml").read_text()
    path = tmp_path / "conditions.yaml"
    path.write_text(text.replace("000.0", ".0"))  # every stiffness in kN/rad
    err = one_line_exit_2(capsys, ["synthesize", "--conditions", str(path)])
    assert "stiffness_lo_n_per_rad = 80 N/rad is implausibly small" in err
    assert "(kN/rad? write 80000)" in err


def test_simulate_stiffness_in_kn_per_rad_is_one_line(designs_file, capsys):
    err = one_line_exit_2(capsys, ["simulate", "--designs", designs_file, "--stiffness", "100"])
    assert err == ("drake-cert simulate: error: --stiffness 100 N/rad is implausibly small for a "
                   "cornering stiffness per tire, below 1000 N/rad (kN/rad? write 100000)")


@pytest.mark.parametrize("command", [["synthesize", "--vehicle"], ["drive", "--scenario"],
                                     ["drive", "--vehicle"]])
def test_a_binary_file_given_as_yaml_is_one_line(tmp_path, capsys, command):
    path = tmp_path / "photo.yaml"
    path.write_bytes(bytes(range(256)) * 4)
    err = one_line_exit_2(capsys, [*command, str(path)])
    assert f"{path}: not a text file (byte 0x80 at offset 128 is not UTF-8)" in err


def test_a_key_given_twice_is_one_line_naming_both_lines(tmp_path, capsys):
    """PyYAML keeps the last of two equal keys silently; an input file may not."""
    path = _vehicle_with(tmp_path, "mass_kg: 1573.0", "mass_kg: 1573.0\nmass_kg: 2000.0")
    err = one_line_exit_2(capsys, ["synthesize", "--vehicle", path])
    assert "key 'mass_kg' given twice (lines" in err and path in err


def test_a_number_with_an_exponent_is_a_number(tmp_path, capsys):
    """``1.0e12`` is a float (YAML 1.2), so the answer is about its size, not its type."""
    err = one_line_exit_2(capsys, ["synthesize", "--vehicle",
                                   _vehicle_with(tmp_path, "mass_kg: 1573.0", "mass_kg: 1.0e12")])
    assert "mass_kg = 1e+12 kg is implausibly large" in err, err


@pytest.mark.parametrize("command", [["synthesize", "--vehicle"], ["verify"]])
def test_an_endless_file_is_refused_unread(capsys, command):
    err = one_line_exit_2(capsys, [*command, "/dev/zero"])
    assert "/dev/zero: larger than 16 MiB" in err


def test_a_scenario_frame_size_of_100000_says_how_much_memory_it_would_need(tmp_path, capsys):
    import yaml

    data = yaml.safe_load((ROOT / "drake_cert/data/scenarios/dry_to_snow.yaml").read_text())
    data["camera"]["frame_size"] = 100_000
    path = tmp_path / "huge.yaml"
    path.write_text(yaml.safe_dump(data))
    err = one_line_exit_2(capsys, ["drive", "--scenario", str(path)])
    assert "camera.frame_size = 100000 px: one 100000x100000 RGB frame takes 112 GiB" in err
    assert "the limit is 1024 px" in err


@pytest.mark.parametrize("command", [[*CERTIFY, "--sigma", "0.25"],
                                     ["generate", "--preset", "rtk-like", "--out", "x.png"]])
def test_a_frame_size_of_100000_is_one_line_before_any_model_or_frame(command, capsys):
    err = one_line_exit_2(capsys, [*command, "--size", "100000"])
    assert "--size 100000 px: one 100000x100000 RGB frame takes 112 GiB in float32" in err


@pytest.mark.parametrize("command", sorted(cli.COMMANDS))
def test_argument_errors_are_one_line_for_every_command(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main([command, "--no-such-option"])
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and len(err.splitlines()) == 1, err
    # a command with required options names those first, else the unknown option
    assert err.startswith("drake-cert") and ": error: " in err and err.endswith("--help)"), err
    assert "--no-such-option" in err or "are required" in err, err


def test_certify_n_0_is_one_line_and_help_still_works(capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main([*CERTIFY, "--sigma", "0.25", "--n", "0"])
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2
    assert err == ("drake-cert certify: error: argument --n: 0 must be a positive integer "
                   "(see drake-cert certify --help)")
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["certify", "--help"])
    assert exit_info.value.code == 0 and "--frames-dir" in capsys.readouterr().out


CONFIG_ERROR_IMPORTS = """
import sys
from drake_cert import cli
HEAVY = ("pydrake", "cvxpy", "torch")
def loaded():
    return [m for m in HEAVY if m in sys.modules]
for argv in {light!r}:
    assert cli.main(argv) == 2
    print("LIGHT", argv[0], loaded())
for argv in {scenario!r}:
    assert cli.main(argv) == 2
    print("SCENARIO", argv[0], loaded())
"""


def test_a_bad_file_is_answered_before_pydrake_cvxpy_or_torch_are_imported(tmp_path,
                                                                           designs_file):
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe\x00")
    tonnes = _vehicle_with(tmp_path, "mass_kg: 1573.0", "mass_kg: 1.573")
    shipped = (ROOT / "drake_cert/data/scenarios/dry_to_snow.yaml").read_text()
    huge = tmp_path / "huge.yaml"
    huge.write_text(shipped.replace("frame_size: 64 ", "frame_size: 100000 "))
    motion = tmp_path / "motion.yaml"  # a motion key, then a controller key, out of range
    motion.write_text(shipped.replace("max_accel_mps2: 2.0 ", "max_accel_mps2: -2.0 "))
    controller = tmp_path / "controller.yaml"
    controller.write_text(shipped.replace("law: piecewise_constant ", "law: gradient_descent "))
    assert huge.read_text() != shipped != motion.read_text() != controller.read_text()
    light = [["synthesize", "--vehicle", tonnes], ["synthesize", "--vehicle", str(binary)],
             ["drive", "--vehicle", tonnes],
             ["simulate", "--designs", designs_file, "--stiffness", "100"],
             ["certify", "--preset", "rtk-like", "--sigma", "0.25", "--size", "100000"],
             ["generate", "--preset", "rtk-like", "--out", "x.png", "--size", "100000"]]
    scenarios = [["drive", "--scenario", str(path)] for path in (huge, motion, controller)]
    out = _fresh_python(CONFIG_ERROR_IMPORTS.format(light=light, scenario=scenarios))
    lines = out.stdout.splitlines()
    assert out.returncode == 0, out.stderr
    assert lines[:len(light)] == [f"LIGHT {argv[0]} []" for argv in light], out.stdout
    # a scenario's schema holds Drake's SimulatorConfig: pydrake, but neither cvxpy nor torch
    assert lines[len(light):] == ["SCENARIO drive ['pydrake']"] * 3, out.stdout
