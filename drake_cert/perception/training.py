"""Training: the noise-trained classifier (Gaussian augmentation, Cohen et al. 2019, or
consistency regularization, Jeong and Shin 2020) and the stiffness regressor.

Classifier: SGD with Nesterov momentum, a learning rate that is a pure function of the step
(linear warm-up, cosine decay), random horizontal flips, and at sigma > 0 every training
frame is replaced by ``x + N(0, sigma^2 I)`` in [0, 1] pixel space (no clipping, as the
smoothing noise). ``TrainConfig.method`` picks the loss: ``gaussian`` is the cross-entropy
on one noisy copy; ``consistency`` (docs/design.md 3.2) draws m noisy copies of each frame and
adds to their mean cross-entropy lambda times the mean KL divergence from the copies' mean
softmax to each copy's softmax and eta times that mean's entropy. The data order, flips and
noise of epoch e come from a generator seeded by ``(seed, e)`` and are drawn on the CPU (also
when the model trains on a GPU), so a run resumed from its per-epoch checkpoint gives the same
weights as an uninterrupted run.

Regressor (paper: ResNet features + linear SVR): by default the whole network trained end to
end under the same noise (:func:`train_regressor_end_to_end`, backbone initialised from the
classifier at the same sigma); the older option is the classifier's frozen features of
noise-augmented frames and a ridge least-squares fit to the frames' true stiffness (N/rad)
(:func:`fit_regressor`).
"""

from __future__ import annotations

import dataclasses
import io as _io
import math
import sys
from pathlib import Path

import numpy as np
import torch
from torch import nn

from drake_cert.errors import ConfigError
from drake_cert.io import atomic_write_bytes
from drake_cert.perception.frameset import FrameSet
from drake_cert.perception.models import SmallResNet, StiffnessRegressor
from drake_cert.progress import progress_bar
from drake_cert.rng import torch_generator

