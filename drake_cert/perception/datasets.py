"""Frame sets: the synthetic train/calibration/test splits and a loader for users' image folders.

A :class:`FrameSet` is what every perception stage consumes: images in [0, 1] pixel space
(the space in which the smoothing noise is added and L2 budgets are measured), the label of
each frame (an index into ``label_names``, grippiest first as in the preset) and the frame's
true cornering stiffness per tire (N/rad).

Splits (DESIGN section 3). ``train`` has the preset's ``frames_per_class`` frames per class
(carla-like 4000, rtk-like 400, robotcar-like 2000); ``calibration`` and ``test`` each have
20 % of that (at least 10 per class). The three splits are rendered from independent random
streams derived from ``(seed, split, label)`` (numpy ``SeedSequence``), so they are disjoint
and each is reproducible on its own. Generated splits are kept in a small in-memory cache and
on disk (8-bit ``.npz``) under ``$DRAKE_CERT_DATA_CACHE`` (default: ``data_cache/`` of the
source checkout, git-ignored; an empty value disables it); a file's name carries a hash of
the generator's source (``frames.py`` and ``rng.py``), so a changed generator never
reads stale frames.
"""

from __future__ import annotations

import hashlib
import io as _io
import math
import os
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch

from drake_cert.config import STIFFNESS_PLAUSIBLE, ConditionsTable, load_conditions
from drake_cert.errors import ConfigError
from drake_cert.perception.frames import generate_frames
from drake_cert.perception.frameset import FrameSet

SPLITS = ("train", "calibration", "test")
HELD_OUT_FRACTION = 0.2  # calibration and test size, as a fraction of train, per class
MIN_HELD_OUT_PER_CLASS = 10
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def split_frames_per_class(frames_per_class: int, split: str) -> int:
    """Frames per class of a split: train = the preset's count, calibration/test = 20 % of it."""
    if split == "train":
        return frames_per_class
    return max(MIN_HELD_OUT_PER_CLASS, int(round(HELD_OUT_FRACTION * frames_per_class)))


