"""The project's one seed scheme: every random draw comes from a named stream of a root seed.

A stream is ``numpy.random.SeedSequence(root, spawn_key=(code(purpose), *keys))``: the child
that ``SeedSequence(root).spawn`` would hand out at those positions, addressed directly, so
frame 17's streams do not depend on how many frames were drawn before it. ``purpose`` is a
:class:`Purpose` (or its name); ``keys`` are non-negative integers saying which draw of that
purpose it is (frame, camera tick, segment, preset; floats through :func:`float_key`). Streams
that differ in purpose or key are statistically independent; same root, purpose and keys give
the same draws on any machine. Draw from :func:`torch_generator` (:mod:`drake_cert.rng`,
re-exported here) or a numpy Generator, never from ``torch.Generator().manual_seed``, which
keeps only 32 bits of the seed on the CPU (DESIGN 3.10 says why and what it cost).

Who uses which purpose (keys in parentheses):

- the driving Diagram (root: the scenario's seed): ``route`` (segment), ``camera``,
  ``attack``, ``selection``, ``estimation`` (each keyed by tick); ``regression_calibration``,
  ``conformal_calibration``, ``quantization_calibration`` (no key: once before a drive);
- perception experiments (root: the experiment's seed): ``frame_choice`` (no key); ``attack``,
  ``selection``, ``estimation``, ``attacked_selection``, ``attacked_estimation``,
  ``calibration``, each keyed (split, frame) (:func:`stream_seed`, :func:`streams`); a robust
  conformal calibration draws ``calibration`` (calibration split, frame) of its root;
- the reproduction (root: the run's seed): ``frame_choice`` (preset), ``regression_calibration``
  and ``conformal_calibration`` (preset, sigma), and ``cell`` (preset, pipeline, attack, sigma,
  eps), the root of that cell's Diagram blocks, which draw ``attack``, ``selection`` and
  ``estimation`` keyed by the frame's position, exactly as in a drive.

A purpose's code is its place in :class:`Purpose`: append new purposes at the end, never
reorder (a reorder changes every draw).
"""

from __future__ import annotations

import enum
import math
import struct

import numpy as np

from drake_cert.errors import CertificationError
from drake_cert.rng import mt19937_words as mt19937_words
from drake_cert.rng import torch_generator as torch_generator


class Purpose(enum.Enum):
    """What a stream is for (its spawn-key code is its place in this list, from 1)."""

    FRAME_CHOICE = "frame_choice"  # which test frames an experiment uses
    ATTACK = "attack"  # a PGD attack's random start and its noise draws
    SELECTION = "selection"  # the n0 samples that choose a certificate's label
    ESTIMATION = "estimation"  # the samples that bound a certificate's probabilities
    ATTACKED_SELECTION = "attacked_selection"  # selection at the attacked frame (experiments)
    ATTACKED_ESTIMATION = "attacked_estimation"  # estimation at the attacked frame
    CALIBRATION = "calibration"  # the samples of one calibration frame
    ROUTE = "route"  # a route segment's true stiffness
    CAMERA = "camera"  # the frame rendered (or chosen) at a camera tick
    REGRESSION_CALIBRATION = "regression_calibration"  # the regression's conformal beta
    CONFORMAL_CALIBRATION = "conformal_calibration"  # the robust conformal thresholds
    QUANTIZATION_CALIBRATION = "quantization_calibration"  # int8 calibration frames' noise
    CELL = "cell"  # a reproduction cell: the root of its blocks' streams


_CODE = {p: i for i, p in enumerate(Purpose, start=1)}

SPLITS = ("test", "calibration")
# Per-frame purposes of a perception experiment (keyed by split and frame).
FRAME_PURPOSES = ("attack", "selection", "estimation", "attacked_selection",
                  "attacked_estimation", "calibration")


def _check_int(value, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise CertificationError(f"{what} = {value!r} must be a non-negative integer")
    return int(value)


def _purpose(purpose: Purpose | str) -> Purpose:
    if isinstance(purpose, Purpose):
        return purpose
    try:
        return Purpose(purpose)
    except ValueError:
        raise CertificationError(f"purpose {purpose!r} is not one of "
                                 f"{', '.join(p.value for p in Purpose)}") from None


def float_key(value: float) -> int:
    """A spawn-key entry for a non-negative float (a sigma, a budget): its IEEE-754 bits, so
    every distinct value is its own key and ``0.25`` is the same key on every machine."""
    value = float(value)
    if not (math.isfinite(value) and value >= 0.0):
        raise CertificationError(f"key {value!r} must be a finite number >= 0")
    return int.from_bytes(struct.pack(">d", value + 0.0), "big")  # -0.0 -> 0.0


def child_sequence(root: int, purpose: Purpose | str, *keys: int) -> np.random.SeedSequence:
    """The SeedSequence of stream (purpose, keys) of ``root``: spawn key (code, *keys)."""
    root = _check_int(root, "root seed")
    code = _CODE[_purpose(purpose)]
    return np.random.SeedSequence(root, spawn_key=(code, *(_check_int(k, "key") for k in keys)))


def seed_from_sequence(sequence: np.random.SeedSequence) -> int:
    """A 63-bit integer seed (for :func:`torch_generator` and numpy)."""
    return int(sequence.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


def child_seed(root: int, purpose: Purpose | str, *keys: int) -> int:
    """The 63-bit integer seed of stream (purpose, keys) of ``root`` (for
    :func:`torch_generator` or ``numpy.random.default_rng``)."""
    return seed_from_sequence(child_sequence(root, purpose, *keys))


def child_rng(root: int, purpose: Purpose | str, *keys: int) -> np.random.Generator:
    """A numpy Generator on stream (purpose, keys) of ``root``."""
    return np.random.default_rng(child_sequence(root, purpose, *keys))


# ---------------------------------------------------------------- perception experiments
def stream_sequence(root_seed: int, split: str, frame_index: int,
                    purpose: str) -> np.random.SeedSequence:
    """The SeedSequence of one (split, frame, purpose) of an experiment: stream (purpose,
    split index, frame) of the root."""
    if split not in SPLITS:
        raise CertificationError(f"split {split!r} is not one of {', '.join(SPLITS)}")
    if purpose not in FRAME_PURPOSES:
        raise CertificationError(f"purpose {purpose!r} is not one of "
                                 f"{', '.join(FRAME_PURPOSES)}")
    frame_index = _check_int(frame_index, "frame index")
    return child_sequence(root_seed, purpose, SPLITS.index(split), frame_index)


def streams(root_seed: int, frame_index: int, *, split: str = "test") -> dict[str, int]:
    """Integer seeds of every per-frame purpose of one frame: ``{purpose: seed}``."""
    return {p: seed_from_sequence(stream_sequence(root_seed, split, frame_index, p))
            for p in FRAME_PURPOSES}


def stream_seed(root_seed: int, frame_index: int, purpose: str, *, split: str = "test") -> int:
    """The integer seed of one purpose of one frame (one entry of :func:`streams`)."""
    return seed_from_sequence(stream_sequence(root_seed, split, frame_index, purpose))


def frame_choice_seed(root_seed: int) -> int:
    """The seed that chooses which frames an experiment uses (one per root seed)."""
    return child_seed(root_seed, Purpose.FRAME_CHOICE)
