"""The robust conformal calibration's votes, shipped beside each model (docs/design.md 3.6).

A drive's calibration-conditional thresholds (:mod:`drake_cert.certification.pac_conformal`)
need thousands of calibration frames a label; drawing their votes takes minutes on two cores,
so they are computed once per model and shipped as package data beside the ``.pt``:
``<preset>/classify_sigma<S>.calibration.json`` holds the inputs (:class:`VotesSpec`: model
digest, backend, precision, frames per label, samples per frame, noise root, batch size) and,
per calibration frame, its label, true stiffness and the votes for its true label. The
thresholds are a cheap function of these votes and the drive's bins, miss target and
delta_cal (:func:`drake_cert.certification.conformal.pac_calibration_from_counts`).

:func:`calibration_votes` returns the shipped votes when the file's spec equals the wanted one,
else the calibration cache's, else computes them (with the caller's progress bar) and caches
them. The frames are the preset's ``calibration`` split (seed 0) with ``frames_per_label``
frames a label; frame i draws its n samples from ``stream_seed(root_seed, i, "calibration",
split="calibration")``.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from drake_cert.certification.calibration_cache import cached
from drake_cert.errors import CertificationError
from drake_cert.io import atomic_write_text

SCHEMA = 1


@dataclasses.dataclass(frozen=True)
class VotesSpec:
    """Every input of the calibration votes (two specs equal: the same votes)."""

    preset: str
    sigma: float
    model_sha256: str
    backend: str  # as resolved ("onnxruntime" or "torch")
    precision: str  # as resolved ("fp32" or "bf16")
    quantization: str
    frames_per_label: int
    n: int  # samples per calibration frame
    root_seed: int  # noise root of the calibration streams
    batch_size: int
    conditions: tuple[tuple[str, float, float], ...]  # (label, C_lo, C_hi) in preset order

    def to_json(self) -> dict:
        out = dataclasses.asdict(self)
        out["conditions"] = [list(c) for c in self.conditions]
        return out

    @classmethod
    def from_json(cls, data: dict) -> VotesSpec:
        data = dict(data)
        data["conditions"] = tuple((str(a), float(b), float(c)) for a, b, c in data["conditions"])
        return cls(**data)


@dataclasses.dataclass(frozen=True)
class CalibrationVotes:
    """The calibration frames' labels, true stiffness (N/rad) and votes for their true label,
    with the spec that produced them."""

    spec: VotesSpec
    labels: np.ndarray  # (F,) int
    stiffness_n_per_rad: np.ndarray  # (F,) float
    true_counts: np.ndarray  # (F,) int, out of spec.n
    source: str = "computed"  # "shipped", "cache" or "computed"

    def to_json(self) -> dict:
        return {"schema": SCHEMA, "spec": self.spec.to_json(),
                "labels": self.labels.astype(int).tolist(),
                "stiffness_n_per_rad": [float(v) for v in self.stiffness_n_per_rad],
                "true_counts": self.true_counts.astype(int).tolist()}

    @classmethod
    def from_json(cls, data: dict, source: str) -> CalibrationVotes:
        if data.get("schema") != SCHEMA:
            raise CertificationError(f"calibration votes of schema {data.get('schema')!r}; "
                                     f"this version reads schema {SCHEMA}")
        return cls(VotesSpec.from_json(data["spec"]), np.asarray(data["labels"], dtype=np.int64),
                   np.asarray(data["stiffness_n_per_rad"], dtype=np.float64),
                   np.asarray(data["true_counts"], dtype=np.int64), source)


def shipped_path(model_file: str | Path) -> Path:
    """``classify_sigma1.pt`` -> ``classify_sigma1.calibration.json`` beside it."""
    path = Path(model_file)
    return path.with_name(path.stem + ".calibration.json")


def read_shipped(model_file: str | Path) -> CalibrationVotes | None:
    """The votes shipped beside ``model_file``, or None when there is no readable file."""
    try:
        return CalibrationVotes.from_json(json.loads(shipped_path(model_file).read_text()),
                                          "shipped")
    except (OSError, ValueError, KeyError, TypeError, CertificationError):
        return None


def write_shipped(model_file: str | Path, votes: CalibrationVotes) -> Path:
    """Write ``votes`` beside ``model_file`` (atomically)."""
    path = shipped_path(model_file)
    atomic_write_text(path, json.dumps(votes.to_json(), separators=(",", ":")) + "\n")
    return path


def calibration_votes(spec: VotesSpec, model_file: str | Path,
                      compute: Callable[[Callable | None], CalibrationVotes],
                      progress: Callable[[Iterable], Iterable] | None = None, *,
                      refresh: bool = False) -> CalibrationVotes:
    """The shipped votes if their spec is ``spec``, else the cached ones, else
    ``compute(progress)`` (then cached); ``refresh``: always ``compute(progress)``, reading
    neither (what ``drake-cert calibrate --ship`` writes)."""
    if refresh:
        return compute(progress)
    shipped = read_shipped(model_file)
    if shipped is not None and shipped.spec == spec:
        return shipped
    value = cached("conformal_votes", {"spec": spec.to_json()},
                   lambda: compute(progress).to_json())
    return CalibrationVotes.from_json(value, "cache")
