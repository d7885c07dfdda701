"""`drake-cert train` and `drake-cert generate`: files, manifest, skipping, one-line errors."""

import json

import pytest
import torch
import yaml

from drake_cert import cli
from drake_cert.perception.models import load_model, model_path

TINY = ["--preset", "rtk-like", "--frames-per-class", "12", "--epochs", "1"]


@pytest.fixture(autouse=True)
def restore_torch_threads():
    """`drake-cert train --threads` changes the process-wide count: put it back."""
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def _one_error_line(capsys, argv, *needles):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for needle in needles:
        assert needle in err[0]


def test_train_rejects_an_unknown_preset_with_one_line(capsys, tmp_path):
    _one_error_line(capsys, ["train", "--preset", "kitti", "--sigma", "0", "--models",
                             str(tmp_path)], "unknown preset 'kitti'")


@pytest.mark.parametrize("sigma", ["-0.5", "nan", "big"])
def test_train_rejects_a_bad_sigma_with_one_line(capsys, tmp_path, sigma):
    _one_error_line(capsys, ["train", "--preset", "rtk-like", "--sigma", sigma, "--models",
                             str(tmp_path)], f"sigma = '{sigma}'")


def test_regressor_without_its_classifier_names_the_command(capsys, tmp_path):
    _one_error_line(capsys, ["train", "--preset", "rtk-like", "--task", "regress", "--sigma",
                             "0.25", "--models", str(tmp_path)],
                    "drake-cert train --preset rtk-like --task classify --sigma 0.25")


