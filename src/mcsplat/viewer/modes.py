"""What the viewer shows of a model from one camera, rendered by our rasterizer: the RGB image, depth, accumulated
opacity, or the Gaussians' centres as small opaque dots."""

from __future__ import annotations

import numpy as np
import torch

from ..camera import Camera
from ..data.images import uint8_pixels
from ..render import Splats, render

MODES = ("RGB", "depth", "alpha", "centres")
CENTRE_SIZE = 0.002  # dot radius in units of the scene radius


def _gray(values: torch.Tensor) -> np.ndarray:
    return uint8_pixels(values[..., None].expand(*values.shape, 3))


@torch.no_grad()
def render_mode(model, camera: Camera, mode: str, background, sh_degree: int, scene_radius: float) -> np.ndarray:
    """uint8 [H, W, 3] image of `model` (anything with the GaussianModel properties) in `mode`."""
    if mode == "centres":
        n = model.means.shape[0]
        dots = Splats(means=model.means, quats=model.quats,
                      scales=model.means.new_full((n, 3), CENTRE_SIZE * scene_radius),
                      opacities=model.means.new_ones(n), sh=model.sh[:, :1])
        return uint8_pixels(render(dots, camera, background, 0).rgb)
    result = render(model, camera, background, sh_degree)
    if mode == "RGB":
        return uint8_pixels(result.rgb)
    if mode == "alpha":
        return _gray(result.alpha)
    covered = result.alpha > 0.05
    depth = result.depth
    if covered.any():  # near = white, far = black, over the depths actually seen
        near, far = torch.quantile(depth[covered], torch.tensor([0.02, 0.98], device=depth.device))
        shade = 1.0 - (depth - near) / (far - near).clamp(min=1e-6)
        return _gray(torch.where(covered, shade.clamp(0.05, 1.0), torch.zeros_like(depth)))
    return _gray(torch.zeros_like(depth))
