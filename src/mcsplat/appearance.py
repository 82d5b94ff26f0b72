"""Exposure and white-balance compensation: a colour transform per training image, learned with the scene.

Phone captures change exposure and white balance between frames; a scene fitted to every frame as it is bends its
colours (or grows floaters) to explain what is really the camera's doing. `--appearance affine` gives each training
image its own affine colour transform, rgb' = A rgb + b (A 3x3, b 3), identity at start, applied to the render
before the loss, with its own Adam and learning rate (log-linear decay, as 3DGS's per-image exposure), a small L2
pull toward identity, and their median held at identity after every step (AffineAppearance.centre), so that a
transform only explains how its photo departs from the typical one. The transforms are not part of the
scene: renders, the viewer and every export show the scene without them.

Held-out views have no learned transform. `compensated_score` is 3DGS's `train_test_exp` protocol with the scene
frozen: the transform of a test view is fitted on the left half of its photo (least squares, which a frozen scene
makes exact) and the right half is scored with it.
"""

from __future__ import annotations

import math

import torch

MODES = ("none", "affine")


class AffineAppearance(torch.nn.Module):
    """One affine colour transform per training image: `matrix` [N, 3, 3] (identity at start), `bias` [N, 3]."""

    def __init__(self, count: int, device: torch.device | str = "cpu"):
        super().__init__()
        self.matrix = torch.nn.Parameter(torch.eye(3, device=device).repeat(count, 1, 1))
        self.bias = torch.nn.Parameter(torch.zeros(count, 3, device=device))

    def forward(self, index: int, rgb: torch.Tensor) -> torch.Tensor:
        """rgb [H, W, 3] as image `index`'s camera recorded it."""
        return rgb @ self.matrix[index].T + self.bias[index]

    @torch.no_grad()
    def centre(self) -> None:
        """Make the median transform (entry by entry) the identity. The scene's colours and a change common to every
        transform explain the photos equally well; left free, the transforms take up whatever the young scene lacks
        (a brightness the scene then never learns, and that renders without transforms lack). Held at the median,
        the scene keeps the colours of the typical photo, as the L1 loss does without transforms, and each transform
        only how its photo departs from it (the mean would tint the scene toward the odd photos instead)."""
        self.matrix -= self.matrix.median(dim=0).values - torch.eye(3, device=self.matrix.device)
        self.bias -= self.bias.median(dim=0).values

    def pull(self, index: int) -> torch.Tensor:
        """The squared distance of image `index`'s transform from identity (the regulariser)."""
        identity = torch.eye(3, device=self.matrix.device)
        return ((self.matrix[index] - identity) ** 2).sum() + (self.bias[index] ** 2).sum()


def make_appearance(mode: str, count: int, device: torch.device) -> AffineAppearance | None:
    return AffineAppearance(count, device) if mode == "affine" else None


def make_optimizer(appearance: AffineAppearance, lr: float) -> torch.optim.Adam:
    return torch.optim.Adam(appearance.parameters(), lr=lr, eps=1e-15)


def lr_at(step: int, steps: int, lr: float, lr_final: float) -> float:
    """Log-linear from lr at step 0 to lr_final at the last step."""
    t = min(max(step / max(steps, 1), 0.0), 1.0)
    return math.exp((1 - t) * math.log(lr) + t * math.log(lr_final))


def set_lr(optimizer: torch.optim.Optimizer, lr: float) -> None:
    for group in optimizer.param_groups:
        group["lr"] = lr


def fitted_transform(render: torch.Tensor, photo: torch.Tensor) -> torch.Tensor:
    """The affine colour transform [4, 3] (rows: A^T, then b) that best maps `render` onto `photo` in the least
    squares sense, both [H, W, 3]."""
    x = torch.cat([render.reshape(-1, 3), torch.ones_like(render.reshape(-1, 3)[:, :1])], dim=1).double()
    return torch.linalg.lstsq(x, photo.reshape(-1, 3).double()).solution.to(render.dtype)


def apply_transform(transform: torch.Tensor, rgb: torch.Tensor) -> torch.Tensor:
    return rgb @ transform[:3] + transform[3]


def split_halves(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The left and right halves of an [H, W, C] image (the left one a column narrower for an odd width)."""
    half = image.shape[1] // 2
    return image[:, :half], image[:, half:]


class Compensation:
    """What a training step needs of the appearance model: the transforms, their Adam, the schedule and the pull."""

    def __init__(self, transforms: AffineAppearance, lr: float, lr_final: float, pull_weight: float):
        self.transforms, self.lr, self.lr_final, self.pull_weight = transforms, lr, lr_final, pull_weight
        self.optimizer = make_optimizer(transforms, lr)

    def apply(self, index: int, rgb: torch.Tensor) -> torch.Tensor:
        return self.transforms(index, rgb)

    def regularization(self, index: int) -> torch.Tensor:
        return self.pull_weight * self.transforms.pull(index)

    def step(self, step: int, steps: int) -> None:
        """The Adam step of this training step (at its scheduled learning rate)."""
        set_lr(self.optimizer, lr_at(step, steps, self.lr, self.lr_final))
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.transforms.centre()

    def state_dict(self) -> dict:
        return {"transforms": self.transforms.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.transforms.load_state_dict(state["transforms"])
        self.optimizer.load_state_dict(state["optimizer"])
