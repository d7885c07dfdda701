"""PGD attacks and the certificates under attack, on tiny models trained here on easy frames.

The frames encode the true stiffness in their brightness (plus texture), labels are the
carla-like conditions (sunny 80-120k, light rain 60-80k, heavy rain 40-60k N/rad), and the
models are trained with Gaussian noise as in Cohen et al. Small and fast, but real training.
"""

import math

import numpy as np
import pytest
import torch

from drake_cert.certification.attacks import (
    AttackSettings,
    attack,
    efficiency_attack,
    stability_attack,
)
from drake_cert.certification.classifier import ABSTAIN, SmoothedClassifier
from drake_cert.certification.intervals import runtime_classification_interval, runtime_interval
from drake_cert.certification.regressor import MedianSmoothedRegressor, calibrate_conformal
from drake_cert.certification.sampler import CalibrationSampling
from drake_cert.config import load_conditions

PRESET = "carla-like"
SIGMA = 0.25
SIDE = 12


def make_frames(count: int, seed: int):
    """Frames [count, 3, SIDE, SIDE] whose brightness tracks the true stiffness, with labels."""
    table = load_conditions()
    conds = table.preset_conditions(PRESET)
    g = torch.Generator().manual_seed(seed)
    labels = torch.arange(count) % len(conds)
    lo = torch.tensor([conds[int(k)].stiffness_lo_n_per_rad for k in labels])
    hi = torch.tensor([conds[int(k)].stiffness_hi_n_per_rad for k in labels])
    # Stay off the class edges by 10 % so that the clean labels are learnable.
    u = 0.1 + 0.8 * torch.rand(count, generator=g)
    stiffness = lo + u * (hi - lo)
    t = (stiffness - 40_000) / 80_000
    texture = 0.08 * torch.randn(count, 3, SIDE, SIDE, generator=g)
    images = (0.15 + 0.7 * t.view(-1, 1, 1, 1) + texture).clamp(0, 1)
    return images, labels, stiffness


class Tiny(torch.nn.Module):
    def __init__(self, outputs: int):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 8, 3, padding=1)
        self.head = torch.nn.Linear(8, outputs)

    def forward(self, x):
        return self.head(torch.relu(self.conv(x)).mean(dim=(2, 3)))


class TinyRegressor(torch.nn.Module):
    """Outputs stiffness in N/rad, shape [B]."""

    def __init__(self):
        super().__init__()
        self.net = Tiny(1)

    def forward(self, x):
        return 1e5 * self.net(x).squeeze(-1)


def _train(model, loss_of, steps=300):
    images, labels, stiffness = make_frames(600, seed=0)
    g = torch.Generator().manual_seed(1)
    opt = torch.optim.Adam(model.parameters(), lr=0.02)
    for _ in range(steps):
        idx = torch.randint(0, len(images), (64,), generator=g)
        x = images[idx] + SIGMA * torch.randn(images[idx].shape, generator=g)
        opt.zero_grad()
        loss_of(model, x, labels[idx], stiffness[idx]).backward()
        opt.step()
    return model.eval()



@pytest.fixture(scope="module")
def classifier():
    torch.manual_seed(0)
    return _train(Tiny(3), lambda m, x, y, s: torch.nn.functional.cross_entropy(m(x), y))


@pytest.fixture(scope="module")
def regressor():
    torch.manual_seed(0)
    return _train(TinyRegressor(), lambda m, x, y, s: ((m(x) - s) / 1e5).pow(2).mean())


@pytest.fixture(scope="module")
def test_frames():
    return make_frames(12, seed=123)


def test_trained_models_learn_the_easy_task(classifier, regressor, test_frames):
    images, labels, stiffness = test_frames
    with torch.no_grad():
        assert (classifier(images).argmax(1) == labels).float().mean() >= 0.9
        assert (regressor(images) - stiffness).abs().mean() < 6_000


