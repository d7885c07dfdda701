"""The synthetic frame generator and the image-folder loader (DESIGN section 3, data)."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from drake_cert.cli.generate import export_frames
from drake_cert.config import load_conditions
from drake_cert.errors import ConfigError
from drake_cert.perception.datasets import load_image_folder, load_split
from drake_cert.perception.frames import STYLES, generate_frames, render_frames
from drake_cert.perception.probe import mean_colour_probe_accuracy

TABLE = load_conditions()



def test_same_seed_gives_the_same_bytes_and_another_seed_other_frames():
    a = generate_frames(TABLE, "carla-like", seed=3, frames_per_class=6)
    b = generate_frames(TABLE, "carla-like", seed=3, frames_per_class=6)
    c = generate_frames(TABLE, "carla-like", seed=4, frames_per_class=6)
    assert a.images.numpy().tobytes() == b.images.numpy().tobytes()
    assert torch.equal(a.stiffness_n_per_rad, b.stiffness_n_per_rad)
    assert not torch.equal(a.images, c.images)
    assert not torch.equal(a.stiffness_n_per_rad, c.stiffness_n_per_rad)


@pytest.mark.parametrize("size", [64, 32])
def test_frames_are_rgb_in_unit_range_with_balanced_labels(size):
    f = generate_frames(TABLE, "robotcar-like", seed=0, frames_per_class=5, size=size)
    assert f.images.shape == (15, 3, size, size) and f.images.dtype == torch.float32
    assert f.images.min() >= 0.0 and f.images.max() <= 1.0
    assert f.labels.dtype == torch.int64
    assert torch.bincount(f.labels).tolist() == [5, 5, 5]
    assert f.label_names == ["sunny", "rain", "snow"] and f.preset == "robotcar-like"
    levels = f.images * 255  # camera frames: 8-bit levels
    assert torch.allclose(levels, levels.round(), atol=1e-3)


@pytest.mark.parametrize("preset", ["carla-like", "rtk-like", "robotcar-like", "weather"])
def test_each_frame_stiffness_lies_in_its_condition_interval(preset):
    f = generate_frames(TABLE, preset, seed=1, frames_per_class=12, size=32)
    for k, name in enumerate(f.label_names):
        lo, hi = TABLE.condition(name).interval
        c = f.stiffness_n_per_rad[f.labels == k]
        assert len(c) == 12
        assert (c >= lo).all() and (c <= hi).all(), name
        assert c.max() - c.min() > 0.3 * (hi - lo)  # spread over the interval


def _high_pass_energy(x: torch.Tensor) -> torch.Tensor:
    g = x.mean(1, keepdim=True)
    return (g - F.avg_pool2d(g, 3, 1, 1, count_include_pad=False)).abs().mean((1, 2, 3))


# Precipitation shows in the sky (top rows, always above the horizon); surfaces in the
# road's texture (bottom rows).
INTENSITY_STATISTIC = {
    "light_rain": "sky", "rain": "sky", "heavy_rain": "sky", "snow": "sky",
    "sunny": "road", "asphalt": "road", "cobblestone": "road", "sand": "road",
}


@pytest.mark.parametrize("label", sorted(STYLES))
def test_rendering_intensity_rises_as_stiffness_falls(label):
    """Same random draws, severity 0 (C = C_hi) vs 1 (C = C_lo): more streaks/flakes, grain."""
    n = 24
    low = render_frames(STYLES[label], torch.zeros(n), generator=torch.Generator().manual_seed(5))
    high = render_frames(STYLES[label], torch.ones(n), generator=torch.Generator().manual_seed(5))
    rows = slice(0, 16) if INTENSITY_STATISTIC[label] == "sky" else slice(48, 64)
    more = _high_pass_energy(high[:, :, rows]) > _high_pass_energy(low[:, :, rows])
    assert more.float().mean() >= 2 / 3, label


def test_mean_colour_does_not_reveal_the_road_condition():
    """A linear probe on the 3 per-channel means is near chance (1/3) on three weathers."""
    train = generate_frames(TABLE, "carla-like", seed=11, frames_per_class=80, size=32)
    test = generate_frames(TABLE, "carla-like", seed=12, frames_per_class=60, size=32)
    assert mean_colour_probe_accuracy(train, test) < 0.5
    # and the per-class average colours are close relative to the frame-to-frame spread
    means = train.images.mean(dim=(2, 3))
    centres = torch.stack([means[train.labels == k].mean(0) for k in range(3)])
    spread = means.std(0)
    assert ((centres - centres.mean(0)).abs() < 0.25 * spread).all()


def test_splits_are_disjoint_and_reproducible():
    train = load_split("rtk-like", "train", frames_per_class=8, size=32)
    test = load_split("rtk-like", "test", frames_per_class=8, size=32)
    again = generate_frames(TABLE, "rtk-like", seed=_split_seed("test"), frames_per_class=8,
                            size=32)
    assert torch.equal(test.images, again.images)
    flat_train = {bytes(x.numpy().tobytes()) for x in train.images}
    assert all(bytes(x.numpy().tobytes()) not in flat_train for x in test.images)


def _split_seed(split):
    from drake_cert.perception.datasets import split_seed
    return split_seed(0, split)


def test_default_split_sizes_follow_the_preset():
    from drake_cert.perception.datasets import split_frames_per_class
    assert split_frames_per_class(4000, "train") == 4000
    assert split_frames_per_class(4000, "test") == 800
    assert split_frames_per_class(400, "calibration") == 80
    with pytest.raises(ConfigError, match="unknown split 'val'"):
        load_split("rtk-like", "val")


def test_image_folder_round_trips_exported_frames(tmp_path):
    frames = generate_frames(TABLE, "rtk-like", seed=2, frames_per_class=3, size=32)
    export_frames(frames, tmp_path)
    loaded = load_image_folder(tmp_path, size=32)
    assert loaded.preset == "rtk-like" and loaded.label_names == frames.label_names
    assert torch.equal(loaded.labels, frames.labels)
    assert torch.equal(loaded.images, frames.images)  # 8-bit frames survive PNG exactly
    # stiffness.csv (written by export_frames, to 0.1 N/rad) gives back each true stiffness
    assert torch.allclose(loaded.stiffness_n_per_rad, frames.stiffness_n_per_rad, atol=0.1)
    (tmp_path / "stiffness.csv").unlink()
    assert torch.isnan(load_image_folder(tmp_path, size=32).stiffness_n_per_rad).all()


def test_image_folder_resizes_jpeg_and_png_to_the_model_size(tmp_path):
    from PIL import Image
    for label, colour in (("sunny", (200, 180, 90)), ("snow", (240, 240, 250))):
        (tmp_path / label).mkdir()
        Image.new("RGB", (120, 80), colour).save(tmp_path / label / "a.png")
        Image.new("RGB", (50, 50), colour).save(tmp_path / label / "b.jpg")
    f = load_image_folder(tmp_path, size=64)
    assert f.images.shape == (4, 3, 64, 64)
    assert f.label_names == ["sunny", "snow"] and f.preset == ""  # table order, grippiest first
    assert f.labels.tolist() == [1, 1, 0, 0]  # folders read in name order
    f2 = load_image_folder(tmp_path, preset="robotcar-like", size=16)
    assert f2.label_names == ["sunny", "rain", "snow"] and f2.preset == "robotcar-like"
    assert np.allclose(f2.images[2, :, 0, 0].numpy(), np.array([200, 180, 90]) / 255, atol=0.02)


def test_image_folder_rejects_unknown_labels(tmp_path):
    from PIL import Image
    (tmp_path / "fog").mkdir()
    Image.new("RGB", (8, 8)).save(tmp_path / "fog" / "a.png")
    with pytest.raises(ConfigError, match="'fog'"):
        load_image_folder(tmp_path)
    (tmp_path / "fog").rename(tmp_path / "sand")
    with pytest.raises(ConfigError, match="'sand' is not a label of preset 'carla-like'"):
        load_image_folder(tmp_path, preset="carla-like")
    with pytest.raises(ConfigError, match="does not exist"):
        load_image_folder(tmp_path / "missing")


def test_disk_cache_returns_the_generated_bytes(tmp_path, monkeypatch):
    from drake_cert.perception.datasets import clear_cache
    monkeypatch.setenv("DRAKE_CERT_DATA_CACHE", str(tmp_path))
    clear_cache()
    fresh = load_split("carla-like", "calibration", seed=5, frames_per_class=4, size=32)
    assert len(list(tmp_path.glob("carla-like_calibration_*.npz"))) == 1
    clear_cache()
    cached = load_split("carla-like", "calibration", seed=5, frames_per_class=4, size=32)
    assert cached is not fresh
    assert cached.images.numpy().tobytes() == fresh.images.numpy().tobytes()
    assert torch.equal(cached.labels, fresh.labels)
    assert torch.equal(cached.stiffness_n_per_rad, fresh.stiffness_n_per_rad)
    assert cached.label_names == fresh.label_names and cached.preset == "carla-like"
    clear_cache()
