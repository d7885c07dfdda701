"""The generator's own floor under smoothing noise: a classifier that knows the scene.

A frame is a function ``F(label, severity, scene)`` of its road condition, its severity and
the renderer's random stream (the *scene*: geometry, sky, textures, camera), and the scene is
drawn independently of the label. The *known-scene oracle* is told the scene, not the label
or the severity; it sees ``z = x + delta`` with ``delta ~ N(0, sigma^2 I)`` and names the label
of largest likelihood ``p(z | label, scene)``, averaging the Gaussian density over the
severity (uniform on [0, 1], as the generator draws stiffness uniformly in each interval) on
a grid of midpoints. Labels are equally likely, as in every preset.

Knowing more can only help, so the oracle's error under noise is a lower bound on the noisy
error of every base classifier, up to the grid and the Monte Carlo draws: what part of a
model's tail the generator forces and what part the model adds (docs/design.md 3.2, "How much
of the tail the generator forces"). Its per-frame own-label share is an estimate, not a bound:
a classifier that does not know the scene may spread its errors over other frames.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator

import numpy as np
import torch

from drake_cert.config import ConditionsTable
from drake_cert.errors import ConfigError
from drake_cert.perception.frames import (
    CAMERA_CONTRAST,
    render_frames,
    severity_from_stiffness,
    style_for,
)
from drake_cert.rng import torch_generator


def severity_grid(points: int) -> torch.Tensor:
    """The midpoints of ``points`` equal cells of [0, 1]: the oracle's severity quadrature."""
    if isinstance(points, bool) or not isinstance(points, int) or points < 1:
        raise ConfigError(f"severity grid points = {points!r} must be a positive integer")
    return (torch.arange(points, dtype=torch.float32) + 0.5) / points


def render_scene(label: str, severities: torch.Tensor, scene_seed: int, *, size: int = 64,
                 contrast: float = 1.0) -> torch.Tensor:
    """The frames of one scene at each severity: float32 [K, 3, size, size].

    Each severity is rendered alone from a fresh generator seeded with ``scene_seed``, so
    every frame shares the scene's geometry, textures and camera (the renderer's draws do not
    depend on the severity); only the condition's intensity changes.
    """
    style = style_for(label)
    return torch.cat([render_frames(style, s.reshape(1), generator=torch_generator(scene_seed),
                                    size=size, contrast=contrast) for s in severities])


@dataclasses.dataclass(frozen=True)
class OracleFrame:
    """One frame and what the oracle knows about its scene."""

    label: int  # index of the true road condition in the preset
    severity: float  # the frame's severity in [0, 1] (1 = least grip in its interval)
    stiffness_n_per_rad: float
    image: torch.Tensor  # [3, size, size] in [0, 1]
    candidates: torch.Tensor  # [labels, grid, 3 * size * size]: the scene at every label, grid


def oracle_frames(conditions: ConditionsTable, preset: str, *, frames_per_class: int,
                  seed: int, grid_points: int = 16, size: int = 64) -> Iterator[OracleFrame]:
    """Frames of ``preset`` (``frames_per_class`` a label, label by label), each with its scene
    rendered at every label and grid severity. Deterministic by ``seed``; the scenes are not
    the training or test splits' (their own seeds), but drawn from the same distribution."""
    if isinstance(frames_per_class, bool) or not isinstance(frames_per_class, int) \
            or frames_per_class < 1:
        raise ConfigError(f"frames_per_class = {frames_per_class!r} must be a positive integer")
    table = conditions.preset_conditions(preset)
    names = [c.name for c in table]
    grid = severity_grid(grid_points)
    contrast = CAMERA_CONTRAST.get(preset, 1.0)
    for k, cond in enumerate(table):
        lo, hi = cond.interval
        stiffness_rng = np.random.default_rng([int(seed), k])
        for i in range(frames_per_class):
            stiffness = lo + (hi - lo) * float(stiffness_rng.random())
            severity = float(severity_from_stiffness(torch.tensor(stiffness), lo, hi))
            scene = int(np.random.SeedSequence([int(seed), k, i, 1]).generate_state(
                1, dtype=np.uint64)[0] >> 1)
            image = render_scene(cond.name, torch.tensor([severity]), scene, size=size,
                                 contrast=contrast)[0]
            candidates = torch.stack([render_scene(name, grid, scene, size=size,
                                                   contrast=contrast).flatten(1)
                                      for name in names])
            yield OracleFrame(k, severity, stiffness, image, candidates)


def known_scene_votes(frame: OracleFrame, sigma: float, draws: int,
                      generator: torch.Generator) -> np.ndarray:
    """How many of ``draws`` noisy copies of the frame the oracle gives each label, [L].

    Per copy z, the oracle's score of label l is ``log mean_k exp(-|z - r_lk|^2 / (2 sigma^2))``
    over the scene's renders ``r_lk`` at the grid severities; it names the largest.
    """
    if not (isinstance(sigma, (int, float)) and math.isfinite(sigma) and sigma > 0):
        raise ConfigError(f"sigma = {sigma!r} must be a positive finite number")
    if isinstance(draws, bool) or not isinstance(draws, int) or draws < 1:
        raise ConfigError(f"draws = {draws!r} must be a positive integer")
    renders = frame.candidates.double()  # [L, K, D]
    labels, grid, dim = renders.shape
    flat = renders.reshape(labels * grid, dim)
    z = frame.image.double().reshape(1, dim) + sigma * torch.randn(
        draws, dim, generator=generator, dtype=torch.float64)
    # -|z - r|^2 / (2 sigma^2) up to the term in |z|^2, which every candidate shares
    loglik = (z @ flat.T - 0.5 * (flat * flat).sum(dim=1)) / sigma**2
    score = torch.logsumexp(loglik.reshape(draws, labels, grid), dim=2)
    return np.bincount(score.argmax(dim=1).numpy(), minlength=labels)