@pytest.mark.parametrize("kind", ["sa", "ea"])
@pytest.mark.parametrize("sigma", [0.0, SIGMA])
def test_pgd_stays_within_the_budget_and_the_pixel_box(classifier, regressor, test_frames,
                                                       kind, sigma):
    images = test_frames[0]
    for model, task in ((classifier, "classify"), (regressor, "regress")):
        adv = attack(model, images, kind, AttackSettings(eps=0.7, steps=5, noise_draws=2),
                     task=task, sigma=sigma)
        assert adv.shape == images.shape
        assert float((adv - images).flatten(1).norm(dim=1).max()) <= 0.7 + 1e-5
        assert float(adv.min()) >= 0 and float(adv.max()) <= 1


def test_attacks_are_deterministic_by_seed(classifier, test_frames):
    images = test_frames[0]
    settings = AttackSettings(eps=1.0, steps=4, noise_draws=3, seed=5)
    a = stability_attack(classifier, images, settings, task="classify", sigma=SIGMA)
    b = stability_attack(classifier, images, settings, task="classify", sigma=SIGMA)
    c = stability_attack(classifier, images, AttackSettings(eps=1.0, steps=4, noise_draws=3,
                                                            seed=6),
                         task="classify", sigma=SIGMA)
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_stability_attack_raises_and_efficiency_attack_lowers_the_prediction(
        classifier, regressor, test_frames):
    images = test_frames[0]
    settings = AttackSettings(eps=8.0, steps=30)
    with torch.no_grad():
        sa = classifier(stability_attack(classifier, images, settings, task="classify")).argmax(1)
        ea = classifier(efficiency_attack(classifier, images, settings, task="classify")).argmax(1)
        clean = classifier(images).argmax(1)
        assert bool((sa <= clean).all()) and bool((ea >= clean).all())
        assert (sa[clean > 0] < clean[clean > 0]).float().mean() >= 0.9  # grippier
        assert (ea[clean < 2] > clean[clean < 2]).float().mean() >= 0.9  # less grippy
        clean_y = regressor(images)
        up = regressor(stability_attack(regressor, images, AttackSettings(eps=1.0, steps=10),
                                        task="regress"))
        down = regressor(efficiency_attack(regressor, images, AttackSettings(eps=1.0, steps=10),
                                           task="regress"))
    assert bool((up > clean_y).all()) and bool((down < clean_y).all())


def test_smoothed_attack_raises_the_smoothed_median(regressor, test_frames):
    images = test_frames[0][:4]
    smooth = MedianSmoothedRegressor(regressor, SIGMA)
    adv = stability_attack(regressor, images, AttackSettings(eps=1.0, steps=8, noise_draws=8),
                           task="regress", sigma=SIGMA)
    for x, z in zip(images, adv, strict=True):
        before = smooth.certify_interval(x, 0.0, 500, 0.01, 500, seed=0)[0]
        after = smooth.certify_interval(z, 0.0, 500, 0.01, 500, seed=0)[0]
        assert after > before


def test_pgd_inside_the_certified_radius_never_leaves_the_certified_set(classifier,
                                                                        test_frames):
    images = test_frames[0]
    smooth = SmoothedClassifier(classifier, 3, SIGMA)
    attacked = 0
    for i, x in enumerate(images):
        cert = smooth.certify(x, 50, 2000, 0.001, 1000, seed=i)
        if cert.abstained:
            continue
        settings = AttackSettings(eps=0.95 * cert.radius, steps=10, noise_draws=8, seed=i)
        for kind in ("sa", "ea"):
            adv = attack(classifier, x[None], kind, settings, task="classify", sigma=SIGMA)[0]
            assert smooth.predict(adv, 2000, 0.001, 1000, seed=100 + i) in (cert.label, ABSTAIN)
            attacked += 1
    assert attacked >= 16


