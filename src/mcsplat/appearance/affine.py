"""`--appearance affine`: one affine colour transform per training image, rgb' = A rgb + b (A 3x3, b 3)."""

from __future__ import annotations

import torch


class AffineAppearance(torch.nn.Module):
    """One affine colour transform per training image: `matrix` [N, 3, 3] (identity at start), `bias` [N, 3].
    `pull_weight` weighs the squared distance of an image's transform from identity (its regulariser)."""

    MODE = "affine"  # the --appearance value (checkpoints record it)

    def __init__(self, count: int, device: torch.device | str = "cpu", pull_weight: float = 0.01):
        super().__init__()
        self.pull_weight = pull_weight
        self.matrix = torch.nn.Parameter(torch.eye(3, device=device).repeat(count, 1, 1))
        self.bias = torch.nn.Parameter(torch.zeros(count, 3, device=device))

    def forward(self, index: int, rgb: torch.Tensor) -> torch.Tensor:
        """rgb [H, W, 3] as image `index`'s camera recorded it."""
        return rgb @ self.matrix[index].T + self.bias[index]

    def optimizer(self, lr: float) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.parameters(), lr=lr, eps=1e-15)

    @torch.no_grad()
    def centre(self, step: int) -> None:
        """Make the median transform (entry by entry) the identity. The scene's colours and a change common to every
        transform explain the photos equally well; left free, the transforms take up whatever the young scene lacks
        (a brightness the scene then never learns, and that renders without transforms lack). Held at the median,
        the scene keeps the colours of the typical photo, as the L1 loss does without transforms, and each transform
        only how its photo departs from it (the mean would tint the scene toward the odd photos instead)."""
        self.matrix -= self.matrix.median(dim=0).values - torch.eye(3, device=self.matrix.device)
        self.bias -= self.bias.median(dim=0).values

    def penalty(self, index: int) -> torch.Tensor:
        """The regulariser of image `index`'s transform: its weighted squared distance from identity."""
        identity = torch.eye(3, device=self.matrix.device)
        distance = ((self.matrix[index] - identity) ** 2).sum() + (self.bias[index] ** 2).sum()
        return self.pull_weight * distance
