"""Camera pose refinement (`--pose-opt`): a small rigid correction per training image, learned with the scene.

The poses of a phone capture come from structure from motion and are slightly off; a scene fitted to them blurs
what the views disagree on. Each training image gets a correction, a rotation vector omega (radians) and a
translation tau (in scene radii, so that one learning rate suits scenes of any size), zero at the start, applied in
the camera's own axes:

    W' = exp(twist(omega, R tau)) W        W the image's world-to-camera matrix, R the scene radius

learned with its own Adam and weight decay (gsplat's `pose_opt`). The gradient reaches W' through the projection
kernel's hand-written backward (render/project/warp_kernel.py) and torch takes it on to (omega, tau) through the matrix
exponential. Held-out views keep their poses: they are the reference the scene is scored against. The corrections
are in the checkpoint (under "poses"); the scene and its exports do not depend on them. It is a per-image module
(per_image.py): it moves the camera, and adds no loss term (its pull toward zero is Adam's weight decay).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import torch

from .camera import Camera
from .errors import MCSplatError
from .option_checks import refuse_non_finite
from .features import FeatureParts, FeatureStart
from .per_image import PerImageModule, PlanSteps


def correction_matrix(delta: torch.Tensor, scene_radius: float) -> torch.Tensor:
    """[4, 4] rigid transform of one correction delta [6] = (omega, tau); the identity for delta = 0."""
    omega, tau = delta[:3], delta[3:] * scene_radius
    twist = torch.zeros(4, 4, dtype=delta.dtype, device=delta.device)
    twist[0, 1], twist[0, 2], twist[1, 2] = -omega[2], omega[1], -omega[0]
    twist[1, 0], twist[2, 0], twist[2, 1] = omega[2], -omega[1], omega[0]
    twist[:3, 3] = tau
    return torch.linalg.matrix_exp(twist)


class PoseRefinement(PerImageModule):
    """The corrections of `count` training images [count, 6] and their Adam."""

    key = "poses"

    def __init__(self, count: int, scene_radius: float, device: torch.device, lr: float, weight_decay: float):
        self.scene_radius = scene_radius
        self.deltas = torch.nn.Parameter(torch.zeros(count, 6, device=device))
        self.optimizer = torch.optim.Adam([self.deltas], lr=lr, weight_decay=weight_decay)

    def camera(self, index: int, camera: Camera) -> Camera:
        """Training image `index`'s camera with its correction (differentiable in the correction)."""
        view = camera.world_to_camera
        corrected = correction_matrix(self.deltas[index], self.scene_radius).to(view) @ view
        return camera.with_pose(corrected)

    def step(self, step: int = 0, plan: PlanSteps | None = None) -> None:
        """A constant learning rate: the step and the plan do not matter."""
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    @torch.no_grad()
    def summary(self) -> dict[str, float]:
        """The median and largest rotation (degrees) and translation (scene radii) of the corrections learned."""
        degrees = self.deltas[:, :3].norm(dim=1) * (180.0 / math.pi)
        radii = self.deltas[:, 3:].norm(dim=1)
        return {"median_degrees": float(degrees.median()), "max_degrees": float(degrees.max()),
                "median_radii": float(radii.median()), "max_radii": float(radii.max())}

    def state_dict(self) -> dict:
        return {"deltas": self.deltas.detach().clone(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict | None) -> None:
        if state is None:
            raise MCSplatError("--pose-opt: the checkpoint was trained without it; resume without --pose-opt, "
                               "or train a new run")
        with torch.no_grad():
            self.deltas.copy_(state["deltas"])
        self.optimizer.load_state_dict(state["optimizer"])


@dataclass(frozen=True)
class PoseOptions:
    """Camera pose refinement."""

    pose_opt: bool = False
    """Learn a small rigid correction of each training image's pose with the scene (SfM poses of phone captures are
    slightly off); test views keep theirs."""
    pose_opt_lr: float = 1e-4
    """Adam learning rate of the corrections (rotation in radians, translation in scene radii; gsplat's 1e-5 is set
    for 30,000 GPU steps and moves them too little in a few thousand: docs/imperfect-captures.md) ..."""
    pose_opt_reg: float = 1e-6
    """... and their weight decay."""

    def __post_init__(self) -> None:
        refuse_non_finite(self)
        if not (self.pose_opt_lr > 0 and self.pose_opt_reg >= 0):
            raise MCSplatError("--pose-opt-lr must be positive, --pose-opt-reg 0 or more")

    def check_processes(self, world_size: int) -> None:
        if self.pose_opt and world_size > 1:
            raise MCSplatError("--pose-opt does not work with several training processes yet (each holds the "
                               "corrections of its own views); train in one process, or leave it out")

    def setup(self, start: FeatureStart) -> FeatureParts:
        if not self.pose_opt:
            return FeatureParts()
        return FeatureParts(modules=[PoseRefinement(len(start.scene.train), start.scene.radius, start.device,
                                                    self.pose_opt_lr, self.pose_opt_reg)])

    def facts(self, modules: Sequence[PerImageModule]) -> dict[str, Any]:
        """metrics.json's pose_corrections: how far the poses moved."""
        poses = next((module for module in modules if isinstance(module, PoseRefinement)), None)
        return {"pose_corrections": poses.summary()} if poses is not None else {}