STIFFNESS_UNIT = 1.0e5  # N/rad; regression targets are fitted in this unit


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Classifier training hyper-parameters (all recorded in the model's provenance)."""

    epochs: int = 6
    width: int = 16  # channels of the first stage (then 2w, 4w)
    pool: int = 1  # average pool x pool pixel blocks before the network (1: none)
    batch_size: int = 64
    learning_rate: float = 0.05  # peak
    warmup_fraction: float = 0.1
    weight_decay: float = 5.0e-4
    momentum: float = 0.9
    flip: bool = True
    method: str = "gaussian"  # or "consistency", "tail" (TRAINING_METHODS)
    copies: int = 1  # noisy copies of each frame per step (consistency: m >= 2)
    consistency_lambda: float = 0.0  # weight of the KL consistency term
    consistency_eta: float = 0.0  # weight of the entropy of the copies' mean softmax
    tail_fraction: float = 0.0  # tail: the worst share q of a batch's frames (0 < q <= 1)
    tail_weight: float = 0.0  # tail: weight beta of their mean loss beside the batch mean

    def __post_init__(self):
        check_training_method(self)


TRAINING_METHODS = ("gaussian", "consistency", "tail")


@dataclasses.dataclass(frozen=True)
class NoiseTraining:
    """What a noise-trained run learns with: the noise level, the seed of its random streams
    (:func:`epoch_generator`) and the hyper-parameters."""

    sigma: float  # Gaussian noise std in [0, 1] pixel units
    seed: int
    config: TrainConfig


@dataclasses.dataclass(frozen=True)
class TrainRun:
    """How a training run is carried out, not what it learns (none of it is in the weights).

    ``checkpoint`` and ``on_epoch_end`` apply to :func:`train_classifier` only.
    """

    progress: bool = False  # per-epoch lines and a progress bar on stderr
    description: str = "train"  # prefix of those lines
    device: str = "cpu"  # where the model trains ("cpu" or "cuda"); streams stay on the CPU
    checkpoint: str | Path | None = None  # per-epoch checkpoint file (resumed if it matches)
    on_epoch_end: object = None  # callable(epoch counted from 1), after the epoch's checkpoint


def check_training_method(config: TrainConfig) -> None:
    """ConfigError naming the method or the parameter of it that is not valid."""
    if config.method not in TRAINING_METHODS:
        raise ConfigError(f"training method {config.method!r} is not one of "
                         f"{', '.join(TRAINING_METHODS)}")
    if config.method in ("gaussian", "tail") and (config.copies != 1 or config.consistency_lambda
                                                  or config.consistency_eta):
        raise ConfigError(f"the {config.method} method takes one noisy copy and no consistency "
                          "terms")
    if config.method != "tail" and (config.tail_fraction or config.tail_weight):
        raise ConfigError(f"the {config.method} method takes no tail terms")
    if config.method == "tail":
        if not (math.isfinite(config.tail_fraction) and 0.0 < config.tail_fraction <= 1.0):
            raise ConfigError(f"tail_fraction {config.tail_fraction} must be in (0, 1]")
        if not (math.isfinite(config.tail_weight) and 0.0 <= config.tail_weight <= 1.0):
            raise ConfigError(f"tail_weight {config.tail_weight} must be in [0, 1]")
    if config.method == "consistency":
        if int(config.copies) != config.copies or config.copies < 2:
            raise ConfigError(f"consistency needs m >= 2 noisy copies (got {config.copies})")
        for name in ("consistency_lambda", "consistency_eta"):
            value = getattr(config, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"{name} {value} must be a finite number >= 0")


def consistency_config(lam: float, *, copies: int = 2, eta: float = 0.5,
                       base: TrainConfig | None = None) -> TrainConfig:
    """The training configuration of consistency regularization with weights lambda, eta on
    ``copies`` noisy copies (Jeong and Shin's defaults m = 2, eta = 0.5)."""
    return dataclasses.replace(base or TrainConfig(), method="consistency", copies=int(copies),
                               consistency_lambda=float(lam), consistency_eta=float(eta))


def tail_config(fraction: float, weight: float, base: TrainConfig | None = None) -> TrainConfig:
    """The training configuration of the tail-weighted loss (:func:`tail_loss`)."""
    return dataclasses.replace(base or TrainConfig(), method="tail",
                               tail_fraction=float(fraction), tail_weight=float(weight))


def tail_loss(logits: torch.Tensor, labels: torch.Tensor, *, fraction: float,
              weight: float) -> torch.Tensor:
    """``(1 - beta) mean CE + beta CVaR_q(CE)``: the batch's mean cross-entropy mixed with the
    mean over its worst ``ceil(q B)`` frames (the empirical CVaR at level q of the per-frame
    loss; docs/design.md 3.2). It weighs the frames the model misreads most, whose votes set
    the conformal thresholds (3.6)."""
    per_frame = nn.functional.cross_entropy(logits, labels, reduction="none")
    worst = torch.topk(per_frame, max(1, math.ceil(fraction * per_frame.numel()))).values
    return (1.0 - weight) * per_frame.mean() + weight * worst.mean()


def training_method(config: TrainConfig) -> dict:
    """The method and its parameters, as a model file's metadata records them."""
    if config.method == "gaussian":
        return {"method": "gaussian"}
    if config.method == "tail":
        return {"method": "tail", "fraction": config.tail_fraction,
                "weight": config.tail_weight}
    return {"method": "consistency", "copies": config.copies,
            "lambda": config.consistency_lambda, "eta": config.consistency_eta}


def consistency_loss(logits: torch.Tensor, labels: torch.Tensor, *, copies: int, lam: float,
                     eta: float) -> torch.Tensor:
    """Consistency-regularized loss of ``logits`` [m * B, K] of m noisy copies stacked
    copy-major (rows i * B .. (i + 1) * B - 1 are copy i of the batch) with true ``labels`` [B]:
    mean cross-entropy + lam * mean_i KL(p_bar || p_i) + eta * H(p_bar), where p_i is copy i's
    softmax and p_bar their mean (docs/design.md 3.2)."""
    batch = labels.shape[0]
    log_p = torch.log_softmax(logits, dim=1).reshape(copies, batch, -1)
    cross_entropy = -log_p.gather(2, labels.repeat(copies, 1)[..., None]).mean()
    p_bar = log_p.exp().mean(0)
    log_p_bar = torch.log(p_bar.clamp_min(1e-12))
    kl = (p_bar[None] * (log_p_bar[None] - log_p)).sum(2).mean()
    entropy = -(p_bar * log_p_bar).sum(1).mean()
    return cross_entropy + lam * kl + eta * entropy


def learning_rate_at(step: int, total_steps: int, config: TrainConfig) -> float:
    """Linear warm-up to the peak, then cosine decay to 0 (a pure function of the step)."""
    warm = max(1, int(config.warmup_fraction * total_steps))
    if step < warm:
        return config.learning_rate * (step + 1) / warm
    t = (step - warm) / max(1, total_steps - warm)
    return 0.5 * config.learning_rate * (1 + math.cos(math.pi * min(1.0, t)))


def epoch_generator(seed: int, epoch: int) -> torch.Generator:
    """The random stream of one epoch (order, flips, noise)."""
    ss = np.random.SeedSequence([int(seed), 0xE90C, int(epoch)])
    return torch_generator(int(ss.generate_state(1, dtype=np.uint64)[0] >> 1))


def add_gaussian_noise(x: torch.Tensor, sigma: float, generator: torch.Generator | None
                       ) -> torch.Tensor:
    """x + N(0, sigma^2 I) in [0, 1] pixel space (Cohen et al.); no clipping."""
    if sigma == 0:
        return x
    return x + sigma * torch.randn(x.shape, generator=generator)


def train_classifier(train_set: FrameSet, *, sigma: float, epochs: int | None = None,
                     seed: int = 0, config: TrainConfig | None = None,
                     run: TrainRun | None = None) -> tuple[SmallResNet, dict]:
    """Train a :class:`SmallResNet` on ``train_set`` under Gaussian noise at ``sigma`` with the
    configuration's method (gaussian augmentation or consistency regularization).

    ``run`` (:class:`TrainRun`, default: quiet, on the CPU, no checkpoint): ``run.device`` is
    where the model trains ("cpu" or "cuda"); the random streams are the CPU's either way and
    the returned model is on the CPU.

    ``run.checkpoint``: a file written atomically after every epoch; if it exists (same
    configuration and data size) training resumes after its last epoch.
    ``run.on_epoch_end(epoch)`` is called after each epoch's checkpoint (epoch counted from
    1). Returns the model
    (eval mode) and metrics: final-epoch training loss and accuracy (on noisy frames),
    epochs, steps, seconds.
    """
    import time

    run = run or TrainRun()
    checkpoint, device = run.checkpoint, run.device
    progress, description = run.progress, run.description
    cfg = config or TrainConfig()
    if epochs is not None:
        cfg = dataclasses.replace(cfg, epochs=int(epochs))
    torch.manual_seed(seed)
    model = SmallResNet(len(train_set.label_names), width=cfg.width, pool=cfg.pool).to(device)
    optimizer = make_optimizer(model, cfg)
    n = len(train_set)
    steps_per_epoch = math.ceil(n / cfg.batch_size)
    total = steps_per_epoch * cfg.epochs
    signature = {"config": dataclasses.asdict(cfg), "sigma": float(sigma), "seed": int(seed),
                 "frames": n, "labels": list(train_set.label_names)}
    start_epoch, seconds, history = 0, 0.0, []
    if checkpoint is not None and Path(checkpoint).exists():
        start_epoch, seconds, history = _resume(checkpoint, signature, model, optimizer,
                                                run=run, epochs=cfg.epochs)
    for epoch in range(start_epoch, cfg.epochs):
        t0 = time.perf_counter()
        loss, accuracy = train_epoch(model, optimizer, train_set, epoch=epoch,
                                     training=NoiseTraining(sigma, seed, cfg), run=run)
        seconds += time.perf_counter() - t0
        history.append({"epoch": epoch + 1, "loss": loss, "accuracy": accuracy})
        if progress:
            print(f"{description}: epoch {epoch + 1}/{cfg.epochs} loss {loss:.4f} "
                  f"train accuracy {accuracy:.4f}", file=sys.stderr)
        if checkpoint is not None:
            buf = _io.BytesIO()
            torch.save({"signature": signature, "epoch": epoch + 1, "seconds": seconds,
                        "history": history, "model": _to_cpu(model.state_dict()),
                        "optimizer": _to_cpu(optimizer.state_dict())}, buf)
            atomic_write_bytes(checkpoint, buf.getvalue())
        if run.on_epoch_end is not None:
            run.on_epoch_end(epoch + 1)
    model = model.cpu().eval()
    last = history[-1] if history else {"loss": math.nan, "accuracy": math.nan}
    metrics = {"train_loss": last["loss"], "train_accuracy": last["accuracy"],
               "epochs": cfg.epochs, "steps": total, "train_seconds": round(seconds, 2),
               "train_frames": n, "device": str(device), "config": dataclasses.asdict(cfg)}
    return model, metrics


def _to_cpu(state):
    """A (nested) state dict with every tensor on the CPU, so a checkpoint loads anywhere."""
    if isinstance(state, torch.Tensor):
        return state.cpu()
    if isinstance(state, dict):
        return {k: _to_cpu(v) for k, v in state.items()}
    if isinstance(state, list | tuple):
        return type(state)(_to_cpu(v) for v in state)
    return state


def make_optimizer(model: nn.Module, config: TrainConfig) -> torch.optim.SGD:
    """SGD with Nesterov momentum; weight decay on weights only (not biases or norms)."""
    decay, no_decay = [], []
    for p in model.parameters():
        (no_decay if p.ndim == 1 else decay).append(p)
    return torch.optim.SGD([{"params": decay, "weight_decay": config.weight_decay},
                            {"params": no_decay, "weight_decay": 0.0}],
                           lr=config.learning_rate, momentum=config.momentum, nesterov=True)


def _resume(checkpoint, signature: dict, model, optimizer, *, run: TrainRun,
            epochs: int) -> tuple[int, float, list]:
    """Load a per-epoch checkpoint of the same run into model and optimizer.

    Returns (epochs done, seconds spent, history); (0, 0.0, []) when the file is for another run.
    """
    progress, description = run.progress, run.description
    state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    if state.get("signature") != signature:
        if progress:
            print(f"{description}: checkpoint {checkpoint} is for another run; starting over",
                  file=sys.stderr)
        return 0, 0.0, []
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])  # moves the momenta to the params' device
    start_epoch = int(state["epoch"])
    if progress:
        print(f"{description}: resuming after epoch {start_epoch}/{epochs}", file=sys.stderr)
    return start_epoch, float(state["seconds"]), list(state["history"])


