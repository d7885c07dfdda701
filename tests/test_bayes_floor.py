"""The known-scene oracle (docs/design.md 3.2, "How much of the tail the generator forces"):
it sees the scene a frame was rendered from, so its noisy error bounds every classifier's."""

import numpy as np
import pytest
import torch

from drake_cert.certification.classifier import SmoothedClassifier
from drake_cert.certification.sampler import make_generator
from drake_cert.config import load_conditions
from drake_cert.errors import ConfigError
from drake_cert.perception.bayes_floor import (
    known_scene_votes,
    oracle_frames,
    render_scene,
    severity_grid,
)
from drake_cert.perception.models import load_model
from drake_cert.rng import torch_generator

CONDITIONS = load_conditions()


def _frames(preset, per_label, grid=8, seed=5):
    return list(oracle_frames(CONDITIONS, preset, frames_per_class=per_label, seed=seed,
                              grid_points=grid))


def test_a_scene_changes_only_with_the_severity_it_is_rendered_at():
    grid = severity_grid(4)
    assert torch.allclose(grid, torch.tensor([0.125, 0.375, 0.625, 0.875]))
    one = render_scene("light_rain", grid, 1234)
    assert torch.equal(one, render_scene("light_rain", grid, 1234))
    other = render_scene("light_rain", grid, 1235)
    # neighbouring severities of one scene are closer than one severity of two scenes
    assert (one[0] - one[1]).norm() < (one[0] - other[0]).norm() / 3


def test_each_frame_comes_with_its_scene_at_every_label_and_grid_severity():
    frames = _frames("carla-like", 2, grid=8)
    assert [f.label for f in frames] == [0, 0, 1, 1, 2, 2]
    for f in frames:
        assert f.candidates.shape == (3, 8, 3 * 64 * 64)
        assert 0.0 <= f.severity <= 1.0
        lo, hi = CONDITIONS.preset_conditions("carla-like")[f.label].interval
        assert lo <= f.stiffness_n_per_rad <= hi


def test_with_little_noise_the_oracle_names_every_frame_its_own_label():
    for i, f in enumerate(_frames("carla-like", 2)):
        votes = known_scene_votes(f, 0.05, 50, torch_generator(i))
        assert votes[f.label] == 50


def test_under_overwhelming_noise_the_oracle_is_at_chance():
    f = _frames("robotcar-like", 1)[0]
    votes = known_scene_votes(f, 50.0, 900, torch_generator(3))
    assert votes.sum() == 900
    assert np.all(np.abs(votes / 900 - 1 / 3) < 0.07)


def test_the_shipped_classifier_does_not_beat_the_oracle_that_knows_the_scene():
    """The bound the benchmark reports: the oracle's mean own-label share under the noise is
    at least the shipped sigma-1 classifier's, on the same frames."""
    frames = _frames("carla-like", 4, grid=8)
    model = SmoothedClassifier(load_model("carla-like", "classify", 1.0), 3, 1.0)
    oracle, shipped = [], []
    for i, f in enumerate(frames):
        oracle.append(known_scene_votes(f, 1.0, 200, torch_generator(100 + i))[f.label] / 200)
        counts = model.sample_counts(f.image, 200, 200, make_generator(200 + i, model.device))
        shipped.append(counts[f.label] / 200)
    assert np.mean(oracle) >= np.mean(shipped)


@pytest.mark.parametrize("call, word", [
    (lambda f: known_scene_votes(f, 0.0, 10, torch_generator(0)), "sigma"),
    (lambda f: known_scene_votes(f, 1.0, 0, torch_generator(0)), "draws"),
    (lambda f: severity_grid(0), "grid"),
    (lambda f: next(oracle_frames(CONDITIONS, "carla-like", frames_per_class=0, seed=1)),
     "frames_per_class"),
])
def test_bad_settings_are_refused_naming_the_setting(call, word):
    frame = _frames("carla-like", 1, grid=2)[0]
    with pytest.raises(ConfigError, match=word):
        call(frame)
