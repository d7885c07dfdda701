"""Perception models: the ResNet classifier, its regressor head, files, training and resume."""

import pytest
import torch

from drake_cert.errors import ConfigError, ModelNotFoundError
from drake_cert.perception.datasets import load_split
from drake_cert.perception.models import (
    SmallResNet,
    StiffnessRegressor,
    file_sha256,
    load_model,
    model_path,
    save_model,
)
from drake_cert.perception.probe import mean_colour_probe_accuracy
from drake_cert.perception.training import (
    TrainConfig,
    TrainRun,
    consistency_config,
    consistency_loss,
    evaluate_accuracy,
    evaluate_mse,
    fit_regressor,
    tail_config,
    tail_loss,
    train_classifier,
    training_method,
)

TINY = TrainConfig(width=8, batch_size=32, epochs=8)
SHIPPED_PRESETS = ["carla-like", "rtk-like", "robotcar-like"]



@pytest.fixture(scope="module")
def tiny():
    """A width-8 classifier trained for 8 epochs on 60 carla-like frames per class (~2 s)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    train = load_split("carla-like", "train", frames_per_class=60)
    test = load_split("carla-like", "test", frames_per_class=30)
    model, metrics = train_classifier(train, sigma=0.0, seed=0, config=TINY)
    torch.set_num_threads(before)
    return model, metrics, train, test


def test_resnet_maps_frames_to_features_and_logits():
    model = SmallResNet(4, width=8).eval()
    x = torch.rand(5, 3, 64, 64)
    assert model.features(x).shape == (5, 32)
    assert model(x).shape == (5, 4)
    assert model(torch.rand(2, 3, 32, 32)).shape == (2, 4)  # global pooling: any size


def test_a_pooled_network_is_the_same_network_on_the_frame_averaged_over_pixel_blocks(tmp_path):
    # pool 2 is part of the model f: its answer on a 64 x 64 frame is the unpooled network's
    # on the 32 x 32 frame of 2 x 2 block means, and the file keeps it (the noise of smoothing
    # is still added to the full frame, where the certificate's radius is measured).
    torch.manual_seed(0)
    pooled = SmallResNet(3, width=8, pool=2).eval()
    plain = SmallResNet(3, width=8).eval()
    plain.load_state_dict(pooled.state_dict())
    x = torch.rand(4, 3, 64, 64)
    assert torch.allclose(pooled(x), plain(torch.nn.functional.avg_pool2d(x, 2)), atol=1e-6)
    path = save_model(pooled, model_path("carla-like", "classify", 1, tmp_path),
                      meta={"label_names": ["a", "b", "c"]})
    loaded = load_model("carla-like", "classify", 1, tmp_path)
    assert loaded.pool == 2 and torch.equal(loaded(x), pooled(x))
    assert path.exists()


def test_tiny_training_learns_above_chance(tiny):
    model, metrics, _, test = tiny
    assert not model.training
    assert evaluate_accuracy(model, test) > 0.5  # chance is 1/3
    assert metrics["epochs"] == 8 and metrics["train_accuracy"] > 0.5


def test_a_cnn_beats_the_mean_colour_probe_by_20_points(tiny):
    model, _, train, test = tiny
    assert evaluate_accuracy(model, test) >= mean_colour_probe_accuracy(train, test) + 0.2


def test_consistency_loss_is_cross_entropy_plus_lambda_kl_plus_eta_entropy():
    """Jeong and Shin's objective on m copies: with copies that agree, the KL term is zero and
    the loss is the cross-entropy plus eta times the entropy of the (common) softmax; with
    lambda = eta = 0 it is the copies' mean cross-entropy (Gaussian augmentation)."""
    torch.manual_seed(0)
    logits = torch.randn(3, 4)
    labels = torch.tensor([0, 2, 3])
    same = logits.repeat(2, 1)
    ce = torch.nn.functional.cross_entropy(logits, labels)
    p = logits.softmax(1)
    entropy = -(p * p.log()).sum(1).mean()
    assert float(consistency_loss(same, labels, copies=2, lam=10.0, eta=0.0)) == \
        pytest.approx(float(ce), rel=1e-6)
    assert float(consistency_loss(same, labels, copies=2, lam=10.0, eta=0.5)) == \
        pytest.approx(float(ce + 0.5 * entropy), rel=1e-6)
    other = torch.cat([logits, torch.randn(3, 4)])
    mean_ce = torch.nn.functional.cross_entropy(other, labels.repeat(2))
    plain = consistency_loss(other, labels, copies=2, lam=0.0, eta=0.0)
    assert float(plain) == pytest.approx(float(mean_ce), rel=1e-6)
    assert float(consistency_loss(other, labels, copies=2, lam=1.0, eta=0.0)) > float(plain)


