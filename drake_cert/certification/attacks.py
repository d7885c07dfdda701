"""L2 PGD attacks on the perception model (paper section V, DESIGN 3).

Both attacks live in [0, 1] pixel space, where the smoothing noise is added and budgets are
measured: ``||x_adv - x||_2 <= eps`` and ``0 <= x_adv <= 1``.

- Stability attack (SA): raise the predicted stiffness. Classifier: maximise the probability
  of the labels grippier than the frame's clean prediction a (labels 0..a-1; presets list
  labels grippiest first), i.e. push towards the grippiest label; a frame already predicted
  grippiest is pushed to stay there. Regressor: push the output up (against the smoothed
  model: its median, the quantity the certificate bounds; see :func:`regressor_objective`).
- Efficiency attack (EA): lower it. Classifier: the labels less grippy than a (a+1..K-1).
  Regressor: push the output down.

Against the base model f (``sigma = 0``) the attack follows f's gradient. Against the smoothed
model it follows the expectation over the noise (Salman et al. 2019, SmoothAdv): each step
averages the softmax (classifier) over ``noise_draws`` Gaussian draws of the current iterate;
for the regressor it takes a smooth median of the outputs over the draws (the certificate
bounds the smoothed median; ``regression_target="mean"`` averages them instead).
Deterministic by seed (random start and noise draws use seeded ``torch.Generator`` streams,
one for the batch or one per frame).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import numpy as np
import torch
from scipy.stats import beta as beta_dist

from drake_cert.certification.regressor import band_columns
from drake_cert.errors import CertificationError
from drake_cert.rng import torch_generator

ATTACKS = ("sa", "ea")
REGRESSION_TARGETS = ("median", "central", "mean")
MEDIAN_CENTRAL_FRACTION = 0.25  # share of the noisy outputs averaged by the median surrogate


@dataclasses.dataclass(frozen=True)
class AttackSettings:
    """PGD settings; budgets are L2 norms in [0, 1] pixel space."""

    eps: float  # L2 budget
    steps: int = 20  # PGD iterations
    step_size: float | None = None  # L2 length of each step; None: 2.5 * eps / steps (Madry)
    noise_draws: int = 8  # m, noise draws per step against a smoothed model (SmoothAdv)
    random_start: bool = True  # start from a random point of the ball
    seed: int = 0
    regression_target: str = "median"  # smoothed regressor: "median" (certified) or "mean"

    def validate(self) -> None:
        if not (math.isfinite(self.eps) and self.eps >= 0):
            raise CertificationError(f"attack eps = {self.eps!r} must be a finite number >= 0")
        if self.steps < 0:
            raise CertificationError(f"attack steps = {self.steps} must be >= 0")
        if self.step_size is not None and not self.step_size > 0:
            raise CertificationError(f"attack step_size = {self.step_size!r} must be positive")
        if self.noise_draws < 1:
            raise CertificationError(f"attack noise_draws = {self.noise_draws} must be >= 1")
        if self.regression_target not in REGRESSION_TARGETS:
            raise CertificationError(f"attack regression_target = {self.regression_target!r} "
                                     f"is not one of {', '.join(REGRESSION_TARGETS)}")

    @property
    def step_length(self) -> float:
        if self.step_size is not None:
            return float(self.step_size)
        return 2.5 * self.eps / max(self.steps, 1)


def _per_frame_norm(t: torch.Tensor) -> torch.Tensor:
    """L2 norm of each frame of a [B, ...] tensor, shaped [B, 1, 1, 1] for broadcasting."""
    return t.flatten(1).norm(dim=1).clamp_min(1e-12).view(-1, *([1] * (t.dim() - 1)))


def project_l2_box(x: torch.Tensor, x_adv: torch.Tensor, eps: float) -> torch.Tensor:
    """Projection onto {z : ||z - x||_2 <= eps} followed by clipping to [0, 1].

    Clipping moves every pixel towards x (x is in [0, 1]), so the result stays in the ball.
    """
    delta = x_adv - x
    delta = delta * torch.clamp(eps / _per_frame_norm(delta), max=1.0)
    return torch.clamp(x + delta, 0.0, 1.0)


class FrameNoise:
    """The attack's random draws: one seeded generator for the whole batch, or one per frame.

    With ``frame_seeds`` every frame's random start and noise draws come from its own stream
    (:mod:`drake_cert.certification.seeds`), independent of how frames are batched.
    """

    def __init__(self, seed: int, batch: int, device: torch.device,
                 frame_seeds: Sequence[int] | None = None):
        if frame_seeds is None:
            self.generators = [torch_generator(int(seed), device)]
            self.per_frame = False
        else:
            if len(frame_seeds) != batch:
                raise CertificationError(f"{len(frame_seeds)} frame seeds for {batch} frames")
            self.generators = [torch_generator(int(s), device) for s in frame_seeds]
            self.per_frame = True
        self.device = device

    def _draw(self, fn, shape: tuple[int, ...], batch_axis: int, dtype) -> torch.Tensor:
        if not self.per_frame:
            return fn(shape, generator=self.generators[0], device=self.device, dtype=dtype)
        one = shape[:batch_axis] + shape[batch_axis + 1:]
        return torch.stack([fn(one, generator=g, device=self.device, dtype=dtype)
                            for g in self.generators], dim=batch_axis)

    def randn(self, shape: tuple[int, ...], batch_axis: int, dtype) -> torch.Tensor:
        return self._draw(torch.randn, tuple(shape), batch_axis, dtype)

    def rand(self, shape: tuple[int, ...], batch_axis: int, dtype) -> torch.Tensor:
        return self._draw(torch.rand, tuple(shape), batch_axis, dtype)


def pgd_l2(objective: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor,
           settings: AttackSettings, frame_seeds: Sequence[int] | None = None, *,
           noise: FrameNoise | None = None) -> torch.Tensor:
    """Projected gradient ascent of ``objective`` (per-frame values [B]) in the L2 ball.

    Each step moves ``step_length`` along the per-frame normalised gradient, then projects
    onto the ball of radius eps around x intersected with [0, 1]. Returns the last iterate,
    detached, [B, C, H, W]. Random draws: ``settings.seed`` for the batch, or one stream
    per frame from ``frame_seeds`` (:class:`FrameNoise`), or ``noise`` (streams already in use).
    """
    settings.validate()
    x = x.detach()
    gen = noise if noise is not None else FrameNoise(settings.seed, x.shape[0], x.device,
                                                     frame_seeds)
    x_adv = x.clone()
    if settings.eps == 0 or settings.steps == 0:
        return x_adv
    if settings.random_start:
        start = gen.randn(tuple(x.shape), 0, x.dtype)
        radius = gen.rand((x.shape[0],) + (1,) * (x.dim() - 1), 0, x.dtype) * settings.eps
        x_adv = project_l2_box(x, x + start / _per_frame_norm(start) * radius, settings.eps)
    for _ in range(settings.steps):
        x_adv.requires_grad_(True)
        with torch.enable_grad():
            value = objective(x_adv, gen).sum()
            (grad,) = torch.autograd.grad(value, x_adv)
        x_adv = x_adv.detach() + settings.step_length * grad / _per_frame_norm(grad)
        x_adv = project_l2_box(x, x_adv, settings.eps)
    return x_adv.detach()


def _noisy_copies(x: torch.Tensor, sigma: float, draws: int,
                  gen: FrameNoise) -> torch.Tensor:
    """[draws * B, C, H, W]: ``draws`` Gaussian-noised copies of each frame (draw-major)."""
    noise = gen.randn((draws,) + tuple(x.shape), 1, x.dtype) * sigma
    return (x.unsqueeze(0) + noise).flatten(0, 1)


def classifier_objective(model: torch.nn.Module, targets: torch.Tensor, sigma: float,
                         noise_draws: int) -> Callable:
    """log P(label in targets) per frame: of f's softmax (sigma = 0) or of the softmax averaged
    over noise draws (SmoothAdv). ``targets`` is a [B, K] 0/1 mask of the wanted labels."""

    def objective(x: torch.Tensor, gen: FrameNoise) -> torch.Tensor:
        if sigma == 0:
            probs = torch.softmax(model(x), dim=1)
        else:
            probs = torch.softmax(model(_noisy_copies(x, sigma, noise_draws, gen)), dim=1)
            probs = probs.view(noise_draws, x.shape[0], -1).mean(dim=0)
        return torch.log((probs * targets).sum(dim=1).clamp_min(1e-12))

    return objective


def target_labels(predicted: torch.Tensor, num_classes: int, kind: str) -> torch.Tensor:
    """[B, K] mask of the labels an attack pushes towards, from the clean prediction a.

    SA: labels 0..a-1 (grippier; {0} when a = 0); EA: a+1..K-1 (less grippy; {K-1} when
    a = K-1).
    """
    labels = torch.arange(num_classes, device=predicted.device).view(1, -1)
    a = predicted.view(-1, 1)
    if kind == "sa":
        mask = (labels < a) | ((a == 0) & (labels == 0))
    else:
        mask = (labels > a) | ((a == num_classes - 1) & (labels == num_classes - 1))
    return mask.to(torch.float32)


def harrell_davis_median(values: torch.Tensor) -> torch.Tensor:
    """Harrell-Davis median along dim 0: ``sum_i w_i y_(i)`` with Beta((m+1)/2, (m+1)/2) weights
    ``w_i = I_{i/m} - I_{(i-1)/m}`` (I the regularised incomplete beta function).

    A smooth L-estimator of the median: every order statistic gets a weight peaked at the
    middle rank, so the gradient reaches all draws (lower variance than the sample median) yet
    follows the median, not the mean, of a skewed or bimodal output distribution.
    """
    m = values.shape[0]
    a = (m + 1) / 2
    edges = beta_dist.cdf(np.arange(m + 1) / m, a, a)
    weights = torch.as_tensor(np.diff(edges), dtype=values.dtype, device=values.device)
    ordered = torch.sort(values, dim=0).values
    return (weights.view(-1, *([1] * (values.dim() - 1))) * ordered).sum(dim=0)


def central_mean(values: torch.Tensor, fraction: float = MEDIAN_CENTRAL_FRACTION
                 ) -> torch.Tensor:
    """Differentiable median surrogate along dim 0: the mean of the central order statistics.

    Of m values, the central c = max(round(fraction * m), 1 or 2) order statistics, with c of
    the same parity as m so that they sit symmetrically about the median (m = 8: the 4th and
    5th, i.e. the sample median itself). The gradient flows to the selected values (sorting is
    piecewise linear), so ascent moves the median of the noisy outputs, not their mean.
    """
    m = values.shape[0]
    c = max(int(round(fraction * m)), 1)
    if (m - c) % 2:
        c += 1
    c = min(c, m)
    start = (m - c) // 2
    return torch.sort(values, dim=0).values[start:start + c].mean(dim=0)


def regressor_objective(model: torch.nn.Module, direction: float, sigma: float,
                        noise_draws: int, target: str = "median") -> Callable:
    """direction * f(x) (sigma = 0), or, against the smoothed model, direction * a statistic of
    the outputs over ``noise_draws`` noise draws: ``target="median"`` (default) the central
    mean (:func:`central_mean`, a differentiable surrogate of the median that the certificate
    bounds), ``"mean"`` their average (the SmoothAdv expectation; kept for comparison). A band
    regressor's ([B, 2]) end under attack: the lower under SA (direction > 0), the upper under EA.
    """
    if target not in REGRESSION_TARGETS:
        raise CertificationError(f"regression target {target!r} is not one of "
                                 f"{', '.join(REGRESSION_TARGETS)}")

    def end(out: torch.Tensor) -> torch.Tensor:
        # a band regressor: SA raises its lower end, EA lowers its upper end (the end that,
        # moved, takes the interval off a true stiffness on the far side; DESIGN 3.5)
        lo, hi = band_columns(out)
        return lo if direction > 0 else hi

    def objective(x: torch.Tensor, gen: FrameNoise) -> torch.Tensor:
        if sigma == 0:
            return direction * end(model(x))
        out = end(model(_noisy_copies(x, sigma, noise_draws, gen))).reshape(noise_draws,
                                                                            x.shape[0])
        if target == "median":
            return direction * harrell_davis_median(out)
        if target == "central":
            return direction * central_mean(out)
        return direction * out.mean(dim=0)

    return objective


def attack(model: torch.nn.Module, frames: torch.Tensor, kind: str, settings: AttackSettings, *,
           task: str, sigma: float = 0.0,
           frame_seeds: Sequence[int] | None = None) -> torch.Tensor:
    """Stability (``kind="sa"``) or efficiency (``"ea"``) attack on a batch [B, C, H, W].

    ``task`` is "classify" (model returns [B, K] logits, labels grippiest first; the targets
    are set from the model's clean prediction, see :func:`target_labels`) or "regress"
    (model returns stiffness [B] or [B, 1]). ``sigma > 0`` attacks the smoothed model by the
    expectation over ``settings.noise_draws`` noise draws per step; ``sigma = 0`` the base
    model. Returns adversarial frames in [0, 1] within L2 distance eps of the input frames.
    ``frame_seeds`` (one per frame) gives each frame its own random stream (random start,
    noise draws); default: one stream from ``settings.seed`` for the batch.
    """
    if kind not in ATTACKS:
        raise CertificationError(f"attack {kind!r} is not one of {', '.join(ATTACKS)}")
    if not (isinstance(frames, torch.Tensor) and frames.dim() == 4 and frames.is_floating_point()):
        raise CertificationError("attack frames must be a float tensor [B, C, H, W]")
    if not (math.isfinite(sigma) and sigma >= 0):
        raise CertificationError(f"attack sigma = {sigma!r} must be >= 0")
    was_training = model.training
    model.eval()
    # Per-frame streams serve the clean prediction and then PGD, one after the other.
    noise = None if frame_seeds is None else FrameNoise(settings.seed, frames.shape[0],
                                                        frames.device, frame_seeds)
    try:
        if task == "classify":
            predicted = _clean_prediction(model, frames, sigma, settings, noise)
            num_classes = predicted.shape[1]
            targets = target_labels(predicted.argmax(1), num_classes, kind)
            objective = classifier_objective(model, targets, sigma, settings.noise_draws)
        elif task == "regress":
            direction = 1.0 if kind == "sa" else -1.0
            objective = regressor_objective(model, direction, sigma, settings.noise_draws,
                                            settings.regression_target)
        else:
            raise CertificationError(f"task {task!r} is not 'classify' or 'regress'")
        return pgd_l2(objective, frames, settings, noise=noise)
    finally:
        model.train(was_training)


def _clean_prediction(model: torch.nn.Module, frames: torch.Tensor, sigma: float,
                      settings: AttackSettings,
                      noise: FrameNoise | None = None) -> torch.Tensor:
    """Softmax of f at the frames, or its average over noise draws (sigma > 0), [B, K]."""
    with torch.no_grad():
        if sigma == 0:
            return torch.softmax(model(frames), dim=1)
        gen = noise if noise is not None else FrameNoise(int(settings.seed) + 1,
                                                         frames.shape[0], frames.device)
        probs = torch.softmax(model(_noisy_copies(frames, sigma, settings.noise_draws, gen)),
                              dim=1)
        return probs.view(settings.noise_draws, frames.shape[0], -1).mean(dim=0)


def stability_attack(model: torch.nn.Module, frames: torch.Tensor, settings: AttackSettings, *,
                     task: str, sigma: float = 0.0) -> torch.Tensor:
    """SA: raise the predicted stiffness (towards grippier labels). See :func:`attack`."""
    return attack(model, frames, "sa", settings, task=task, sigma=sigma)


def efficiency_attack(model: torch.nn.Module, frames: torch.Tensor, settings: AttackSettings, *,
                      task: str, sigma: float = 0.0) -> torch.Tensor:
    """EA: lower the predicted stiffness (towards less grippy labels). See :func:`attack`."""
    return attack(model, frames, "ea", settings, task=task, sigma=sigma)
