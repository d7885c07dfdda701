"""L2 PGD attacks on the perception model (paper section V, DESIGN 3).

Both attacks live in [0, 1] pixel space, where the smoothing noise is added and budgets are
measured: ``||x_adv - x||_2 <= eps`` and ``0 <= x_adv <= 1``.

- Stability attack (SA): raise the predicted stiffness. Classifier: maximise the probability
  of the labels grippier than the frame's clean prediction a (labels 0..a-1; presets list
  labels grippiest first), i.e. push towards the grippiest label; a frame already predicted
  grippiest is pushed to stay there. Regressor: push the output up.
- Efficiency attack (EA): lower it. Classifier: the labels less grippy than a (a+1..K-1).
  Regressor: push the output down.

Against the base model f (``sigma = 0``) the attack follows f's gradient. Against the smoothed
model it follows the expectation over the noise (Salman et al. 2019, SmoothAdv): each step
averages the softmax (classifier) or the output (regressor) over ``noise_draws`` Gaussian draws
of the current iterate. Deterministic by seed (random start and noise draws use a seeded
``torch.Generator``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import torch

from drake_cert.errors import CertificationError

ATTACKS = ("sa", "ea")


@dataclasses.dataclass(frozen=True)
class AttackSettings:
    """PGD settings; budgets are L2 norms in [0, 1] pixel space."""

    eps: float  # L2 budget
    steps: int = 20  # PGD iterations
    step_size: float | None = None  # L2 length of each step; None: 2.5 * eps / steps (Madry)
    noise_draws: int = 8  # m, noise draws per step against a smoothed model (SmoothAdv)
    random_start: bool = True  # start from a random point of the ball
    seed: int = 0

    def validate(self) -> None:
        if not (math.isfinite(self.eps) and self.eps >= 0):
            raise CertificationError(f"attack eps = {self.eps!r} must be a finite number >= 0")
        if self.steps < 0:
            raise CertificationError(f"attack steps = {self.steps} must be >= 0")
        if self.step_size is not None and not self.step_size > 0:
            raise CertificationError(f"attack step_size = {self.step_size!r} must be positive")
        if self.noise_draws < 1:
            raise CertificationError(f"attack noise_draws = {self.noise_draws} must be >= 1")

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


def pgd_l2(objective: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor,
           settings: AttackSettings) -> torch.Tensor:
    """Projected gradient ascent of ``objective`` (per-frame values [B]) in the L2 ball.

    Each step moves ``step_length`` along the per-frame normalised gradient, then projects
    onto the ball of radius eps around x intersected with [0, 1]. Returns the last iterate,
    detached, [B, C, H, W].
    """
    settings.validate()
    x = x.detach()
    gen = torch.Generator(device=x.device).manual_seed(int(settings.seed))
    x_adv = x.clone()
    if settings.eps == 0 or settings.steps == 0:
        return x_adv
    if settings.random_start:
        start = torch.randn(x.shape, generator=gen, device=x.device, dtype=x.dtype)
        radius = torch.rand((x.shape[0],) + (1,) * (x.dim() - 1), generator=gen,
                            device=x.device, dtype=x.dtype) * settings.eps
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
                  gen: torch.Generator) -> torch.Tensor:
    """[draws * B, C, H, W]: ``draws`` Gaussian-noised copies of each frame (draw-major)."""
    noise = torch.randn((draws,) + tuple(x.shape), generator=gen, device=x.device,
                        dtype=x.dtype) * sigma
    return (x.unsqueeze(0) + noise).flatten(0, 1)


def classifier_objective(model: torch.nn.Module, targets: torch.Tensor, sigma: float,
                         noise_draws: int) -> Callable:
    """log P(label in targets) per frame: of f's softmax (sigma = 0) or of the softmax averaged
    over noise draws (SmoothAdv). ``targets`` is a [B, K] 0/1 mask of the wanted labels."""

    def objective(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
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


def regressor_objective(model: torch.nn.Module, direction: float, sigma: float,
                        noise_draws: int) -> Callable:
    """direction * f(x) (sigma = 0) or direction * the output averaged over noise draws."""

    def objective(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        if sigma == 0:
            return direction * model(x).reshape(x.shape[0])
        out = model(_noisy_copies(x, sigma, noise_draws, gen)).reshape(noise_draws, x.shape[0])
        return direction * out.mean(dim=0)

    return objective


def attack(model: torch.nn.Module, frames: torch.Tensor, kind: str, settings: AttackSettings, *,
           task: str, sigma: float = 0.0) -> torch.Tensor:
    """Stability (``kind="sa"``) or efficiency (``"ea"``) attack on a batch [B, C, H, W].

    ``task`` is "classify" (model returns [B, K] logits, labels grippiest first; the targets
    are set from the model's clean prediction, see :func:`target_labels`) or "regress"
    (model returns stiffness [B] or [B, 1]). ``sigma > 0`` attacks the smoothed model by the
    expectation over ``settings.noise_draws`` noise draws per step; ``sigma = 0`` the base
    model. Returns adversarial frames in [0, 1] within L2 distance eps of the input frames.
    """
    if kind not in ATTACKS:
        raise CertificationError(f"attack {kind!r} is not one of {', '.join(ATTACKS)}")
    if not (isinstance(frames, torch.Tensor) and frames.dim() == 4 and frames.is_floating_point()):
        raise CertificationError("attack frames must be a float tensor [B, C, H, W]")
    if not (math.isfinite(sigma) and sigma >= 0):
        raise CertificationError(f"attack sigma = {sigma!r} must be >= 0")
    was_training = model.training
    model.eval()
    try:
        if task == "classify":
            predicted = _clean_prediction(model, frames, sigma, settings)
            num_classes = predicted.shape[1]
            targets = target_labels(predicted.argmax(1), num_classes, kind)
            objective = classifier_objective(model, targets, sigma, settings.noise_draws)
        elif task == "regress":
            direction = 1.0 if kind == "sa" else -1.0
            objective = regressor_objective(model, direction, sigma, settings.noise_draws)
        else:
            raise CertificationError(f"task {task!r} is not 'classify' or 'regress'")
        return pgd_l2(objective, frames, settings)
    finally:
        model.train(was_training)


def _clean_prediction(model: torch.nn.Module, frames: torch.Tensor, sigma: float,
                      settings: AttackSettings) -> torch.Tensor:
    """Softmax of f at the frames, or its average over noise draws (sigma > 0), [B, K]."""
    with torch.no_grad():
        if sigma == 0:
            return torch.softmax(model(frames), dim=1)
        gen = torch.Generator(device=frames.device).manual_seed(int(settings.seed) + 1)
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