def test_the_tail_loss_mixes_the_mean_with_the_mean_of_the_worst_frames():
    """(1 - beta) mean CE + beta mean of the worst ceil(q B) per-frame CEs (the empirical CVaR):
    beta = 0 is cross-entropy, q = 1 is cross-entropy too, and the worst frames weigh more."""
    torch.manual_seed(0)
    logits = torch.randn(8, 4)
    labels = torch.tensor([0, 1, 2, 3, 0, 1, 2, 3])
    per_frame = torch.nn.functional.cross_entropy(logits, labels, reduction="none")
    ce = per_frame.mean()
    worst = per_frame.sort(descending=True).values[:2].mean()  # ceil(0.25 * 8) = 2
    assert float(tail_loss(logits, labels, fraction=0.25, weight=0.0)) == pytest.approx(float(ce))
    assert float(tail_loss(logits, labels, fraction=1.0, weight=0.7)) == pytest.approx(float(ce))
    assert float(tail_loss(logits, labels, fraction=0.25, weight=0.5)) == \
        pytest.approx(float(0.5 * ce + 0.5 * worst))
    assert float(worst) > float(ce)
    assert training_method(tail_config(0.25, 0.5)) == {"method": "tail", "fraction": 0.25,
                                                       "weight": 0.5}


@pytest.mark.parametrize("bad", [dict(method="smoothadv"), dict(method="consistency", copies=1),
                                 dict(method="consistency", copies=2,
                                      consistency_lambda=-1.0),
                                 dict(method="gaussian", copies=2),
                                 dict(method="tail", tail_fraction=0.0, tail_weight=0.5),
                                 dict(method="tail", tail_fraction=0.25, tail_weight=1.5),
                                 dict(method="tail", tail_fraction=0.25, copies=2),
                                 dict(method="gaussian", tail_fraction=0.25)])
def test_a_bad_training_method_is_a_config_error(bad):
    with pytest.raises(ConfigError):
        TrainConfig(**bad)


def test_consistency_training_learns_and_its_copies_agree_more_under_noise():
    """Consistency regularization (m = 2, lambda = 10) learns a classifier above chance whose
    predictions under the noise disagree less, across two noisy copies, than those of
    Gaussian augmentation trained on the same data for the same steps."""
    from drake_cert.perception.training import add_gaussian_noise

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    train = load_split("carla-like", "train", frames_per_class=60)
    test = load_split("carla-like", "test", frames_per_class=30)
    sigma = 0.5
    plain, _ = train_classifier(train, sigma=sigma, seed=0, config=TINY)
    regular, metrics = train_classifier(train, sigma=sigma, seed=0,
                                        config=consistency_config(10.0, base=TINY))
    torch.set_num_threads(before)
    assert metrics["config"]["method"] == "consistency"
    assert evaluate_accuracy(regular, test, sigma=sigma) > 0.5  # chance is 1/3

    def disagreement(model):
        g = torch.Generator().manual_seed(1)
        with torch.no_grad():
            a = model(add_gaussian_noise(test.images, sigma, g)).argmax(1)
            b = model(add_gaussian_noise(test.images, sigma, g)).argmax(1)
        return float((a != b).float().mean())

    assert disagreement(regular) < disagreement(plain)