def test_train_writes_models_with_provenance_and_a_manifest_then_skips(capsys, tmp_path):
    root = str(tmp_path)
    assert cli.main(["train", *TINY, "--sigma", "0.5", "--models", root, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out[0]["task"] == "classify" and 0 <= out[0]["test_accuracy_clean"] <= 1
    assert cli.main(["train", *TINY, "--task", "regress", "--sigma", "0.5", "--models",
                     root]) == 0
    classifier = load_model("rtk-like", "classify", 0.5, root)
    regressor = load_model("rtk-like", "regress", 0.5, root)
    cmd = classifier.meta["provenance"]["command"]
    assert cmd.startswith("drake-cert train --preset rtk-like --task classify --sigma 0.5")
    assert classifier.meta["sigma"] == 0.5 and classifier.meta["provenance"]["seed"] == 0
    # The default regressor is the end-to-end network: [B, 1] stiffness in N/rad.
    assert regressor.meta["regressor"] == "end_to_end"
    with torch.no_grad():
        stiffness = regressor(torch.rand(2, 3, 64, 64))
    assert stiffness.shape == (2, 1)
    assert bool(((stiffness > 1e4) & (stiffness < 3e5)).all())  # N/rad, not 1e5-scaled units
    manifest = yaml.safe_load((tmp_path / "MANIFEST.yaml").read_text())
    assert set(manifest["models"]) == {"rtk-like/classify_sigma0.5.pt",
                                       "rtk-like/regress_sigma0.5.pt"}
    assert not list(tmp_path.rglob("*.ckpt"))  # the checkpoint is removed when done
    before = model_path("rtk-like", "classify", 0.5, root).stat().st_mtime_ns
    capsys.readouterr()
    assert cli.main(["train", *TINY, "--sigma", "0.5", "--models", root]) == 0
    assert "exists; skipping" in capsys.readouterr().err
    assert model_path("rtk-like", "classify", 0.5, root).stat().st_mtime_ns == before


def test_consistency_training_is_recorded_in_the_file_the_manifest_and_certify(capsys,
                                                                               tmp_path):
    from drake_cert.perception.models import training_of

    root = str(tmp_path)
    assert cli.main(["train", *TINY, "--sigma", "0.25", "--models", root, "--method",
                     "consistency", "--consistency-lambda", "5", "--copies", "2"]) == 0
    model = load_model("rtk-like", "classify", 0.25, root)
    assert training_of(model) == {"method": "consistency", "copies": 2, "lambda": 5.0,
                                  "eta": 0.5}
    assert "--method consistency --consistency-lambda 5" in \
        model.meta["provenance"]["command"]
    manifest = yaml.safe_load((tmp_path / "MANIFEST.yaml").read_text())
    assert manifest["models"]["rtk-like/classify_sigma0.25.pt"]["training"]["lambda"] == 5.0
    capsys.readouterr()
    assert cli.main(["certify", "--preset", "rtk-like", "--sigma", "0.25", "--frames", "3",
                     "--n0", "10", "--n", "200", "--compile", "off", "--models", root,
                     "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)["summary"]
    assert summary["training"]["method"] == "consistency"


def test_tail_training_at_another_width_is_recorded_in_the_file(capsys, tmp_path):
    from drake_cert.perception.models import training_of

    root = str(tmp_path)
    assert cli.main(["train", *TINY, "--sigma", "0.25", "--models", root, "--method", "tail",
                     "--tail-fraction", "0.5", "--tail-weight", "0.25", "--width", "8"]) == 0
    model = load_model("rtk-like", "classify", 0.25, root)
    assert training_of(model) == {"method": "tail", "fraction": 0.5, "weight": 0.25}
    assert model.backbone.width == 8
    assert "--method tail --tail-fraction 0.5 --tail-weight 0.25 --width 8" in \
        model.meta["provenance"]["command"]


@pytest.mark.parametrize("extra, message", [
    (["--method", "consistency", "--copies", "1"], "m >= 2"),
    (["--method", "consistency", "--consistency-lambda", "-3"], "consistency_lambda -3"),
    (["--device", "tpu9"], "device"),
    (["--method", "tail", "--tail-fraction", "0"], "tail_fraction 0.0 must be in (0, 1]"),
    (["--width", "1"], "--width 1 must be between 2 and 256"),
    (["--band-quantiles", "0.1", "0.9"], "--band-quantiles needs --task regress"),
    (["--task", "regress", "--regressor", "band", "--band-quantiles", "0.9", "0.1"],
     "must be two levels 0 < LO < HI < 1"),
])
def test_bad_training_options_give_one_line(capsys, tmp_path, extra, message):
    _one_error_line(capsys, ["train", *TINY, "--sigma", "0.25", "--models", str(tmp_path),
                             *extra], message)


def test_regressor_head_option_fits_the_ridge_head_on_frozen_features(capsys, tmp_path):
    from drake_cert.perception.models import StiffnessRegressor, read_model_file

    root = str(tmp_path)
    assert cli.main(["train", *TINY, "--sigma", "0.25", "--models", root]) == 0
    assert cli.main(["train", *TINY, "--task", "regress", "--regressor", "head", "--sigma",
                     "0.25", "--models", root]) == 0
    path = model_path("rtk-like", "regress", 0.25, root)
    assert read_model_file(path)["kind"] == "regressor"
    head = load_model("rtk-like", "regress", 0.25, root)
    assert isinstance(head, StiffnessRegressor)
    assert "--regressor head" in head.meta["provenance"]["command"]
    assert head(torch.rand(2, 3, 64, 64)).shape == (2,)


def test_band_regressor_option_trains_two_ends_and_records_its_levels(capsys, tmp_path):
    from drake_cert.perception.models import training_of

    root = str(tmp_path)
    assert cli.main(["train", *TINY, "--sigma", "0.25", "--models", root]) == 0
    assert cli.main(["train", *TINY, "--task", "regress", "--regressor", "band",
                     "--band-quantiles", "0.1", "0.9", "--sigma", "0.25", "--models",
                     root]) == 0
    band = load_model("rtk-like", "regress", 0.25, root)
    assert training_of(band) == {"method": "quantile_band_end_to_end", "quantiles": [0.1, 0.9]}
    assert "--regressor band --band-quantiles 0.1 0.9" in band.meta["provenance"]["command"]
    assert band(torch.rand(2, 3, 64, 64)).shape == (2, 2)
    metrics = band.meta["test_metrics"]
    assert 0.0 <= metrics["test_band_coverage_noisy"] <= 1.0


def test_generate_writes_a_sample_grid_and_class_folders(capsys, tmp_path):
    out = tmp_path / "grid.png"
    assert cli.main(["generate", "--preset", "rtk-like", "--out", str(out), "--per-class", "2",
                     "--export", str(tmp_path / "frames"), "--frames-per-class", "2"]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(list((tmp_path / "frames").rglob("*.png"))) == 6
    assert (tmp_path / "frames" / "stiffness.csv").read_text().count("\n") == 7
    capsys.readouterr()
    _one_error_line(capsys, ["generate", "--preset", "rtk-like"], "nothing to do")