def train_epoch(model: nn.Module, optimizer, train_set: FrameSet, *, epoch: int,
                training: NoiseTraining, run: TrainRun | None = None) -> tuple[float, float]:
    """One epoch (0-based ``epoch``) of noise-trained SGD at ``training`` (:class:`NoiseTraining`:
    sigma, seed, configuration) with the configuration's method; its order, flips and noise
    come from :func:`epoch_generator` (seed, epoch). With m copies (consistency) each step
    draws the m copies' noise of its batch one copy after another. ``run``: progress bar,
    description and device (:class:`TrainRun`; checkpoint unused).
    Returns mean loss and accuracy on noisy frames (all copies)."""
    sigma, seed, config = training.sigma, training.seed, training.config
    run = run or TrainRun()
    progress, description, device = run.progress, run.description, run.device
    cfg = config
    n = len(train_set)
    steps_per_epoch = math.ceil(n / cfg.batch_size)
    total = steps_per_epoch * cfg.epochs
    loss_fn = nn.CrossEntropyLoss()
    model.train()
    gen = epoch_generator(seed, epoch)
    order = torch.randperm(n, generator=gen)
    flips = torch.rand(n, generator=gen) < 0.5 if cfg.flip else torch.zeros(n, dtype=bool)
    total_loss, correct = 0.0, 0
    bar = progress_bar(range(steps_per_epoch),
                       desc=f"{description} epoch {epoch + 1}/{cfg.epochs}",
                       disable=not progress, leave=False)
    for b in bar:
        idx = order[b * cfg.batch_size:(b + 1) * cfg.batch_size]
        x = train_set.images[idx]
        flip = flips[idx]
        x = torch.where(flip[:, None, None, None], x.flip(-1), x)
        x = torch.cat([add_gaussian_noise(x, sigma, gen) for _ in range(cfg.copies)])
        y = train_set.labels[idx].to(device)
        for group in optimizer.param_groups:
            group["lr"] = learning_rate_at(epoch * steps_per_epoch + b, total, cfg)
        logits = model(x.to(device))
        if cfg.method == "consistency":
            loss = consistency_loss(logits, y, copies=cfg.copies, lam=cfg.consistency_lambda,
                                    eta=cfg.consistency_eta)
        elif cfg.method == "tail":
            loss = tail_loss(logits, y, fraction=cfg.tail_fraction, weight=cfg.tail_weight)
        else:
            loss = loss_fn(logits, y)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        total_loss += float(loss.detach()) * len(idx)
        correct += int((logits.argmax(1) == y.repeat(cfg.copies)).sum()) / cfg.copies
        bar.set_postfix(loss=f"{float(loss.detach()):.3f}")
    bar.close()
    return total_loss / n, correct / n


