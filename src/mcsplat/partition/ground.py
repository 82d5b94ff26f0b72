"""The ground plane the blocks are cut on: large captures (streets, buildings, drone flights) spread along the ground,
so blocks are columns standing on it. Its normal is the mean up direction of the cameras (a camera's -y axis in
OpenCV's convention), its first axis the longest direction of the points on it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch

from ..camera import Camera

Vector = tuple[float, float, float]


@dataclass(frozen=True)
class GroundFrame:
    """Two orthonormal axes spanning the ground plane and its normal (`up`), in world coordinates."""

    first: Vector
    second: Vector
    up: Vector

    def coordinates(self, xyz: torch.Tensor) -> torch.Tensor:
        """[N, 2] float64: where the points [N, 3] stand on the ground plane."""
        axes = torch.tensor([self.first, self.second], dtype=torch.float64)
        return xyz.to(torch.float64) @ axes.T

    def to_json(self) -> dict:
        return {"first": list(self.first), "second": list(self.second), "up": list(self.up)}

    @classmethod
    def from_json(cls, data: dict) -> "GroundFrame":
        return cls(*(tuple(float(v) for v in data[key]) for key in ("first", "second", "up")))


def ground_of(cameras: Sequence[Camera], points: torch.Tensor) -> GroundFrame:
    """The ground frame of a capture: up from the cameras, the first axis along the points' longest spread on the
    plane (so that the first cut goes across the scene's long side)."""
    ups = torch.stack([-camera.world_to_camera[1, :3].to(torch.float64) for camera in cameras])
    up = ups.mean(dim=0)
    if up.norm() < 0.3:  # cameras held every which way: no common up; the world's z is as good as any
        up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    up = up / up.norm()
    helper = torch.tensor([1.0, 0.0, 0.0] if abs(float(up[0])) < 0.9 else [0.0, 1.0, 0.0], dtype=torch.float64)
    first = torch.linalg.cross(up, helper)
    first = first / first.norm()
    second = torch.linalg.cross(up, first)
    flat = points.to(torch.float64) @ torch.stack([first, second]).T
    if flat.shape[0] >= 2:
        centred = flat - flat.mean(dim=0)
        _, vectors = torch.linalg.eigh(centred.T @ centred)
        a, b = vectors[:, 1]  # the direction of the largest spread, in (first, second)
        first, second = a * first + b * second, -b * first + a * second
    return GroundFrame(_vector(first), _vector(second), _vector(up))


def _vector(v: torch.Tensor) -> Vector:
    return (float(v[0]), float(v[1]), float(v[2]))