def split_seed(seed: int, split: str) -> int:
    """A 63-bit seed for one split, independent of the others (numpy SeedSequence)."""
    if split not in SPLITS:
        raise ConfigError(f"unknown split {split!r}; expected one of {', '.join(SPLITS)}")
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed = {seed!r} must be a non-negative integer")
    ss = np.random.SeedSequence([int(seed), 0x5EED, SPLITS.index(split)])
    return int(ss.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


_CACHE: OrderedDict = OrderedDict()
_CACHE_ENTRIES = 4


def load_split(preset: str, split: str, *, seed: int = 0, size: int = 64,
               frames_per_class: int | None = None,
               conditions: ConditionsTable | None = None) -> FrameSet:
    """The ``split`` ("train", "calibration" or "test") of a preset's synthetic frames.

    ``frames_per_class`` overrides the split's count per class (default: the preset's
    count for train, 20 % of it for calibration and test). Same arguments, same bytes.
    """

    table = conditions if conditions is not None else load_conditions()
    p = table.preset(preset)
    count = frames_per_class if frames_per_class is not None else split_frames_per_class(
        p.frames_per_class, split)
    sseed = split_seed(seed, split)
    key = (preset, split, int(seed), int(size), int(count),
           tuple((c.name, c.stiffness_lo_n_per_rad, c.stiffness_hi_n_per_rad)
                 for c in table.preset_conditions(preset)))
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    frames = _read_disk_cache(key)
    if frames is None:
        frames = generate_frames(table, preset, seed=sseed, frames_per_class=count, size=size)
        _write_disk_cache(key, frames)
    _CACHE[key] = frames
    while len(_CACHE) > _CACHE_ENTRIES:
        _CACHE.popitem(last=False)
    return frames


def clear_cache() -> None:
    """Forget every split cached in memory (the disk cache stays)."""
    _CACHE.clear()


def disk_cache_dir() -> Path | None:
    """``$DRAKE_CERT_DATA_CACHE`` ("" disables the cache), else ``data_cache/`` at the root of
    the source checkout this package runs from (the folder holding ``drake_cert/`` and
    ``pyproject.toml``: a clone or an editable install), else None (an installed wheel)."""
    env = os.environ.get("DRAKE_CERT_DATA_CACHE")
    if env is not None:
        return Path(env) if env else None
    root = Path(__file__).resolve().parents[2]  # drake_cert/perception/datasets.py -> root
    return root / "data_cache" if (root / "pyproject.toml").is_file() else None


def _disk_cache_file(key: tuple) -> Path | None:
    folder = disk_cache_dir()
    if folder is None:
        return None
    package = Path(__file__).parents[1]  # the renderer and the generators it draws from
    source = b"".join((package / name).read_bytes()
                      for name in ("perception/frames.py", "rng.py"))
    digest = hashlib.sha256(source + repr(key).encode()).hexdigest()[:20]
    return folder / f"{key[0]}_{key[1]}_{digest}.npz"


def _read_disk_cache(key: tuple) -> FrameSet | None:
    path = _disk_cache_file(key)
    if path is None or not path.exists():
        return None
    try:
        with np.load(path) as z:
            images = torch.from_numpy(z["images"]).float().div_(255.0)
            return FrameSet(images, torch.from_numpy(z["labels"]),
                            torch.from_numpy(z["stiffness"]), [str(n) for n in z["label_names"]],
                            str(z["preset"]))
    except (OSError, KeyError, ValueError):
        return None  # unreadable cache file: regenerate (and overwrite it)


def _write_disk_cache(key: tuple, frames: FrameSet) -> None:
    from drake_cert.io import atomic_write_bytes

    path = _disk_cache_file(key)
    if path is None:
        return
    buf = _io.BytesIO()
    np.savez(buf, images=(frames.images * 255.0).round().to(torch.uint8).numpy(),
             labels=frames.labels.numpy(), stiffness=frames.stiffness_n_per_rad.numpy(),
             label_names=np.array(frames.label_names), preset=np.array(frames.preset))
    try:
        atomic_write_bytes(path, buf.getvalue())
    except OSError:
        pass  # a read-only checkout: no disk cache


def load_image_folder(path: str | Path, *, preset: str | None = None, size: int = 64,
                      conditions: ConditionsTable | None = None) -> FrameSet:
    """Read a class-per-folder directory of PNG/JPEG frames (users' Carla/RTK/RobotCar data).

    ``path/<label>/*.png|jpg|jpeg``; each folder name is a road-condition label. With
    ``preset`` the folders must be labels of that preset and the label order is the preset's;
    without it the folders must exactly be some preset's labels (that preset is used), or
    else names from the conditions table (ordered grippiest first, preset ""). Images are
    converted to RGB and resized to ``size`` x ``size`` (bilinear). A ``path/stiffness.csv``
    (columns ``file,label,stiffness_n_per_rad``, ``file`` relative to ``path``; what
    ``drake-cert generate --export`` writes) gives each listed frame its true stiffness; frames
    it does not list, or every frame without the file, have unknown stiffness (NaN). Raises
    :class:`ConfigError` for a missing folder, unknown labels, no images or a malformed CSV.
    """
    from PIL import Image

    root = Path(path)
    if not root.is_dir():
        raise ConfigError(f"image folder {str(root)!r} does not exist or is not a directory")
    table = conditions if conditions is not None else load_conditions()
    folders = sorted(d for d in root.iterdir() if d.is_dir() and not d.name.startswith("."))
    found = [d.name for d in folders]
    if not found:
        raise ConfigError(f"image folder {str(root)!r} has no class sub-folders")
    label_names, preset_name = _label_order(table, found, preset, root)
    known_stiffness = read_stiffness_csv(root / STIFFNESS_CSV)
    images, labels, stiffness = [], [], []
    for d in folders:
        files = sorted(f for f in d.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
        for f in files:
            try:
                with Image.open(f) as im:
                    im = im.convert("RGB").resize((size, size), Image.Resampling.BILINEAR)
                    arr = np.asarray(im, dtype=np.uint8)
            except OSError as e:
                raise ConfigError(f"cannot read image {str(f)!r}: {e}") from None
            images.append(arr)
            labels.append(label_names.index(d.name))
            stiffness.append(known_stiffness.get(f.relative_to(root).as_posix(), math.nan))
    if not images:
        raise ConfigError(f"image folder {str(root)!r} holds no PNG/JPEG images "
                          f"in its sub-folders {found}")
    x = torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).float().div_(255.0).contiguous()
    y = torch.tensor(labels, dtype=torch.int64)
    c = torch.tensor(stiffness, dtype=torch.float32)
    return FrameSet(x, y, c, label_names, preset_name)


STIFFNESS_CSV = "stiffness.csv"  # beside the class folders: file,label,stiffness_n_per_rad


def read_stiffness_csv(path: Path) -> dict[str, float]:
    """``{relative file: stiffness (N/rad)}`` from a stiffness CSV; {} when there is none."""
    import csv

    if not path.exists():
        return {}
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise ConfigError(f"cannot read {str(path)!r}: {e}") from None
    out = {}
    for i, row in enumerate(rows, start=2):
        try:
            value = float(row["stiffness_n_per_rad"])
            out[str(row["file"]).strip()] = value
        except (KeyError, TypeError, ValueError):
            raise ConfigError(f"{path}:{i}: expected columns file,label,stiffness_n_per_rad "
                              f"with a number, got {dict(row)}") from None
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{path}:{i}: stiffness_n_per_rad = {value!r} must be a "
                              "positive number of N/rad")
        STIFFNESS_PLAUSIBLE.check(value, "stiffness_n_per_rad", f"{path}:{i}")  # kN/rad?
    return out


def _label_order(table: ConditionsTable, found: list[str], preset: str | None,
                 root: Path) -> tuple[list[str], str]:
    """Label order (grippiest first) and preset name for folder names ``found``."""
    if preset is not None:
        labels = table.preset(preset).labels
        unknown = [n for n in found if n not in labels]
        if unknown:
            raise ConfigError(f"{root}: folder {unknown[0]!r} is not a label of preset "
                              f"{preset!r} ({', '.join(labels)})")
        return list(labels), preset
    for p in table.presets:
        if sorted(p.labels) == sorted(found):
            return list(p.labels), p.name
    known = {c.name for c in table.conditions}
    unknown = [n for n in found if n not in known]
    if unknown:
        raise ConfigError(f"{root}: folder {unknown[0]!r} is not a road condition of the "
                          f"conditions table ({', '.join(sorted(known))})")
    order = sorted(found, key=lambda n: -table.condition(n).friction_mu)
    return order, ""