@torch.no_grad()
def batched_features(features: nn.Module, images: torch.Tensor, *, sigma: float = 0.0,
                     generator: torch.Generator | None = None,
                     batch_size: int = 500) -> torch.Tensor:
    """features(x + N(0, sigma^2 I)) over ``images`` in batches -> [N, F]."""
    was_training = features.training
    features.eval()
    out = [features(add_gaussian_noise(images[i:i + batch_size], sigma, generator))
           for i in range(0, len(images), batch_size)]
    features.train(was_training)
    return torch.cat(out)


def fit_regressor(classifier: SmallResNet, train_set: FrameSet, *, sigma: float, seed: int = 0,
                  ridge: float = 1.0e-3, copies: int = 1) -> tuple[StiffnessRegressor, dict]:
    """Ridge fit of a linear head on the classifier's frozen features to the true stiffness.

    Features are computed on ``copies`` noisy copies of each training frame at ``sigma``.
    The ridge penalty ``ridge * N`` applies to standardised features. Returns the regressor
    (eval mode; output N/rad) and metrics: training MSE in (N/rad)^2.
    """
    if torch.isnan(train_set.stiffness_n_per_rad).any():
        raise ValueError("fit_regressor needs the true stiffness of every training frame")
    gen = epoch_generator(seed, 10_000)
    feats = torch.cat([batched_features(classifier.backbone, train_set.images, sigma=sigma,
                                        generator=gen) for _ in range(copies)]).double()
    target = (train_set.stiffness_n_per_rad.double() / STIFFNESS_UNIT).repeat(copies)
    mu, sd = feats.mean(0), feats.std(0).clamp_min(1e-8)
    z = (feats - mu) / sd
    y_mean = target.mean()
    n, d = z.shape
    w = torch.linalg.solve(z.T @ z + ridge * n * torch.eye(d, dtype=z.dtype),
                           z.T @ (target - y_mean))
    weight = (w / sd) * STIFFNESS_UNIT
    bias = (y_mean - (mu / sd * w).sum()) * STIFFNESS_UNIT
    head = nn.Linear(d, 1)
    with torch.no_grad():
        head.weight.copy_(weight.float()[None])
        head.bias.copy_(bias.float().reshape(1))
    regressor = StiffnessRegressor(classifier.backbone, head).eval()
    residual = (z @ w + y_mean - target) * STIFFNESS_UNIT
    metrics = {"train_mse_n_per_rad_sq": float((residual**2).mean()), "ridge": ridge,
               "copies": copies, "train_frames": len(train_set)}
    return regressor, metrics


