"""Small helpers shared by several test modules (pytest puts this folder on sys.path)."""

from __future__ import annotations

import torch


def visible_fraction(view, points: torch.Tensor) -> float:
    """Share of `points` that project inside the view's image with positive depth."""
    cam = view.camera
    in_camera = points @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    z = in_camera[:, 2]
    uv = (in_camera @ cam.K.T)[:, :2] / z[:, None]
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    return inside.float().mean().item()
