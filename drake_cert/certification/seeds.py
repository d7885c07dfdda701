"""Independent random streams for an experiment, all from one root seed (DESIGN 3).

Every random draw of a perception experiment belongs to one *purpose* and, for per-frame
purposes, to one frame of one split. Each (split, frame, purpose) gets its own stream,
a child of ``numpy.random.SeedSequence(root_seed)`` reached by the spawn key
``(split, frame_index, purpose)`` -- exactly the child that ``SeedSequence.spawn`` would
hand out at those positions, but addressable directly, so that frame 17's streams do not
depend on how many frames run before it. SeedSequence hashes the root entropy together with
the spawn key, so distinct keys give statistically independent streams (and, in practice,
distinct 63-bit seeds: :func:`streams` is tested to give 10,000 distinct seeds).

Purposes (per frame):

- ``attack``: the PGD random start and the noise draws of the SmoothAdv objective;
- ``selection``: the n0 samples that choose the certificate's label;
- ``estimation``: the n samples that bound the label probabilities (clean frame);
- ``attacked_selection`` / ``attacked_estimation``: the same at the attacked frame;
- ``calibration``: the samples of a calibration frame (split "calibration").

One stream per root seed, not per frame: ``frame_choice`` (which test frames are used).

Why: the certificate's guarantee is over noise the attacker does not know, and the conformal
guarantee needs calibration noise independent of test noise. Adding offsets to one integer
seed (``seed + i``, ``seed + 500_000``) made the attack stream of one frame the certificate
stream of another; spawned streams cannot collide that way.
"""

from __future__ import annotations

import numpy as np

from drake_cert.errors import CertificationError

SPLITS = ("test", "calibration")
PURPOSES = ("attack", "selection", "estimation", "attacked_selection", "attacked_estimation",
            "calibration")
_FRAME_CHOICE_KEY = 2  # spawn key of the root-level frame-choice stream (splits use 0, 1)


def _check_seed(root_seed: int) -> int:
    if isinstance(root_seed, bool) or not isinstance(root_seed, (int, np.integer)) \
            or root_seed < 0:
        raise CertificationError(f"root seed = {root_seed!r} must be a non-negative integer")
    return int(root_seed)


def seed_from_sequence(sequence: np.random.SeedSequence) -> int:
    """A 63-bit integer seed (fits ``torch.Generator.manual_seed`` and numpy)."""
    return int(sequence.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


def stream_sequence(root_seed: int, split: str, frame_index: int,
                    purpose: str) -> np.random.SeedSequence:
    """The SeedSequence of one (split, frame, purpose): spawn key (split, frame, purpose)."""
    root_seed = _check_seed(root_seed)
    if split not in SPLITS:
        raise CertificationError(f"split {split!r} is not one of {', '.join(SPLITS)}")
    if purpose not in PURPOSES:
        raise CertificationError(f"purpose {purpose!r} is not one of {', '.join(PURPOSES)}")
    if isinstance(frame_index, bool) or not isinstance(frame_index, (int, np.integer)) \
            or frame_index < 0:
        raise CertificationError(f"frame index = {frame_index!r} must be an integer >= 0")
    return np.random.SeedSequence(root_seed, spawn_key=(SPLITS.index(split), int(frame_index),
                                                        PURPOSES.index(purpose)))


def streams(root_seed: int, frame_index: int, *, split: str = "test") -> dict[str, int]:
    """Integer seeds of every purpose of one frame: ``{purpose: seed}`` (see module doc).

    Use them with ``torch.Generator().manual_seed(seed)`` or ``numpy.random.default_rng(seed)``.
    """
    return {p: seed_from_sequence(stream_sequence(root_seed, split, frame_index, p))
            for p in PURPOSES}


def stream_seed(root_seed: int, frame_index: int, purpose: str, *, split: str = "test") -> int:
    """The integer seed of one purpose of one frame (one entry of :func:`streams`)."""
    return seed_from_sequence(stream_sequence(root_seed, split, frame_index, purpose))


def frame_choice_seed(root_seed: int) -> int:
    """The seed that chooses which frames an experiment uses (one per root seed)."""
    root = _check_seed(root_seed)
    return seed_from_sequence(np.random.SeedSequence(root, spawn_key=(_FRAME_CHOICE_KEY,)))