@torch.no_grad()
def predict_logits(model: nn.Module, images: torch.Tensor, *, sigma: float = 0.0,
                   seed: int = 0, batch_size: int = 500) -> torch.Tensor:
    """Model outputs on ``images`` (+ Gaussian noise at sigma, seeded) in eval mode."""
    model.eval()
    gen = epoch_generator(seed, 20_000)
    return torch.cat([model(add_gaussian_noise(images[i:i + batch_size], sigma, gen))
                      for i in range(0, len(images), batch_size)])


def evaluate_accuracy(model: nn.Module, frames: FrameSet, *, sigma: float = 0.0,
                      seed: int = 0) -> float:
    """Share of frames whose top logit is the true label (under noise at sigma if > 0)."""
    logits = predict_logits(model, frames.images, sigma=sigma, seed=seed)
    return float((logits.argmax(1) == frames.labels).float().mean())


def point_prediction(out: torch.Tensor) -> torch.Tensor:
    """A regressor's point prediction [B] (N/rad, float64) from its outputs: [B] or [B, 1] as
    they are, a band regressor's [B, 2] (lower, upper) by its midpoint."""
    if out.dim() == 2 and out.shape[1] == 2:
        return out.double().mean(dim=1)
    return out.double().reshape(-1)


def evaluate_mse(regressor: nn.Module, frames: FrameSet, *, sigma: float = 0.0,
                 seed: int = 0) -> float:
    """Mean squared error of predicted vs true stiffness, in (N/rad)^2
    (:func:`point_prediction`)."""
    pred = point_prediction(predict_logits(regressor, frames.images, sigma=sigma, seed=seed))
    return float(((pred - frames.stiffness_n_per_rad.double()) ** 2).mean())


