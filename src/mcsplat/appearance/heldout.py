"""The colour transform of a held-out view, for 3DGS's `train_test_exp` protocol (run/evaluation.py): fitted on the
left half of its photo by least squares (a frozen scene makes that exact), the right half scored with it. Every
appearance mode is scored this way, the bilateral grid too: a grid fitted on one half would have nothing to say
about the other half's cells."""

from __future__ import annotations

import torch


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
