"""The attacker between the camera and perception (DESIGN 3 attacks, DESIGN 6).

Kinds: ``none`` (frames pass unchanged); ``sa`` (stability attack: push the predicted stiffness
up, towards the grippiest label) and ``ea`` (efficiency attack: push it down), L2 PGD at
budget ``eps`` in [0, 1] pixel space with :func:`drake_cert.certification.attacks.attack`,
against the base model f (``target="base"``: f's own gradient, no noise) or the smoothed
model (``target="smoothed"``: SmoothAdv, the expectation over ``noise_draws`` draws at
``sigma``); and two faults for testing the pipeline's handling of bad frames: ``nan`` (every
pixel NaN) and ``misshaped`` (the top half of the image only, [3, H/2, W]).

Parameters: the scenario's blocks. ``attack`` (:class:`AttackSettingsYaml`): ``kind``,
``eps``, ``target``, ``steps``, ``noise_draws`` (the Diagram builder sets ``target`` by
pipeline: ``smoothed`` for the certified one, ``base`` for the base one); ``perception``
(:class:`PerceptionSettings`): ``task`` (what the model outputs) and ``sigma`` (read with
``target="smoothed"`` only); ``camera`` (:class:`CameraSettings`): ``frame_size``. Keywords:
the attacked ``model`` and the scenario's ``seed``.

Ports: input ``frame`` and output ``frame`` (abstract :class:`CameraFrame`). Stateless: the
output is cached on the input, so each attack runs once per new frame. The attack of tick k
draws its random start and noise from the stream ``attack`` (k) of the seed
(:mod:`drake_cert.certification.seeds`).
A frame that is already bad (NaN, wrong rank) is passed through unchanged by sa/ea.
"""

import dataclasses
import math

import torch
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from drake_cert.certification.attacks import AttackSettings, attack
from drake_cert.certification.seeds import Purpose, child_seed
from drake_cert.errors import ConfigError
from drake_cert.systems.camera import CameraFrame
from drake_cert.systems.scenario import AttackSettingsYaml, CameraSettings, PerceptionSettings

KINDS = ("none", "sa", "ea", "nan", "misshaped")
TARGETS = ("base", "smoothed")


def _check_attack(attack: AttackSettingsYaml, sigma: float, has_model: bool) -> None:
    """ConfigError for a kind, target or eps out of range, an sa/ea attack without a model,
    or a smoothed target without noise."""
    kind, eps, target = attack.kind, attack.eps, attack.target
    if kind not in KINDS:
        raise ConfigError(f"attack kind {kind!r}; expected one of {', '.join(KINDS)}")
    if target not in TARGETS:
        raise ConfigError(f"attack target {target!r}; expected one of {', '.join(TARGETS)}")
    if not (math.isfinite(eps) and eps >= 0):
        raise ConfigError(f"attack eps = {eps!r} must be a finite number >= 0")
    if kind in ("sa", "ea") and not has_model:
        raise ConfigError(f"attack {kind!r} needs the perception model it attacks")
    if target == "smoothed" and kind in ("sa", "ea") and not sigma > 0:
        raise ConfigError(f"attack target 'smoothed' needs sigma > 0, got {sigma!r}")


def attack_settings(attack: AttackSettingsYaml, perception: PerceptionSettings,
                    has_model: bool) -> AttackSettings:
    """The checked PGD settings of :class:`Attacker` (eps, steps, noise draws; no seed: each
    tick gets its own); ConfigError as :func:`_check_attack` says."""
    _check_attack(attack, perception.sigma, has_model)
    settings = AttackSettings(eps=float(attack.eps), steps=int(attack.steps),
                              noise_draws=int(attack.noise_draws))
    settings.validate()
    return settings


class Attacker(LeafSystem):
    """Input ``frame`` (abstract :class:`CameraFrame`), output ``frame`` (perturbed copy).

    Args:
        attack: kind, budget eps (L2, pixel units), target ("base": PGD on ``model``;
            "smoothed": SmoothAdv on ``model`` at ``perception.sigma``), PGD steps and noise
            draws (:class:`AttackSettings`; the step size is PGD's default).
        perception: ``task`` ("classify" or "regress": what ``model`` outputs) and ``sigma``.
        camera: ``frame_size``, the side of the camera's frames (model value of the ports).
        model: the perception model attacked (classifier logits or stiffness regressor);
            needed for sa/ea.
        seed: scenario seed; tick k uses its stream ``attack`` (k).
    """

    def __init__(self, attack: AttackSettingsYaml | None = None,
                 perception: PerceptionSettings | None = None,
                 camera: CameraSettings | None = None, *,
                 model: torch.nn.Module | None = None, seed: int = 0):
        super().__init__()
        attack = attack if attack is not None else AttackSettingsYaml()
        perception = perception if perception is not None else PerceptionSettings()
        camera = camera if camera is not None else CameraSettings()
        self._settings = attack_settings(attack, perception, model is not None)
        self.kind, self.eps, self.target = attack.kind, float(attack.eps), attack.target
        self.model, self.task, self.seed = model, perception.task, int(seed)
        self.sigma = float(perception.sigma) if attack.target == "smoothed" else 0.0
        placeholder = CameraFrame.placeholder(camera.frame_size)
        self._in = self.DeclareAbstractInputPort("frame", AbstractValue.Make(placeholder))
        self.DeclareAbstractOutputPort("frame", lambda: AbstractValue.Make(placeholder),
                                       self._calc_frame,
                                       prerequisites_of_calc={self._in.ticket()})

    def perturb(self, frame: CameraFrame) -> CameraFrame:
        """The attacked frame (pure: same frame, same tick, same result)."""
        x = frame.image
        if self.kind == "none":
            return frame
        if self.kind == "nan":
            return dataclasses.replace(frame, image=torch.full_like(x, math.nan),
                                       attack="nan", perturbation_l2=math.nan)
        if self.kind == "misshaped":
            return dataclasses.replace(frame, image=x[..., : max(1, x.shape[-2] // 2), :].clone(),
                                       attack="misshaped", perturbation_l2=math.nan)
        if not (x.dim() == 3 and bool(torch.isfinite(x).all())) or self.eps == 0:
            return frame
        settings = dataclasses.replace(
            self._settings, seed=child_seed(self.seed, Purpose.ATTACK, frame.tick))
        adv = attack(self.model, x[None].float(), self.kind, settings, task=self.task,
                     sigma=self.sigma)[0]
        return dataclasses.replace(frame, image=adv, attack=self.kind,
                                   perturbation_l2=float((adv - x).norm()))

    def _calc_frame(self, context, output: AbstractValue) -> None:
        output.set_value(self.perturb(self._in.Eval(context)))