def test_training_is_deterministic_and_resumes_from_its_checkpoint(tmp_path):
    train = load_split("robotcar-like", "train", frames_per_class=16, size=32)
    cfg = TrainConfig(width=4, batch_size=16, epochs=2)
    straight, _ = train_classifier(train, sigma=0.25, seed=7, config=cfg)

    def interrupt(epoch):
        if epoch == 1:
            raise KeyboardInterrupt

    ckpt = tmp_path / "model.pt.ckpt"
    with pytest.raises(KeyboardInterrupt):
        train_classifier(train, sigma=0.25, seed=7, config=cfg,
                         run=TrainRun(checkpoint=ckpt, on_epoch_end=interrupt))
    assert ckpt.exists()
    epochs_run = []
    resumed, _ = train_classifier(train, sigma=0.25, seed=7, config=cfg,
                                  run=TrainRun(checkpoint=ckpt, on_epoch_end=epochs_run.append))
    assert epochs_run == [2]  # only the missing epoch ran
    for a, b in zip(straight.state_dict().values(), resumed.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    other, _ = train_classifier(train, sigma=0.25, seed=8, config=cfg)
    assert not torch.equal(other.fc.weight, straight.fc.weight)


def test_regressor_head_predicts_stiffness_in_n_per_rad(tiny, tmp_path):
    model, _, train, test = tiny
    regressor, metrics = fit_regressor(model, train, sigma=0.0, seed=0)
    pred = regressor(test.images[:7])
    assert pred.shape == (7,)
    # better than predicting the mean stiffness (the classes' intervals differ)
    var = float(test.stiffness_n_per_rad.double().var())
    assert evaluate_mse(regressor, test) < 0.6 * var
    assert metrics["train_mse_n_per_rad_sq"] < 0.6 * var
    # the features stay frozen: only the head is new
    assert all(not p.requires_grad for p in regressor.features.parameters())


def test_saved_models_reload_with_their_provenance(tiny, tmp_path):
    model, metrics, train, test = tiny
    cpath = save_model(model, model_path("carla-like", "classify", 0.25, tmp_path),
                       meta={"label_names": train.label_names, "train_metrics": metrics})
    assert cpath == tmp_path / "carla-like" / "classify_sigma0.25.pt"
    regressor, _ = fit_regressor(model, train, sigma=0.25, seed=0)
    save_model(regressor, model_path("carla-like", "regress", 0.25, tmp_path),
               meta={"classifier_file": cpath.name, "classifier_sha256": file_sha256(cpath)})
    loaded = load_model("carla-like", "classify", 0.25, tmp_path)
    assert not loaded.training and loaded.meta["label_names"] == train.label_names
    assert torch.equal(loaded(test.images[:4]), model(test.images[:4]))
    loaded_r = load_model("carla-like", "regress", 0.25, tmp_path)
    assert isinstance(loaded_r, StiffnessRegressor)
    assert torch.allclose(loaded_r(test.images[:4]), regressor(test.images[:4]))
    # a regressor refuses features from another classifier file
    save_model(SmallResNet(3, width=8), cpath, meta={})
    with pytest.raises(ConfigError, match="refit"):
        load_model("carla-like", "regress", 0.25, tmp_path)


def test_missing_model_names_the_command_that_makes_it(tmp_path):
    with pytest.raises(ModelNotFoundError,
                       match="drake-cert train --preset carla-like --task classify --sigma 0.5"):
        load_model("carla-like", "classify", 0.5, tmp_path)
    with pytest.raises(ConfigError, match="sigma = -1"):
        model_path("carla-like", "classify", -1)


@pytest.mark.parametrize("preset", SHIPPED_PRESETS)
def test_shipped_nonrobust_classifier_is_at_least_95_percent_accurate(preset):
    """The paper's f (sigma = 0) on clean held-out test frames; the probe is 20 points below."""
    test = load_split(preset, "test", frames_per_class=100)
    model = load_model(preset, "classify", 0.0)
    accuracy = evaluate_accuracy(model, test)
    assert accuracy >= 0.95
    assert model.meta["label_names"] == test.label_names
    assert "drake-cert train --preset" in model.meta["provenance"]["command"]
    probe_train = load_split(preset, "calibration", frames_per_class=100)
    assert mean_colour_probe_accuracy(probe_train, test) <= accuracy - 0.2


def test_every_shipped_model_names_its_file_method_and_sweep():
    """MANIFEST.yaml: each shipped file's SHA-256, training method and the sweep that chose it
    (or that none did); a sweep's pick names the table that shows the comparison."""
    import yaml

    from drake_cert.perception.models import default_root, load_model_file, training_of

    root = default_root()
    manifest = yaml.safe_load((root / "MANIFEST.yaml").read_text())["models"]
    assert set(manifest) == {str(p.relative_to(root)) for p in root.rglob("*.pt")}
    for name, entry in manifest.items():
        assert entry["sha256"] == file_sha256(root / name), name
        assert entry["training"]["method"] == training_of(load_model_file(root / name))["method"]
        assert entry["sweep"], name
        if not entry["sweep"].startswith("none"):
            table = entry["sweep"].split()[0]
            assert (root.parents[2] / table).exists(), table