def test_runtime_interval_contains_true_stiffness_when_clean_prediction_right(
        classifier, test_frames):
    images, labels, stiffness = test_frames
    table = load_conditions()
    eps = 0.5
    smooth = SmoothedClassifier(classifier, 3, SIGMA)
    checked = 0
    for kind in ("sa", "ea"):
        adv = attack(classifier, images, kind, AttackSettings(eps=eps, steps=10, noise_draws=8),
                     task="classify", sigma=SIGMA)
        for i in range(len(images)):
            if smooth.predict(images[i], 2000, 0.001, 1000, seed=i) != int(labels[i]):
                continue
            cert = smooth.certify(adv[i], 50, 2000, 0.001, 1000, seed=1000 + i)
            rt = runtime_classification_interval(cert, table, PRESET, eps)
            assert rt.stiffness_lo_n_per_rad <= float(stiffness[i]) <= rt.stiffness_hi_n_per_rad
            checked += 1
    assert checked >= 20


def test_regression_runtime_interval_covers_true_stiffness_under_attack(regressor):
    table = load_conditions()
    smooth = MedianSmoothedRegressor(regressor, SIGMA)
    cal_images, cal_labels, cal_stiffness = make_frames(300, seed=7)
    cal = calibrate_conformal(smooth, cal_images, cal_stiffness.tolist(), cal_labels.tolist(),
                              sampling=CalibrationSampling(n=200, batch_size=200, seed=0),
                              alpha_m=0.01, alpha_c=0.05)
    assert math.isfinite(cal.beta) and cal.beta > 0
    images, _, stiffness = make_frames(24, seed=99)
    eps = 0.3
    misses, widths = 0, []
    for kind in ("sa", "ea"):
        adv = attack(regressor, images, kind, AttackSettings(eps=eps, steps=8, noise_draws=4),
                     task="regress", sigma=SIGMA)
        for i in range(len(images)):
            _, lower, upper = smooth.certify_interval(adv[i], eps, 2000, 0.001, 1000, seed=i)
            lo, hi = runtime_interval(lower, upper, cal.beta, table.envelope(PRESET))
            misses += not lo <= float(stiffness[i]) <= hi
            widths.append(hi - lo)
    # Coverage >= 1 - (0.001 + 0.05 + 0.01) marginally; 48 frames allow a few misses at most.
    assert misses <= 4
    assert np.mean(widths) < 80_000  # narrower than the carla-like envelope


def test_bad_attack_inputs_are_rejected(classifier, test_frames):
    from drake_cert.errors import CertificationError
    images = test_frames[0]
    with pytest.raises(CertificationError, match="attack 'up'"):
        attack(classifier, images, "up", AttackSettings(eps=1.0), task="classify")
    with pytest.raises(CertificationError, match="eps"):
        attack(classifier, images, "sa", AttackSettings(eps=-1.0), task="classify")
    with pytest.raises(CertificationError, match=r"\[B, C, H, W\]"):
        attack(classifier, images[0], "sa", AttackSettings(eps=1.0), task="classify")


@pytest.mark.parametrize("preset", ["carla-like", "rtk-like", "robotcar-like"])
def test_pgd_at_half_budget_breaks_the_shipped_nonrobust_classifier(preset):
    """Paper Table 'Vulnerability': L2 PGD at eps = 0.5 takes f to <= 50% accuracy.

    A frame counts as robust only if neither the stability nor the efficiency attack flips it.
    """
    from drake_cert.perception.datasets import load_split
    from drake_cert.perception.models import load_model

    frames = load_split(preset, "test", frames_per_class=10, seed=3)
    f = load_model(preset, "classify", 0.0)
    settings = AttackSettings(eps=0.5, steps=20, seed=0)
    robust = torch.ones(len(frames.labels), dtype=torch.bool)
    with torch.no_grad():
        robust &= f(frames.images).argmax(1) == frames.labels
    for kind in ("sa", "ea"):
        adv = attack(f, frames.images, kind, settings, task="classify")
        assert float((adv - frames.images).flatten(1).norm(dim=1).max()) <= 0.5 + 1e-4
        with torch.no_grad():
            robust &= f(adv).argmax(1) == frames.labels
    assert float(robust.float().mean()) <= 0.5