def evaluate_mae(regressor: nn.Module, frames: FrameSet, *, sigma: float = 0.0,
                 seed: int = 0) -> float:
    """Mean absolute error of predicted vs true stiffness, in N/rad (:func:`point_prediction`)."""
    pred = point_prediction(predict_logits(regressor, frames.images, sigma=sigma, seed=seed))
    return float((pred - frames.stiffness_n_per_rad.double()).abs().mean())


def evaluate_band(regressor: nn.Module, frames: FrameSet, *, sigma: float = 0.0,
                  seed: int = 0) -> dict:
    """A band regressor's raw band (no smoothing, no conformal step) on ``frames``: the share
    of frames whose [lower, upper] output holds the true stiffness and its mean width (N/rad)."""
    out = predict_logits(regressor, frames.images, sigma=sigma, seed=seed).double()
    lo, hi = out.min(dim=1).values, out.max(dim=1).values
    y = frames.stiffness_n_per_rad.double()
    return {"test_band_coverage_noisy": float(((lo <= y) & (y <= hi)).double().mean()),
            "test_band_width_noisy_n_per_rad": float((hi - lo).mean())}


def pinball_loss(pred: torch.Tensor, target: torch.Tensor,
                 quantiles: tuple[float, ...]) -> torch.Tensor:
    """Mean quantile (pinball) loss of ``pred`` [B, Q] against ``target`` [B], column j at
    level ``quantiles[j]``: ``max(tau (y - q), (tau - 1)(y - q))`` (Koenker and Bassett 1978)."""
    diff = target[:, None] - pred
    tau = torch.tensor(quantiles, dtype=pred.dtype, device=pred.device)[None]
    return torch.maximum(tau * diff, (tau - 1.0) * diff).mean()


BAND_QUANTILES = (0.05, 0.95)  # levels of a band regressor's two outputs (DESIGN 3.5)


