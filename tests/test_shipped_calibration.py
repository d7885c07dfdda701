"""The robust conformal calibration ships with each model (docs/design.md 3.6): a drive on the
shipped defaults reads its votes instead of drawing them, and the votes are the ones the drive's
own path draws."""

import dataclasses

import numpy as np
import pytest

from drake_cert.certification.classifier import SmoothedClassifier
from drake_cert.certification.sampler import make_generator, with_precision
from drake_cert.certification.seeds import stream_seed
from drake_cert.certification.shipped_calibration import read_shipped
from drake_cert.config import load_conditions
from drake_cert.perception.datasets import load_split
from drake_cert.perception.models import load_model, model_path
from drake_cert.systems import driving
from drake_cert.systems.scenario import SHIPPED_SCENARIOS, load_scenario

PRESET_SCENARIO = {"robotcar-like": "dry_to_snow", "carla-like": "rain_route",
                   "rtk-like": "road_surface"}


def _evaluated(scenario, conditions):
    p = scenario.perception
    model = with_precision(load_model(p.preset, p.task, p.sigma), p.precision)
    return driving._evaluated_model(model, scenario, conditions, p.sigma)


@pytest.mark.parametrize("name", SHIPPED_SCENARIOS)
def test_every_shipped_scenario_finds_its_calibration_votes_shipped(name):
    sc = load_scenario(name)
    spec = driving.conformal_votes_spec(sc, load_conditions())
    p = sc.perception
    shipped = read_shipped(model_path(p.preset, p.task, p.sigma))
    assert shipped is not None and shipped.spec == spec, (name, spec)
    assert len(shipped.true_counts) == 3 * p.conformal_frames_per_class


def _recomputed(preset, indices):
    sc, conditions = load_scenario(PRESET_SCENARIO[preset]), load_conditions()
    p = sc.perception
    shipped = read_shipped(model_path(p.preset, p.task, p.sigma))
    spec = shipped.spec
    cal = load_split(p.preset, "calibration", conditions=conditions,
                     frames_per_class=spec.frames_per_label)
    assert np.array_equal(cal.labels.numpy(), shipped.labels)
    assert np.allclose(cal.stiffness_n_per_rad.numpy(), shipped.stiffness_n_per_rad)
    classifier = SmoothedClassifier(_evaluated(sc, conditions), 3, p.sigma)
    out = []
    for i in indices:
        seed = stream_seed(spec.root_seed, int(i), "calibration", split="calibration")
        counts = classifier.sample_counts(cal.images[int(i)], spec.n, spec.batch_size,
                                          make_generator(seed, classifier.device))
        out.append((int(counts[int(cal.labels[int(i)])]), int(shipped.true_counts[int(i)])))
    return out


def test_a_few_shipped_votes_are_what_the_drives_path_draws():
    for got, shipped in _recomputed("robotcar-like", [0, 2999, 5999]):
        assert got == shipped


@pytest.mark.slow
@pytest.mark.parametrize("preset", list(PRESET_SCENARIO))
def test_every_shipped_vote_is_what_the_drives_path_draws(preset):
    n = len(read_shipped(model_path(preset, "classify", 1.0)).true_counts)
    pairs = _recomputed(preset, range(n))
    assert [g for g, _ in pairs] == [s for _, s in pairs]


def test_another_setting_calibrates_with_a_progress_bar_and_caches(tmp_path, monkeypatch):
    monkeypatch.setenv("DRAKE_CERT_CACHE", str(tmp_path))
    sc = load_scenario("dry_to_snow")
    sc = dataclasses.replace(sc, perception=dataclasses.replace(
        sc.perception, conformal_frames_per_class=4, conformal_calibration_n=16))
    conditions = load_conditions()
    seen = []

    def progress(iterable):
        seen.append(True)
        return iterable

    evaluated = _evaluated(sc, conditions)
    votes = driving.conformal_votes(evaluated, sc, conditions, progress)
    assert seen and votes.source == "cache" and len(votes.true_counts) == 12
    assert (votes.true_counts <= 16).all()
    again = driving.conformal_votes(evaluated, sc, conditions, lambda it: 1 / 0)  # no drawing
    assert np.array_equal(again.true_counts, votes.true_counts)


@pytest.mark.parametrize("preset", list(PRESET_SCENARIO))
def test_the_reproduction_calibrates_g_conformal_as_the_drive_does(preset, monkeypatch):
    """At sigma 1 the reproduction's g_conformal reads the shipped votes (nothing is drawn)
    and gets the drive's thresholds, bins and bound, with the drive's settings as defaults."""
    from drake_cert.certification import conformal as rc
    from drake_cert.experiments.calibrations import conformal_calibration
    from drake_cert.experiments.reproduce_config import ReproduceConfig

    sc, conditions = load_scenario(PRESET_SCENARIO[preset]), load_conditions()
    drive = driving.drive_conformal_calibration(_evaluated(sc, conditions), sc, conditions)
    monkeypatch.setattr(rc, "true_label_counts", lambda *a, **k: 1 / 0)  # drawing would fail
    config = ReproduceConfig(presets=(preset,), precision=sc.perception.precision,
                             backend=sc.perception.backend)
    assert config.conformal_alpha_c == sc.perception.conformal_alpha_c
    ours = conformal_calibration(config, preset, 1.0, conditions)
    assert ours.thresholds == drive.thresholds and ours.alpha_c == drive.alpha_c <= 0.25
    assert ours.delta_cal == drive.delta_cal and ours.bins == drive.bins


def test_every_classifier_the_reproduction_certifies_with_has_its_votes_shipped():
    """The default reproduction (fp32, ONNX Runtime) finds the votes of every (preset, sigma) it
    calibrates g_conformal at shipped beside the model, drawn for exactly its spec (the model
    file's digest included), so a regeneration draws none."""
    from drake_cert.experiments.calibrations import conformal_scenario, conformal_sigmas
    from drake_cert.experiments.reproduce_config import ReproduceConfig

    config, conditions = ReproduceConfig(precision="fp32", backend="onnxruntime"), \
        load_conditions()
    for preset in config.presets:
        for sigma in conformal_sigmas(config):
            spec = driving.conformal_votes_spec(conformal_scenario(config, preset, sigma),
                                                conditions)
            shipped = read_shipped(model_path(preset, "classify", sigma))
            assert shipped is not None and shipped.spec == spec, (preset, sigma)


def test_calibrate_prints_each_bins_threshold_and_bound_from_the_shipped_votes(capsys):
    from drake_cert.cli import main

    assert main(["calibrate", "--scenario", "dry_to_snow"]) == 0
    out = capsys.readouterr().out
    assert "votes shipped" in out and "[80-90] k " in out and "per-frame miss bound" in out


def test_calibrate_refuses_a_scenario_without_the_conformal_interval(tmp_path, capsys):
    from drake_cert.cli import main
    from drake_cert.systems.scenario import scenario_path

    text = scenario_path("dry_to_snow").read_text().replace("interval: conformal",
                                                             "interval: safe_set")
    path = tmp_path / "safe.yaml"
    path.write_text(text)
    assert main(["calibrate", "--scenario", str(path)]) == 2
    assert "only the robust conformal interval" in capsys.readouterr().err
