"""What a reproduction runs: its settings, its seed streams and its models (DESIGN 7).

Seeds (the project's one scheme, :mod:`drake_cert.certification.seeds`): every stream is a named
child of the root seed: a preset's frame choice ``frame_choice`` (preset), h's calibration
``regression_calibration`` (preset, sigma), and each cell ``cell`` (:func:`cell_seed`: preset and
what the cell is: pipeline, attack, sigma, budget). A cell's seed is the root of its Diagram
blocks' streams (``attack``, ``selection``, ``estimation``, keyed by the frame's position), as
a scenario's seed is in a drive. So no attack draws the noise of the certificate it attacks, a
cell draws the same noise in any run that has it (whatever presets, pipelines or other cells
the run holds), ``g`` and ``g_conformal`` share theirs (one attack and one certificate, read
by two intervals), and a frame's rows can be recomputed alone (``reproduce.recompute_frame``)
with the same numbers, whatever the executor. g's robust conformal calibration is the drive's,
the model's own (its noise rooted at a constant, whatever the run's seed; docs/design.md 3.6).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from drake_cert.config import load_conditions
from drake_cert.errors import ConfigError
from drake_cert.systems.scenario import PerceptionSettings

_DRIVE = PerceptionSettings()  # the drive's defaults, which g_conformal's calibration shares

# The pipelines of a run. ``g`` reads the paper's safe-set interval off its certificate and
# ``g_conformal`` the robust conformal interval (DESIGN 3) off the same certificate: the same
# frames, attacks and noise, only the interval differs.
PIPELINES = ("f", "g", "g_conformal", "f_reg", "h")
ATTACK_KINDS = ("none", "sa", "ea")
# Whose noise a pipeline's cells draw (a spawn-key entry: the place in NOISE_OWNERS).
NOISE_OWNERS = ("f", "g", "f_reg", "h")
_NOISE_OWNER = {"f": "f", "g": "g", "g_conformal": "g", "f_reg": "f_reg", "h": "h"}
# The paper's "delta = 255" read as an L2 norm over [0, 255] pixel values (docs/design.md 7.1):
# at this budget of the sweep every pipeline runs at every sigma, so that each of the paper's
# claims is tested where its own numbers were measured.
PAPER_BUDGET_EPS = 1.0
# The units of the paper's own figures, as the claims and tables name them beside ours.
PAPER_UNITS = dict(accuracy="% of frames", instability="the paper's own unit, not a share",
                   velocity_mps="unit not stated, ours m/s",
                   mse="unit not stated, ours (kN/rad)^2",
                   certificate_tau="an L2 radius, pixel scale not stated")


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
    regression: bool = True  # the regression pipelines f_reg and h
    conformal: bool = True  # the pipeline g_conformal (g's certificates, robust conformal interval)
    # h's conformal beta: calibration frames per label and samples per frame. At alpha_c 0.01 a
    # label's beta is its ceil(0.99 (m + 1))-th smallest score: with m = 100 the largest, with
    # 400 the 4th largest (carla-like sigma 0.25: run-time beta 11.3 kN/rad with 100 frames at
    # n 1,000, 6.2 with 400 at n 500; docs/results.md)
    calibration_per_class: int = 400
    calibration_n: int = 500
    alpha_c: float = 0.01
    alpha_m: float = 0.001
    # g_conformal's calibration is the drive's (docs/design.md 3.6), with the drive's defaults:
    # the model's votes on conformal_per_class calibration frames a label, conformal_n
    # samples each (shipped beside the sigma-1 models, so those are not drawn again),
    # thresholds calibration-conditional in conformal_bins_per_label stiffness bins a label,
    # each bin's miss rate within conformal_alpha_c outside an event of probability
    # conformal_delta_cal
    conformal_per_class: int = _DRIVE.conformal_frames_per_class
    conformal_n: int = _DRIVE.conformal_calibration_n
    conformal_alpha_c: float = _DRIVE.conformal_alpha_c
    conformal_bins_per_label: int = _DRIVE.conformal_bins_per_label
    conformal_delta_cal: float = _DRIVE.conformal_delta_cal
    precision: str = "auto"  # model arithmetic of attacks, certificates and calibration alike;
    # "auto" is resolved on construction (sampler.resolve_precision), so results and the run
    # identity always name the arithmetic that ran
    seed: int = 0
    # What evaluates the models' noisy samples (certificates and calibrations; the attacks'
    # gradients always run in torch on the CPU, as on a machine without a GPU): "cpu" or a
    # CUDA device, and on the CPU torch or ONNX Runtime ("auto": ONNX Runtime where installed
    # and fp32, as in the Diagram). Resolved on construction; both are in the run identity.
    device: str = "cpu"
    backend: str = "auto"
    # How g's cells read only as a decision at their budget (clean cells and the sweep's) are
    # decided: "sequential" (stop once the label range at eps is decided either way; the
    # robust conformal set likewise) or "fixed" (Cohen's n0 + n). The cells whose radius the
    # tables print (g under SA and EA at the main budget) always keep fixed n.
    decisions: str = "sequential"

    def __post_init__(self):
        from drake_cert.certification.backends import BACKENDS, resolve_backend
        from drake_cert.certification.sampler import PRECISION_SETTINGS, resolve_precision

        if self.precision not in PRECISION_SETTINGS:
            raise ConfigError(f"precision {self.precision!r} is not one of "
                              f"{', '.join(PRECISION_SETTINGS)}")
        object.__setattr__(self, "precision", resolve_precision(self.precision))
        if self.decisions not in ("sequential", "fixed"):
            raise ConfigError(f"decisions {self.decisions!r} is not sequential or fixed")
        if not (self.device == "cpu" or str(self.device).startswith("cuda")):
            raise ConfigError(f"device {self.device!r} is not cpu or cuda[:N]")
        if self.backend not in ("auto", *BACKENDS):
            raise ConfigError(f"backend {self.backend!r} is not one of auto, "
                              f"{', '.join(BACKENDS)}")
        if self.device != "cpu":
            if self.backend == "onnxruntime":
                raise ConfigError("backend onnxruntime runs on the CPU; with a CUDA device the "
                                  "models run in torch (backend auto or torch)")
            object.__setattr__(self, "backend", "torch")
        elif self.backend == "onnxruntime" and self.precision != "fp32":
            # ONNX Runtime runs fp32 only: bf16 is torch's (the CLI refuses the pair if named)
            object.__setattr__(self, "backend", "torch")
        else:
            object.__setattr__(self, "backend", resolve_backend(self.backend, self.precision))

    @staticmethod
    def quick(seed: int = 0) -> ReproduceConfig:
        """A few frames per cell, small n, one budget: the CI-sized run (< 2 min on 2 cores).

        Its robust conformal calibration (6 frames per label, 50 samples each, one stiffness
        bin a label, miss target 0.5 at delta_cal 0.1, which need 5 frames a bin for a
        threshold) checks the plumbing of that pipeline, not its coverage."""
        return ReproduceConfig(sigmas=(0.25, 0.5, 1.0), eps=0.25, sweep_eps=(0.25,),
                               sweep_sigma=0.25, frames=2, n0=20, n=200, batch_size=200,
                               attack_steps=4, attack_noise_draws=2, calibration_per_class=6,
                               calibration_n=100, conformal_per_class=6, conformal_n=50,
                               conformal_alpha_c=0.5, conformal_bins_per_label=1,
                               conformal_delta_cal=0.1, seed=seed)

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
        for name in ("conformal_per_class", "conformal_n", "conformal_bins_per_label"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name} = {getattr(self, name)} must be a positive integer")
        for name in ("conformal_alpha_c", "conformal_delta_cal"):
            if not 0 < getattr(self, name) < 1:
                raise ConfigError(f"{name} = {getattr(self, name)!r} must be in (0, 1)")
        if self.conformal:
            self._check_conformal_frames(conditions)
        if self.seed < 0:
            raise ConfigError(f"seed = {self.seed} must be >= 0")
        check_device(self.device)

    def _check_conformal_frames(self, conditions) -> None:
        """Refuse a g_conformal calibration whose bins are too short for any threshold (as a
        drive's settings are refused), before any vote is drawn."""
        from drake_cert.certification.pac_conformal import min_frames_per_bin

        labels = max(len(conditions.preset(p).labels) for p in self.presets)
        bins = self.conformal_bins_per_label
        need = min_frames_per_bin(self.conformal_alpha_c,
                                  self.conformal_delta_cal / (labels * bins))
        if self.conformal_per_class < bins * need:
            raise ConfigError(
                f"conformal_per_class = {self.conformal_per_class} gives fewer than the {need} "
                f"calibration frames a stiffness bin (of {bins}) that conformal_alpha_c = "
                f"{self.conformal_alpha_c:g} at conformal_delta_cal = "
                f"{self.conformal_delta_cal:g} needs; raise it to at least {bins * need}")

    @property
    def pipelines(self) -> tuple[str, ...]:
        """The pipelines this run evaluates, in :data:`PIPELINES` order."""
        return tuple(p for p in PIPELINES if (self.regression or p not in ("f_reg", "h"))
                     and (self.conformal or p != "g_conformal"))

    def cells(self) -> list[tuple[str, float, str, float]]:
        """Every (pipeline, sigma, attack, eps) evaluated on each frame, in a fixed order.

        Main tables: f, g and g_conformal (each sigma), f_reg and h (each sigma), clean and
        under SA and EA, at budget ``eps`` (a clean frame's run-time interval is also taken at
        ``eps``). Sweep: f, g and g_conformal at ``sweep_sigma`` under SA and EA at every other
        budget (eps = 0: g's clean interval at budget 0); at :data:`PAPER_BUDGET_EPS`, g and
        g_conformal at every sigma and f_reg and h too. Without ``regression``
        (``conformal``) the cells of f_reg and h (g_conformal) are left out; the others do not
        change.
        """
        g_pipes = [p for p in ("g", "g_conformal") if p in self.pipelines]
        out: list[tuple[str, float, str, float]] = []
        for kind in ATTACK_KINDS:
            out.append(("f", 0.0, kind, self.eps))
            out.extend((g, s, kind, self.eps) for g in g_pipes for s in self.sigmas)
            if self.regression:
                out.append(("f_reg", 0.0, kind, self.eps))
                out.extend(("h", s, kind, self.eps) for s in self.sigmas)
        for eps in sorted(set(self.sweep_eps) - {self.eps}):
            if eps == 0:
                out.extend((g, self.sweep_sigma, "none", 0.0) for g in g_pipes)
                continue
            paper = math.isclose(eps, PAPER_BUDGET_EPS)
            sigmas = self.sigmas if paper else (self.sweep_sigma,)
            for kind in ("sa", "ea"):
                out.append(("f", 0.0, kind, eps))
                out.extend((g, s, kind, eps) for g in g_pipes for s in sigmas)
                if paper and self.regression:
                    out.append(("f_reg", 0.0, kind, eps))
                    out.extend(("h", s, kind, eps) for s in self.sigmas)
        return out


@functools.cache  # the shipped conditions table: read once
def preset_key(preset: str) -> int:
    """A preset's stable spawn-key entry: its position in the conditions table (not in the
    run's preset list), so a preset gets the same frames and streams in any selection."""
    return [p.name for p in load_conditions().presets].index(preset)


def noise_cell(cell: tuple[str, float, str, float]) -> tuple[str, float, str, float]:
    """The cell whose attack and certificate ``cell`` shares: itself, or for g_conformal the g
    cell of the same sigma, attack and budget."""
    pipeline, sigma, kind, eps = cell
    return (_NOISE_OWNER[pipeline], sigma, kind, eps)


def cell_seed(config: ReproduceConfig, preset: str, cell: tuple[str, float, str, float]) -> int:
    """The root seed of one cell's streams on every frame of ``preset``: stream ``cell``
    (preset, noise owner, attack, sigma, eps) of the run's root seed, keyed by what the cell is
    (:func:`noise_cell`), not by its place in the run's cell list, so a run with fewer presets,
    pipelines, sigmas or budgets draws the same noise for a cell as the full run."""
    from drake_cert.certification.seeds import Purpose, child_seed, float_key

    owner, sigma, kind, eps = noise_cell(cell)
    return child_seed(config.seed, Purpose.CELL, preset_key(preset), NOISE_OWNERS.index(owner),
                      ATTACK_KINDS.index(kind), float_key(sigma), float_key(eps))


def calibration_seed(config: ReproduceConfig, purpose, preset: str, sigma: float) -> int:
    """The seed of a calibration of (preset, sigma): stream ``purpose`` (preset, sigma) of the
    root (``regression_calibration`` for h's beta, ``conformal_calibration`` for g_conformal)."""
    from drake_cert.certification.seeds import child_seed, float_key

    return child_seed(config.seed, purpose, preset_key(preset), float_key(sigma))


def frame_indices(config: ReproduceConfig, preset: str, labels) -> np.ndarray:
    """The test frames of a preset: round-robin over classes from a seeded permutation
    (stream ``frame_choice`` (preset) of the root seed)."""
    from drake_cert.certification.seeds import Purpose, child_seed
    from drake_cert.experiments.perception_eval import select_frames

    return select_frames(labels, config.frames,
                         child_seed(config.seed, Purpose.FRAME_CHOICE, preset_key(preset)))


@dataclasses.dataclass(frozen=True)
class FrameTask:
    preset: str
    position: int  # which of the preset's chosen frames (0 .. frames - 1)


def max_certifiable_radius(sigma: float, n: int, alpha: float) -> float:
    """An upper bound on the radius any of g's certificates with n estimation samples at level
    alpha can certify: every vote in the range gives p_low <= alpha**(1/n) (one-sided
    Clopper-Pearson at n of n), radius <= sigma Phi^-1(p_low)."""
    from scipy.stats import norm

    return float(sigma * norm.ppf(alpha ** (1.0 / n)))


def radius_cell(config: ReproduceConfig, cell: tuple[str, float, str, float]) -> bool:
    """Whether the tables read a cell's certified radius (g and g_conformal under SA and EA at
    the main budget): such a cell keeps Cohen's fixed-n certificate."""
    pipeline, _, kind, eps = cell
    return pipeline in ("g", "g_conformal") and kind != "none" and eps == config.eps


def check_device(device: str) -> None:
    """:class:`ConfigError` in one line when ``device`` is a CUDA device this machine lacks."""
    if device == "cpu":
        return
    import torch

    if not torch.cuda.is_available():
        raise ConfigError(f"device {device!r}: CUDA is not available here (torch "
                          f"{torch.__version__}); use --device cpu")


def run_model(config: ReproduceConfig, preset: str, task: str, sigma: float):
    """The shipped model of (preset, task, sigma) in the run's precision, a torch module on the
    CPU: what the run's attacks differentiate (and, through :func:`evaluated_run_model`, what
    its certificates and calibrations evaluate)."""
    from drake_cert.certification.sampler import with_precision
    from drake_cert.perception.models import load_model

    return with_precision(load_model(preset, task, sigma), config.precision)


def evaluated_run_model(config: ReproduceConfig, model):
    """The module the run's samplers call for ``model`` (from :func:`run_model`): the model
    itself (torch on the CPU), its ONNX Runtime session (fp32; agrees with torch to float
    rounding), or a copy on the run's CUDA device (the attack keeps the CPU original)."""
    import copy

    from drake_cert.certification.backends import evaluated_model

    if config.device != "cpu":
        return copy.deepcopy(model).to(config.device)
    return evaluated_model(model, backend=config.backend, precision=config.precision)