def train_regressor_end_to_end(train_set: FrameSet, *, sigma: float, epochs: int | None = None,
                               seed: int = 0, config: TrainConfig | None = None,
                               init: SmallResNet | None = None,
                               run: TrainRun | None = None,
                               quantiles: tuple[float, float] | None = None
                               ) -> tuple[SmallResNet, dict]:
    """A stiffness regressor trained end to end under Gaussian noise (DESIGN 3.2).

    The frozen-feature ridge head (:func:`fit_regressor`) mostly predicts class means; here the
    whole network learns the stiffness, which the generator ties to the rendering intensity
    within a condition. Model: a :class:`SmallResNet` with one output (backbone copied from
    ``init``, e.g. the classifier at the same sigma, when given, at its width; else
    ``config.width``). Loss: Huber (smooth L1,
    beta 0.1) on ``(y - mean y) / 1e5`` at ``x + N(0, sigma^2 I)`` (plus flips), with the
    classifier's schedule (:class:`TrainConfig`, :func:`epoch_generator` streams). After
    training the output layer is rescaled to N/rad, so ``model(x)`` is [B, 1] stiffness in
    N/rad, as :class:`~drake_cert.certification.regressor.MedianSmoothedRegressor` expects.
    ``run`` (:class:`TrainRun`, default: quiet, described "train regressor", on the CPU):
    ``run.device`` is where it trains (streams drawn on the CPU; the model is returned on the
    CPU); it takes no checkpoint.
    ``save_model`` stores it like a classifier with one output (``num_classes`` 1).
    ``quantiles`` (a band regressor, e.g. :data:`BAND_QUANTILES`): two outputs, the lower and
    upper conditional quantiles of the stiffness at those levels, trained with
    :func:`pinball_loss` instead of Huber; ``model(x)`` is then [B, 2] N/rad.
    Returns the model (eval mode) and metrics: final-epoch training MSE in (N/rad)^2 (of the
    band's midpoint for a band regressor), seconds.
    """
    import time

    if torch.isnan(train_set.stiffness_n_per_rad).any():
        raise ValueError("train_regressor_end_to_end needs the true stiffness of every frame")
    run = run or TrainRun(description="train regressor")
    if run.checkpoint is not None or run.on_epoch_end is not None:
        raise ValueError("train_regressor_end_to_end takes no checkpoint or on_epoch_end")
    progress, description, device = run.progress, run.description, run.device
    cfg = config or TrainConfig()
    if epochs is not None:
        cfg = dataclasses.replace(cfg, epochs=int(epochs))
    torch.manual_seed(seed)
    if quantiles is not None and not (len(quantiles) == 2
                                      and 0.0 < quantiles[0] < quantiles[1] < 1.0):
        raise ValueError(f"quantiles = {quantiles!r} must be two levels 0 < lo < hi < 1")
    # the backbone is the init's (its width, e.g. a width-8 classifier), else cfg.width
    width, pool = (init.width, init.pool) if init is not None else (cfg.width, cfg.pool)
    model = SmallResNet(1 if quantiles is None else 2, width=width, pool=pool)
    if init is not None:
        model.backbone.load_state_dict(init.backbone.state_dict())
    model = model.to(device)
    optimizer = make_optimizer(model, cfg)
    n = len(train_set)
    target = train_set.stiffness_n_per_rad.double()
    y_mean = float(target.mean())
    scaled = ((target - y_mean) / STIFFNESS_UNIT).float().to(device)
    steps_per_epoch = math.ceil(n / cfg.batch_size)
    total = steps_per_epoch * cfg.epochs
    loss_fn = nn.SmoothL1Loss(beta=0.1)
    start = time.perf_counter()
    mse = math.nan
    for epoch in range(cfg.epochs):
        model.train()
        gen = epoch_generator(seed, 50_000 + epoch)
        order = torch.randperm(n, generator=gen)
        flips = torch.rand(n, generator=gen) < 0.5 if cfg.flip else torch.zeros(n, dtype=bool)
        sq = 0.0
        bar = progress_bar(range(steps_per_epoch),
                           desc=f"{description} epoch {epoch + 1}/{cfg.epochs}",
                           disable=not progress, leave=False)
        for b in bar:
            idx = order[b * cfg.batch_size:(b + 1) * cfg.batch_size]
            x = train_set.images[idx]
            x = torch.where(flips[idx][:, None, None, None], x.flip(-1), x)
            x = add_gaussian_noise(x, sigma, gen)
            for group in optimizer.param_groups:
                group["lr"] = learning_rate_at(epoch * steps_per_epoch + b, total, cfg)
            pred = model(x.to(device))
            if quantiles is None:
                pred = pred.squeeze(-1)
                loss = loss_fn(pred, scaled[idx.to(device)])
            else:
                loss = pinball_loss(pred, scaled[idx.to(device)], quantiles)
                pred = pred.mean(dim=1)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            sq += float(((pred.detach() - scaled[idx.to(device)]) ** 2).sum())
        bar.close()
        mse = sq / n * STIFFNESS_UNIT**2
        if progress:
            print(f"{description}: epoch {epoch + 1}/{cfg.epochs} mse {mse:.4g} (N/rad)^2",
                  file=sys.stderr)
    model = model.cpu()
    with torch.no_grad():  # output in N/rad: y = 1e5 * out + mean
        model.fc.weight.mul_(STIFFNESS_UNIT)
        model.fc.bias.mul_(STIFFNESS_UNIT).add_(y_mean)
    model.eval()
    metrics = {"train_mse_n_per_rad_sq": mse, "epochs": cfg.epochs, "steps": total,
               "train_seconds": round(time.perf_counter() - start, 2), "train_frames": n,
               "init": "classifier backbone" if init is not None else "fresh",
               "quantiles": list(quantiles) if quantiles is not None else None,
               "device": str(device), "config": dataclasses.asdict(cfg)}
    return model, metrics
