"""Quaternions to rotation matrices and the 3D covariance Sigma = R S S^T R^T, in torch (autograd gives the
backward). Quaternions are (w, x, y, z) and need not be unit length: they are normalised here, as the model stores
them raw."""

from __future__ import annotations

import torch


def quaternion_to_rotation(quats: torch.Tensor) -> torch.Tensor:
    """Unit-normalised (w, x, y, z) quaternions [N, 4] -> rotation matrices [N, 3, 3]."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def covariance_3d(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Sigma = R S S^T R^T from quaternions [N, 4] and (activated) scales [N, 3] -> [N, 3, 3]."""
    m = quaternion_to_rotation(quats) * scales[:, None, :]
    return m @ m.transpose(1, 2)
