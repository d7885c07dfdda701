"""Mean-colour probe: can the road condition be read from a frame's average colour alone?

A multinomial logistic regression on the three per-channel means (standardised), fitted by
L-BFGS on the training frames. If it scored close to the CNN, the classes would differ in
colour rather than in structure, and L2 attacks and certificates would measure colour
shifts: shifting one channel's mean by d costs 64 d in L2 at 64 x 64.
"""

from __future__ import annotations

import torch

from drake_cert.perception.frameset import FrameSet


def mean_colour(images: torch.Tensor) -> torch.Tensor:
    """Per-channel mean of each frame: [N, 3, H, W] -> [N, 3]."""
    return images.double().mean(dim=(2, 3))


def fit_mean_colour_probe(train_set: FrameSet, *, iterations: int = 200,
                          l2: float = 1.0e-4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                                       torch.Tensor]:
    """Fit logistic regression on mean colour; returns (mean, std, weight [3, K], bias [K])."""
    x = mean_colour(train_set.images)
    mu, sd = x.mean(0), x.std(0).clamp_min(1e-12)
    z = (x - mu) / sd
    k = len(train_set.label_names)
    w = torch.zeros(3, k, dtype=torch.float64, requires_grad=True)
    b = torch.zeros(k, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([w, b], max_iter=iterations, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = torch.nn.functional.cross_entropy(z @ w + b, train_set.labels) + l2 * (w**2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    return mu, sd, w.detach(), b.detach()


def mean_colour_probe_accuracy(train_set: FrameSet, test_set: FrameSet) -> float:
    """Test accuracy of a linear classifier on the 3 per-channel mean colours."""
    mu, sd, w, b = fit_mean_colour_probe(train_set)
    z = (mean_colour(test_set.images) - mu) / sd
    return float(((z @ w + b).argmax(1) == test_set.labels).double().mean())
