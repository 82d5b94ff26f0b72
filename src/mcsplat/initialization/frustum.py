"""Random points where the cameras look: inside the training views' frustums, coloured by the pixel they project to.

The fallback for a real capture with poses but no points when triangulation fails: unlike a cube around the world
origin, every point starts in front of a camera, at a depth where the scene can be (log-uniform between 0.1 and 2
scene radii), with the colour that camera saw there.
"""

from __future__ import annotations

from typing import Sequence

import torch

from ..data import View

NEAR, FAR = 0.1, 2.0  # depth range in scene radii


def points_in_frustums(views: Sequence[View], scene_radius: float, count: int, generator: torch.Generator
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """(points [count, 3], colours [count, 3] in [0, 1]), spread evenly over `views`, on the CPU."""
    if not views:
        raise ValueError("points_in_frustums needs at least one view")
    which = torch.randint(len(views), (count,), generator=generator)
    u, v = torch.rand(count, generator=generator), torch.rand(count, generator=generator)
    log_near, log_far = torch.log(torch.tensor(NEAR * scene_radius)), torch.log(torch.tensor(FAR * scene_radius))
    depth = torch.exp(log_near + (log_far - log_near) * torch.rand(count, generator=generator))
    points = torch.empty(count, 3)
    colors = torch.empty(count, 3)
    for index in torch.unique(which).tolist():
        mine = which == index
        camera, image = views[index].camera, views[index].image
        px, py = u[mine] * camera.width, v[mine] * camera.height
        rays = torch.stack([(px - camera.cx) / camera.fx, (py - camera.cy) / camera.fy, torch.ones_like(px)], -1)
        in_camera = rays * depth[mine, None]
        rotation, translation = camera.world_to_camera[:3, :3], camera.world_to_camera[:3, 3]
        points[mine] = (in_camera - translation) @ rotation  # R^T (x - t), row-wise
        colors[mine] = image[py.long().clamp(max=camera.height - 1), px.long().clamp(max=camera.width - 1)] / 255.0
    return points, colors
