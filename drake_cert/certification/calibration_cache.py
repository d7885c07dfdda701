"""A disk cache of calibrations a drive computes before it starts (DESIGN 3.6).

A calibration is a deterministic function of its inputs (model file, evaluation backend and
precision, settings, seeds: DESIGN 3.10), so a drive can reuse one computed earlier instead of
drawing its samples again (the robust conformal calibration of a robotcar-like drive is
450 frames x 1,000 samples, about four minutes on one core). The key holds every input and a
digest of the source files that compute it, so a change of code or model computes anew; an
entry is written atomically and read back only if its stored key equals the wanted one.

Location: ``$DRAKE_CERT_CACHE`` or ``~/.cache/drake-cert``; ``DRAKE_CERT_CACHE=off`` turns
it off. Deployment drives (fresh noise, ``seed: null``) are never cached.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path

from drake_cert.io import atomic_write_text

CACHE_ENV = "DRAKE_CERT_CACHE"

# The modules whose code determines a calibration's numbers (frames, noise, model evaluation).
_SOURCES = ("certification/conformal.py", "certification/classifier.py",
            "certification/sampler.py", "certification/seeds.py",
            "certification/backends.py", "certification/statistics.py",
            "perception/frames.py", "perception/datasets.py", "rng.py")


@functools.cache
def code_digest() -> str:
    """SHA-256 of the source files that compute a calibration."""
    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    for name in _SOURCES:
        h.update(name.encode())
        h.update((root / name).read_bytes())
    return h.hexdigest()


def cache_dir() -> Path | None:
    """The cache folder, or None when caching is off."""
    value = os.environ.get(CACHE_ENV, "").strip()
    if value.lower() == "off":
        return None
    return Path(value) if value else Path.home() / ".cache" / "drake-cert"


def cached(kind: str, key: dict, compute: Callable[[], dict]) -> dict:
    """``compute()`` (a JSON-ready dict), or the one stored under ``(kind, key)``.

    ``key`` must hold every input of the computation (JSON-ready); the code digest is added.
    """
    folder = cache_dir()
    if folder is None:
        return compute()
    full = {"kind": kind, "code": code_digest(), **key}
    text = json.dumps(full, sort_keys=True)
    path = folder / f"{kind}-{hashlib.sha256(text.encode()).hexdigest()[:32]}.json"
    try:
        stored = json.loads(path.read_text())
        if stored.get("key") == json.loads(text):
            return stored["value"]
    except (OSError, ValueError, KeyError, AttributeError):
        pass  # absent or unreadable: compute anew
    value = compute()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps({"key": full, "value": value}, sort_keys=True))
    except OSError:
        pass  # a read-only home: the drive goes on without a cache
    return value
