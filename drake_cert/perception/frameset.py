"""``FrameSet``: camera frames with their road condition and true cornering stiffness."""

from __future__ import annotations

import dataclasses

import torch


@dataclasses.dataclass
class FrameSet:
    """Camera frames with their road condition and true cornering stiffness.

    images: float32 [N, 3, H, W] in [0, 1]; labels: int64 [N], index into ``label_names``;
    stiffness_n_per_rad: float32 [N], true cornering stiffness per tire (N/rad; NaN when
    unknown, e.g. users' frames); label_names: the preset's labels, grippiest first;
    preset: the preset's name (or "" for frames whose labels match no preset).
    """

    images: torch.Tensor
    labels: torch.Tensor
    stiffness_n_per_rad: torch.Tensor
    label_names: list[str]
    preset: str

    def __post_init__(self) -> None:
        n = self.images.shape[0]
        if self.images.ndim != 4 or self.images.shape[1] != 3:
            raise ValueError(f"images must be [N, 3, H, W], got {tuple(self.images.shape)}")
        if self.labels.shape != (n,) or self.stiffness_n_per_rad.shape != (n,):
            raise ValueError("labels and stiffness_n_per_rad must have one entry per image")

    def __len__(self) -> int:
        return int(self.images.shape[0])

    @property
    def size(self) -> int:
        """Image side length in pixels."""
        return int(self.images.shape[-1])

    def subset(self, index) -> FrameSet:
        """The frames at ``index`` (a slice, an index tensor or a boolean mask)."""
        return FrameSet(self.images[index], self.labels[index], self.stiffness_n_per_rad[index],
                        list(self.label_names), self.preset)

    def per_class(self, count: int) -> FrameSet:
        """The first ``count`` frames of every class (in order of appearance)."""
        chosen = torch.zeros(len(self), dtype=torch.bool)
        for k in range(len(self.label_names)):
            idx = torch.nonzero(self.labels == k).flatten()[:count]
            chosen[idx] = True
        return self.subset(chosen)
