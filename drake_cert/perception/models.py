"""Perception models (DESIGN section 3): a small ResNet classifier and the stiffness regressor.

The classifier f maps a frame in [0, 1] pixel space to logits over a preset's labels; trained
with Gaussian noise at sigma (Cohen et al. 2019) it is the base model of randomized smoothing,
and sigma = 0 is the paper's non-robust f. The regressor (paper: ResNet features + linear
SVR) is, by default, a one-output :class:`SmallResNet` trained end to end under Gaussian noise
(backbone initialised from the classifier at the same sigma) whose output is the cornering
stiffness per tire in N/rad, [B, 1]; the older regressor is the classifier's frozen
convolutional features plus a linear head (:class:`StiffnessRegressor`, output [B]).

Files: one model per file, ``<root>/<preset>/<task>_sigma<S>.pt`` with root
``drake_cert/data/models`` by default. A classifier file holds its weights (kind
"classifier"); an end-to-end regressor file holds its full one-output network (kind
"regressor_net"); a head regressor file holds its head and the SHA-256 of the classifier
file whose features it uses (kind "regressor"; both are loaded together). Every file carries
provenance (command line, git revision, seed, schema version) and the label names, sigma and
training metrics.
"""

from __future__ import annotations

import hashlib
import io as _io
import math
from importlib import resources
from pathlib import Path

import torch
from torch import nn

from drake_cert.errors import ConfigError, ModelNotFoundError
from drake_cert.io import SCHEMA_VERSION, atomic_write_bytes

TASKS = ("classify", "regress")
MODEL_FORMAT = "drake-cert-model"


