"""Pinhole cameras in the OpenCV convention (x right, y down, z forward), pixel centres at +0.5."""

from __future__ import annotations

from dataclasses import dataclass

import torch

SCALED_KEPT = 4  # the sizes of a camera `scaled` keeps


@dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    K is the 3x3 intrinsic matrix in pixels for an image of `width` x `height`, with the COLMAP convention that the
    centre of the top-left pixel is at (0.5, 0.5). `world_to_camera` is a 4x4 rigid transform into OpenCV camera
    coordinates. Both are float32 tensors.
    """

    K: torch.Tensor
    world_to_camera: torch.Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.K.shape != (3, 3) or self.world_to_camera.shape != (4, 4):
            raise ValueError(f"Camera needs K [3,3] and world_to_camera [4,4], got {tuple(self.K.shape)} and "
                             f"{tuple(self.world_to_camera.shape)}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Camera size must be positive, got {self.width}x{self.height}")

    @property
    def fx(self) -> float:
        return self.focal_and_centre[0]

    @property
    def fy(self) -> float:
        return self.focal_and_centre[1]

    @property
    def cx(self) -> float:
        return self.focal_and_centre[2]

    @property
    def cy(self) -> float:
        return self.focal_and_centre[3]

    @property
    def focal_and_centre(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) as Python numbers: read from K once per camera (the camera a camera was moved from by
        `to` hands them over), not at every render, where reading a GPU tensor would wait for the queued kernels."""
        numbers = self.__dict__.get("_focal_and_centre")
        if numbers is None:
            K = (self.on_host() or self).K.detach()
            numbers = tuple(float(K[i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
            object.__setattr__(self, "_focal_and_centre", numbers)
        return numbers

    @property
    def pose_numbers(self) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        """(rotation row-major, translation, centre) of world_to_camera as Python numbers (the float32 values, the
        centre computed in float32), read once per camera as focal_and_centre is."""
        numbers = self.__dict__.get("_pose_numbers")
        if numbers is None:
            source = self.on_host() or self
            w2c = source.world_to_camera.detach().to(dtype=torch.float64).cpu()
            center = source.center.detach().to(dtype=torch.float64).cpu()
            numbers = (tuple(w2c[:3, :3].reshape(-1).tolist()), tuple(w2c[:3, 3].tolist()), tuple(center.tolist()))
            object.__setattr__(self, "_pose_numbers", numbers)
        return numbers

    def with_pose(self, world_to_camera: torch.Tensor) -> "Camera":
        """This camera (its intrinsics, already read) at another pose."""
        posed = Camera(K=self.K, world_to_camera=world_to_camera, width=self.width, height=self.height)
        object.__setattr__(posed, "_focal_and_centre", self.focal_and_centre)
        return posed

    @property
    def center(self) -> torch.Tensor:
        """Camera centre in world coordinates, [3]."""
        rotation = self.world_to_camera[:3, :3]
        translation = self.world_to_camera[:3, 3]
        return -rotation.T @ translation

    def scaled(self, width: int, height: int) -> "Camera":
        """The same camera for an image resized to width x height (intrinsics scaled per axis). The last few sizes
        asked for are kept, so that a run at full size (or its coarse phase's last sizes) reads their numbers once."""
        made = self.__dict__.setdefault("_scaled", {})
        if (width, height) not in made:
            sx, sy = width / self.width, height / self.height
            K = self.K.clone()
            K[0, :] *= sx
            K[1, :] *= sy
            if len(made) >= SCALED_KEPT:  # coarse to fine asks for a new size at many steps: keep the newest
                made.pop(next(iter(made)))
            made[(width, height)] = Camera(K=K, world_to_camera=self.world_to_camera, width=width, height=height)
        return made[(width, height)]

    def to(self, device: torch.device | str) -> "Camera":
        """The camera with its tensors on `device`; it remembers the host copy it came from (see `on_host`). Moved to
        another device, a camera whose pose is not being learned keeps the copy it made, so that a training step on a
        view seen before copies nothing to the GPU (a copy from pageable memory waits for the GPU's queue); on its own
        device nothing is copied, and nothing is kept (small objects kept between the large transient buffers of
        many renders raise the process's peak memory)."""
        target = torch.device(device)
        learned = self.world_to_camera.requires_grad or self.K.requires_grad
        keep = not learned and target != self.K.device
        made = self.__dict__.setdefault("_moved", {})
        key = str(target)
        if keep and key in made:
            return made[key]
        moved = Camera(K=self.K.to(device), world_to_camera=self.world_to_camera.to(device),
                       width=self.width, height=self.height)
        object.__setattr__(moved, "_host", self.on_host())
        object.__setattr__(moved, "_focal_and_centre", self.focal_and_centre)
        if not learned:  # a pose being learned is read where it is used
            object.__setattr__(moved, "_pose_numbers", self.pose_numbers)
        if keep:
            made[key] = moved
        return moved

    def on_host(self) -> "Camera | None":
        """This camera with its tensors in host memory, without a copy from the device: itself when its tensors are
        there, the camera it was moved from by `to`, else None. A kernel's scalar arguments are read from it, for
        reading them from GPU tensors would wait for every kernel queued before."""
        if self.K.device.type == "cpu" and self.world_to_camera.device.type == "cpu":
            return self
        return getattr(self, "_host", None)

    def to_camera_space(self, points: torch.Tensor) -> torch.Tensor:
        """World points [N, 3] in this camera's coordinates, in their own dtype and device."""
        w2c = self.world_to_camera.to(points.device, points.dtype)
        return points @ w2c[:3, :3].T + w2c[:3, 3]

    def pixels_of(self, local: torch.Tensor, near: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(u, v, inside): the pixel coordinates (centres at +0.5) of camera-space points [N, 3], and which of them lie
        in front of depth `near` and project inside the image. Points at or behind `near` take depth 1 for the
        division (their u, v mean nothing), so that no value is infinite."""
        z = local[:, 2]
        in_front = z > near
        z_safe = torch.where(in_front, z, torch.ones_like(z))
        u = local[:, 0] / z_safe * self.fx + self.cx
        v = local[:, 1] / z_safe * self.fy + self.cy
        return u, v, in_front & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> torch.Tensor:
    """A 3x3 float32 intrinsic matrix."""
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float32)
