"""What a reproduction runs: its settings, its seed streams and its models (DESIGN 7, issue 8).

Seeds: one root seed; every stream is a child of ``SeedSequence(root)`` addressed by its spawn
key (:func:`seed_of`): a preset's frame choice ``(preset, FRAME_CHOICE)``, h's calibration
``(preset, CALIBRATION, sigma index)``, g's conformal calibration ``(preset, CONFORMAL, sigma
index)`` and each cell ``(preset, CELL, cell index)``, the index being the cell's place in
:meth:`ReproduceConfig.cells` (a run without regression cells numbers its cells otherwise). A
cell's blocks draw their attack and certificate noise from ``SeedSequence([cell seed,
purpose, frame position])`` (``systems.streams``), so no attack draws the noise of the
certificate it attacks, and a frame's rows can be recomputed alone
(``reproduce.recompute_frame``) with the same numbers, whatever the executor.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from drake_cert.config import load_conditions
from drake_cert.errors import ConfigError

PIPELINES = ("f", "g", "f_reg", "h")
ATTACK_KINDS = ("none", "sa", "ea")

# Purposes of the seed streams (spawn-key entries; distinct by construction). A cell's
# blocks draw their attack and certificate noise from SeedSequence([cell seed, purpose, frame])
# (systems.streams), the cell seed being the root's child (preset, CELL, cell).
FRAME_CHOICE, CALIBRATION, CELL, CONFORMAL = 0, 1, 2, 3


@dataclasses.dataclass(frozen=True)
class ReproduceConfig:
    """What to reproduce; budgets are L2 norms in [0, 1] pixel space."""

    presets: tuple[str, ...] = ("carla-like", "rtk-like", "robotcar-like")
    sigmas: tuple[float, ...] = (0.25, 0.5, 1.0)
    eps: float = 0.25  # budget of the main tables (attack and certificate)
    sweep_eps: tuple[float, ...] = (0.0, 0.25, 0.5, 1.0, 1.5, 2.0)  # classification sweep
    sweep_sigma: float = 0.5  # the g of the sweep
    frames: int = 100  # test frames per preset; every cell sees the same frames
    n0: int = 100
    n: int = 10_000
    alpha: float = 0.001
    batch_size: int = 250  # noisy copies per forward pass (larger batches page-fault: slower)
    attack_steps: int = 20
    attack_noise_draws: int = 8
    regression: bool = True
    calibration_per_class: int = 100  # conformal calibration frames per label
    calibration_n: int = 1000  # samples per calibration frame
    alpha_c: float = 0.01
    alpha_m: float = 0.001
    interval: str = "safe_set"  # g's interval: "safe_set" (paper) or "conformal" (DESIGN 3)
    conformal_per_class: int = 150  # robust conformal calibration frames per label (>= 124)
    conformal_n: int = 500  # samples per conformal calibration frame
    precision: str = "auto"  # model arithmetic of attacks, certificates and calibration alike;
    # "auto" is resolved on construction (sampler.resolve_precision), so results and the run
    # identity always name the arithmetic that ran
    seed: int = 0

    def __post_init__(self):
        from drake_cert.certification.sampler import PRECISION_SETTINGS, resolve_precision

        if self.precision not in PRECISION_SETTINGS:
            raise ConfigError(f"precision {self.precision!r} is not one of "
                              f"{', '.join(PRECISION_SETTINGS)}")
        object.__setattr__(self, "precision", resolve_precision(self.precision))

    @staticmethod
    def quick(seed: int = 0) -> ReproduceConfig:
        """A few frames per cell, small n, one budget: the CI-sized run (< 2 min on 2 cores)."""
        return ReproduceConfig(sigmas=(0.25, 0.5, 1.0), eps=0.25, sweep_eps=(0.25,),
                               sweep_sigma=0.25, frames=2, n0=20, n=200, batch_size=200,
                               attack_steps=4, attack_noise_draws=2, calibration_per_class=6,
                               calibration_n=100, seed=seed)

    def validate(self) -> None:
        conditions = load_conditions()
        known = [p.name for p in conditions.presets]
        for p in self.presets:
            if p not in known:
                raise ConfigError(f"unknown preset {p!r}; expected one of {known}")
        for name in ("frames", "n0", "n", "batch_size", "calibration_per_class",
                     "calibration_n"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name} = {getattr(self, name)} must be a positive integer")
        for s in (*self.sigmas, self.sweep_sigma):
            if not (math.isfinite(s) and s > 0):
                raise ConfigError(f"sigma = {s!r} must be positive")
        for e in (self.eps, *self.sweep_eps):
            if not (math.isfinite(e) and e >= 0):
                raise ConfigError(f"eps = {e!r} must be a finite number >= 0")
        if not 0 < self.alpha < 1:
            raise ConfigError(f"alpha = {self.alpha!r} must be in (0, 1)")
        if self.interval not in ("safe_set", "conformal"):
            raise ConfigError(f"interval {self.interval!r} is not 'safe_set' or 'conformal'")
        for name in ("conformal_per_class", "conformal_n"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name} = {getattr(self, name)} must be a positive integer")
        if self.seed < 0:
            raise ConfigError(f"seed = {self.seed} must be >= 0")

    def cells(self) -> list[tuple[str, float, str, float]]:
        """Every (pipeline, sigma, attack, eps) evaluated on each frame, in a fixed order.

        Main tables: f, g (each sigma), f_reg and h (each sigma), clean and under SA and EA,
        at budget ``eps`` (a clean frame's run-time interval is also taken at ``eps``).
        Sweep: f and g at ``sweep_sigma`` under SA and EA at every other budget (eps = 0:
        g's clean interval at budget 0).
        """
        out: list[tuple[str, float, str, float]] = []
        for kind in ATTACK_KINDS:
            out.append(("f", 0.0, kind, self.eps))
            out.extend(("g", s, kind, self.eps) for s in self.sigmas)
            if self.regression:
                out.append(("f_reg", 0.0, kind, self.eps))
                out.extend(("h", s, kind, self.eps) for s in self.sigmas)
        for eps in sorted(set(self.sweep_eps) - {self.eps}):
            if eps == 0:
                out.append(("g", self.sweep_sigma, "none", 0.0))
                continue
            for kind in ("sa", "ea"):
                out += [("f", 0.0, kind, eps), ("g", self.sweep_sigma, kind, eps)]
        return out


def preset_key(preset: str) -> int:
    """A preset's stable spawn-key entry: its position in the conditions table (not in the
    run's preset list), so a preset gets the same frames and streams in any selection."""
    return [p.name for p in load_conditions().presets].index(preset)


def seed_of(config: ReproduceConfig, *key: int) -> int:
    """A 63-bit integer seed of the stream with spawn key ``key`` under the root seed."""
    from drake_cert.certification.seeds import seed_from_sequence

    return seed_from_sequence(np.random.SeedSequence(entropy=config.seed,
                                                     spawn_key=tuple(int(k) for k in key)))


def frame_indices(config: ReproduceConfig, preset_index: int, labels) -> np.ndarray:
    """The test frames of a preset: round-robin over classes from a seeded permutation."""
    from drake_cert.experiments.perception_eval import select_frames

    return select_frames(labels, config.frames, seed_of(config, preset_index, FRAME_CHOICE))


@dataclasses.dataclass(frozen=True)
class FrameTask:
    preset: str
    position: int  # which of the preset's chosen frames (0 .. frames - 1)


def run_model(config: ReproduceConfig, preset: str, task: str, sigma: float):
    """The shipped model of (preset, task, sigma) in the run's precision: the one module that
    the run's attacks, certificates and calibrations all evaluate."""
    from drake_cert.certification.sampler import with_precision
    from drake_cert.perception.models import load_model

    return with_precision(load_model(preset, task, sigma), config.precision)
