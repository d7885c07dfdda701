"""`drake-cert certify`: the numbers it reports, and one line + exit 2 for bad inputs.

Uses small (untrained, seeded) SmallResNet files written to a temporary model folder and
16x16 frames, so that the command's plumbing is tested in seconds; the statistics themselves
are tested in test_smoothing.py.
"""

import json

import pytest
import torch

from drake_cert import cli
from drake_cert.cli.certify import format_summary
from drake_cert.perception.models import (
    SmallResNet,
    StiffnessRegressor,
    file_sha256,
    model_path,
    save_model,
)

PRESET = "rtk-like"
FAST = ["--preset", PRESET, "--size", "16", "--frames", "3", "--n0", "10", "--n", "200",
        "--batch-size", "100", "--compile", "off", "--attack-steps", "2"]



@pytest.fixture(scope="module")
def models(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    torch.manual_seed(0)
    for sigma in (0.0, 0.25):
        classifier = SmallResNet(3, width=4).eval()
        cpath = save_model(classifier, model_path(PRESET, "classify", sigma, root),
                           meta={"image_size": 16})
        head = torch.nn.Linear(16, 1)
        torch.nn.init.zeros_(head.weight)
        torch.nn.init.constant_(head.bias, 50_000.0)
        save_model(StiffnessRegressor(classifier.backbone, head),
                   model_path(PRESET, "regress", sigma, root),
                   meta={"image_size": 16, "classifier_file": cpath.name,
                         "classifier_sha256": file_sha256(cpath)})
    return str(root)


def _run_json(capsys, args):
    assert cli.main(["certify", *args, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_certify_json_keeps_its_progress_on_stderr_in_a_log(models, capsys):
    """With --json the JSON is on stdout and the progress still on stderr, as whole lines
    (capsys: stderr is not a terminal, as in a log): a long run is never silent."""
    out = _run_json(capsys, [*FAST, "--models", models, "--sigma", "0.25"])
    assert out["summary"]["frames"] == 3
    assert cli.main(["certify", *FAST, "--models", models, "--sigma", "0.25", "--json"]) == 0
    captured = capsys.readouterr()
    json.loads(captured.out)
    lines = [line for line in captured.err.splitlines() if "certify rtk-like" in line]
    assert lines and all("\r" not in line for line in lines)


def test_certify_reports_accuracy_radius_abstain_rate_and_interval(models, capsys):
    out = _run_json(capsys, [*FAST, "--models", models, "--sigma", "0.25", "--attack", "sa"])
    s = out["summary"]
    assert s["frames"] == 3 and len(out["records"]) == 3
    for key in ("accuracy", "clean_accuracy", "abstain_rate", "interval_coverage",
                "envelope_rate"):
        assert 0.0 <= s[key] <= 1.0
    assert s["mean_radius"] is None or s["mean_radius"] >= 0
    assert 0.0 <= s["unbounded_radius_rate"] <= 1.0 and s["interval_width_mean"] > 0
    assert {r["label"] for r in out["records"]} == {0, 1, 2}  # balanced frame choice
    assert out["provenance"]["seed"] == 0
    # every frame's label range is certified right, certified wrong, or abstains
    shares = [s[f"{k}_rate"] for k in ("certified_right", "certified_wrong",
                                        "interval_abstain")]
    assert sum(shares) == pytest.approx(1.0)
    assert s["interval_abstain_rate"] == s["envelope_rate"]
    wrong = sum(r["interval_certified"] and not r["interval_holds_label"]
                for r in out["records"])
    assert s["certified_wrong_rate"] == wrong / 3
    lo, hi = s["certified_wrong_rate_ci95"]
    assert lo <= s["certified_wrong_rate"] <= hi
    assert s["training"] == {"method": "gaussian"}  # a file without the field: the old way


def test_certify_base_model_reports_attack_accuracy_and_no_radius(models, capsys):
    out = _run_json(capsys, [*FAST, "--models", models, "--sigma", "0", "--attack", "ea"])
    assert "mean_radius" not in out["summary"]
    assert 0.0 <= out["summary"]["accuracy"] <= 1.0
    assert cli.main(["certify", *FAST, "--models", models, "--sigma", "0"]) == 0
    assert "no certificate" in capsys.readouterr().out


def test_certify_regressor_reports_interval_within_the_envelope(models, capsys):
    out = _run_json(capsys, [*FAST, "--models", models, "--sigma", "0.25", "--task", "regress",
                             "--eps", "0.1", "--calibration-per-class", "99",
                             "--calibration-n", "50"])
    s = out["summary"]
    # 99 calibration frames per label: the fewest with a finite beta at alpha_c = 0.01 (fewer
    # is an input error, tests/test_bad_inputs.py). The interval stays inside the envelope
    # (30k-60k N/rad for rtk-like).
    assert s["beta_n_per_rad"] is not None and s["beta_n_per_rad"] >= 0
    assert 0 < s["interval_width_mean"] <= 30_000.0


def test_certify_text_output_names_the_metrics(models, capsys):
    assert cli.main(["certify", *FAST, "--models", models, "--sigma", "0.25"]) == 0
    text = capsys.readouterr().out
    for word in ("accuracy", "abstain rate", "mean certified radius", "coverage"):
        assert word in text


@pytest.mark.parametrize("extra, message", [
    (["--sigma", "-1"], "sigma"),
    (["--sigma", "0.25", "--alpha", "1.5"], "alpha"),
    (["--sigma", "0.25", "--n", "5"], "n = 5 samples can never certify"),
    (["--sigma", "0.5"], "make it with: drake-cert train"),
    (["--sigma", "0.25", "--task", "regress", "--eps", "5"], "too few"),
    (["--sigma", "0.25", "--device", "cuda"], "CUDA is not available"),
])
def test_bad_inputs_give_one_line_and_exit_2(models, capsys, extra, message):
    # argparse keeps the last of a repeated option, so `extra` overrides FAST.
    assert cli.main(["certify", *FAST, "--models", models, *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1 and "Traceback" not in err


def test_malformed_numbers_are_usage_errors(models, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["certify", *FAST, "--models", models, "--sigma", "0.25", "--n", "many"])
    assert exit_info.value.code == 2
    assert "'many' is not an integer" in capsys.readouterr().err


def test_unknown_preset_exits_2(models, capsys):
    assert cli.main(["certify", "--preset", "mars", "--sigma", "0.25", "--models", models]) == 2
    assert "unknown preset 'mars'" in capsys.readouterr().err


def test_certify_frames_dir_certifies_a_users_class_folders(models, tmp_path, capsys):
    folder = tmp_path / "frames"
    assert cli.main(["generate", "--preset", PRESET, "--split", "test", "--size", "16",
                     "--frames-per-class", "2", "--export", str(folder)]) == 0
    capsys.readouterr()
    out = _run_json(capsys, [*FAST, "--models", models, "--sigma", "0.25", "--frames", "50",
                             "--frames-dir", str(folder)])
    assert out["summary"]["frames"] == 6  # every exported frame (2 per label), not 50
    assert {r["label"] for r in out["records"]} == {0, 1, 2}
    # stiffness.csv gave each frame its true stiffness: coverage is a number, not NaN
    assert 0.0 <= out["summary"]["interval_coverage"] <= 1.0


@pytest.mark.parametrize("beta, shown", [(3900.0, "conformal beta 3,900 N/rad\n"),
                                         (float("inf"), "conformal beta inf (too few")])
def test_the_regressors_text_says_too_few_frames_only_where_beta_is_infinite(beta, shown):
    s = dict(preset="rtk-like", task="regress", sigma=0.25, attack="none", eps=0.25, frames=9,
             n=500, alpha=0.001, mae_n_per_rad=2000.0, beta_n_per_rad=beta,
             interval_width_mean=25000.0, raw_width_mean=20000.0, interval_coverage=1.0)
    text = format_summary(s)
    assert shown in text
    assert ("too few" in text) == (beta == float("inf"))