class BasicBlock(nn.Module):
    """Two 3x3 convolutions with batch norm and an identity (or 1x1 projection) shortcut."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.shortcut = nn.Identity()
        if stride != 1 or cin != cout:
            self.shortcut = nn.Sequential(nn.Conv2d(cin, cout, 1, stride=stride, bias=False),
                                          nn.BatchNorm2d(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = torch.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return torch.relu(out + self.shortcut(x))


class ConvFeatures(nn.Module):
    """Stride-2 stem, three residual stages (w, 2w, 4w channels), global average pooling.

    Input: frames [B, 3, H, W] in [0, 1]; output: features [B, 4w]. ``pool`` > 1 first averages
    pool x pool pixel blocks (part of the model: the smoothing noise is still added to the full
    frame, and certificates are in its pixel space; DESIGN 3.2): each convolution then costs
    1/pool^2 as much.
    """

    def __init__(self, width: int = 16, pool: int = 1):
        super().__init__()
        self.width, self.pool = width, pool
        self.average = nn.AvgPool2d(pool) if pool > 1 else nn.Identity()
        self.stem = nn.Sequential(nn.Conv2d(3, width, 3, stride=2, padding=1, bias=False),
                                  nn.BatchNorm2d(width), nn.ReLU())
        self.stages = nn.Sequential(BasicBlock(width, width),
                                    BasicBlock(width, 2 * width, stride=2),
                                    BasicBlock(2 * width, 4 * width, stride=2))
        self.out_dim = 4 * width

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = (self.average(x) - 0.5) * 4.0  # centre [0, 1] pixels; the scale is the model's
        return self.stages(self.stem(x)).mean(dim=(2, 3))


class SmallResNet(nn.Module):
    """ResNet-style classifier: ``features(x) -> [B, F]`` and ``forward(x) -> logits [B, K]``."""

    def __init__(self, num_classes: int, width: int = 16, pool: int = 1):
        super().__init__()
        self.num_classes = num_classes
        self.width, self.pool = width, pool
        self.backbone = ConvFeatures(width, pool)
        self.fc = nn.Linear(self.backbone.out_dim, num_classes)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        return self.backbone(x)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(self.backbone(x))


class StiffnessRegressor(nn.Module):
    """Frozen convolutional features + linear head: frames [B, 3, H, W] -> stiffness (N/rad) [B]."""

    def __init__(self, features: nn.Module, head: nn.Linear):
        super().__init__()
        self.features = features
        self.head = head
        for p in self.features.parameters():
            p.requires_grad_(False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x)).squeeze(-1)


# --------------------------------------------------------------------------- files

def default_root() -> Path:
    """Folder of the shipped weights: ``drake_cert/data/models``."""
    return Path(str(resources.files("drake_cert.data"))) / "models"


def sigma_tag(sigma: float) -> str:
    """Canonical text of a noise level in file names and commands ('0', '0.25', '1')."""
    return f"{check_sigma(sigma):g}"


def check_sigma(sigma) -> float:
    """sigma as a float, or :class:`ConfigError` unless it is finite and >= 0."""
    try:
        value = float(sigma)
    except (TypeError, ValueError):
        raise ConfigError(f"sigma = {sigma!r} is not a number") from None
    if not math.isfinite(value) or value < 0:
        raise ConfigError(f"sigma = {sigma!r} must be a finite number >= 0")
    return value


def check_task(task: str) -> str:
    if task not in TASKS:
        raise ConfigError(f"unknown task {task!r}; expected one of {', '.join(TASKS)}")
    return task


def model_path(preset: str, task: str, sigma: float, root: str | Path | None = None) -> Path:
    """``<root>/<preset>/<task>_sigma<S>.pt`` (root: the shipped ``drake_cert/data/models``)."""
    check_task(task)
    base = Path(root) if root is not None else default_root()
    return base / preset / f"{task}_sigma{sigma_tag(sigma)}.pt"


def train_command(preset: str, task: str, sigma: float, root: str | Path | None = None) -> str:
    """The command line that makes a model file."""
    cmd = f"drake-cert train --preset {preset} --task {task} --sigma {sigma_tag(sigma)}"
    if root is not None:
        cmd += f" --models {root}"
    return cmd


def file_sha256(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def save_model(model: nn.Module, path: str | Path, *, meta: dict) -> Path:
    """Write a classifier or regressor atomically with ``meta`` (provenance, labels, metrics).

    A :class:`SmallResNet` with one output, or any whose meta says task "regress" (a band
    regressor's two outputs), is stored whole as kind "regressor_net" (an end-to-end
    regressor, outputs N/rad). A head regressor's meta must name its classifier
    file (``classifier_file``, relative to the regressor's folder) and its SHA-256
    (``classifier_sha256``); only the head is stored.
    """
    if isinstance(model, SmallResNet):  # one output, or a regress task: an end-to-end regressor
        regress = model.num_classes == 1 or meta.get("task") == "regress"
        kind = "regressor_net" if regress else "classifier"
        payload = {"kind": kind, "num_classes": model.num_classes,
                   "width": model.width, "pool": model.pool,
                   "state_dict": {k: v.detach().clone() for k, v in model.state_dict().items()}}
    elif isinstance(model, StiffnessRegressor):
        for key in ("classifier_file", "classifier_sha256"):
            if key not in meta:
                raise ValueError(f"a regressor's meta needs {key!r}")
        payload = {"kind": "regressor",
                   "head": {k: v.detach().clone() for k, v in model.head.state_dict().items()}}
    else:
        raise TypeError(f"cannot save a {type(model).__name__}")
    payload.update({"format": MODEL_FORMAT, "schema_version": SCHEMA_VERSION, "meta": dict(meta)})
    buf = _io.BytesIO()
    torch.save(payload, buf)
    return atomic_write_bytes(path, buf.getvalue())


def read_model_file(path: str | Path) -> dict:
    """The raw payload of a model file (weights-only unpickling)."""
    path = Path(path)
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise ModelNotFoundError(f"model file {str(path)!r} does not exist") from None
    except Exception as e:  # torch raises several types for corrupt files
        raise ConfigError(f"model file {str(path)!r} cannot be read ({type(e).__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") != MODEL_FORMAT:
        raise ConfigError(f"{str(path)!r} is not a drake-cert model file")
    if payload.get("schema_version") != SCHEMA_VERSION:
        raise ConfigError(f"{str(path)!r} has schema version {payload.get('schema_version')}, "
                          f"expected {SCHEMA_VERSION}")
    return payload


def load_model_file(path: str | Path) -> nn.Module:
    """Load a model file in eval mode: a classifier ([B, K] logits), an end-to-end regressor
    (one-output :class:`SmallResNet`, [B, 1] N/rad) or a head regressor with its classifier
    (:class:`StiffnessRegressor`, [B] N/rad).

    The model's ``meta`` dict is attached as ``model.meta``.
    """
    path = Path(path)
    payload = read_model_file(path)
    if payload["kind"] in ("classifier", "regressor_net"):
        model = SmallResNet(payload["num_classes"], width=payload["width"],
                            pool=payload.get("pool", 1))  # files before pooling: 1
        model.load_state_dict(payload["state_dict"])
    elif payload["kind"] == "regressor":
        meta = payload["meta"]
        cpath = path.parent / meta["classifier_file"]
        if not cpath.exists():
            raise ModelNotFoundError(f"regressor {str(path)!r} needs classifier {str(cpath)!r}, "
                                     "which does not exist")
        if file_sha256(cpath) != meta["classifier_sha256"]:
            raise ConfigError(f"regressor {str(path)!r} was fitted on another version of "
                              f"{str(cpath)!r}; refit it (drake-cert train --task regress ...)")
        classifier = load_model_file(cpath)
        weight = payload["head"]["weight"]
        head = nn.Linear(weight.shape[1], 1, dtype=weight.dtype)
        head.load_state_dict(payload["head"])
        model = StiffnessRegressor(classifier.backbone, head)
    else:
        raise ConfigError(f"{str(path)!r}: unknown model kind {payload['kind']!r}")
    model.meta = payload["meta"]
    return model.eval()


def load_model(preset: str, task: str, sigma: float, root: str | Path | None = None) -> nn.Module:
    """The trained model for (preset, task, sigma), in eval mode, with ``.meta``.

    Raises :class:`ModelNotFoundError` naming the ``drake-cert train`` command that makes it.
    """
    path = model_path(preset, task, sigma, root)
    if not path.exists():
        raise ModelNotFoundError(f"no trained {task} model for preset {preset!r} at sigma "
                                 f"{sigma_tag(sigma)} ({path}); make it with: "
                                 f"{train_command(preset, task, sigma, root)}")
    return load_model_file(path)


def training_of(model: nn.Module) -> dict:
    """How the model was trained, from its metadata: ``{"method": ..., parameters}``. Files
    written before the method was recorded were all trained one way: classifiers by
    Gaussian augmentation; regressors end to end, or a ridge head when their metadata names
    the classifier the head was fitted on."""
    meta = getattr(model, "meta", {}) or {}
    if "training" in meta:
        return dict(meta["training"])
    if meta.get("task") == "regress":
        return {"method": "ridge_head" if "classifier_file" in meta else "huber_end_to_end"}
    return {"method": "gaussian"}
