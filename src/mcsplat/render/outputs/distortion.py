"""2DGS's depth distortion: how far apart in depth the Gaussians a pixel composites lie, what
render(outputs={"distortion"}) gives and what --surface-distortion pulls down.

For a pixel with compositing weights w_i and mapped depths m_i (front to back), 2DGS's term is

    sum over pairs i < j of w_i w_j (m_i - m_j)^2.

The sum over all ordered pairs is half the sum over every (i, j), and that one expands into sums a compositing pass
already makes: with A = sum w_i (the alpha), S1 = sum w_i m_i and S2 = sum w_i m_i^2,

    sum_{i<j} w_i w_j (m_i - m_j)^2 = A S2 - S1^2.

So the term needs no kernel of its own: each Gaussian's m and m^2 are composited like a colour, in the same kernels
(SIMD on the CPU, tiles on CUDA, scalar for float64), and their backward gives the term's gradient to the weights
and to the depths exactly. The reference renderer computes the pairwise sum itself, as the test oracle.

The depth is mapped as 2DGS maps it, m = f / (f - n) (1 - n / z): up to a scale and an offset, which the pairs'
differences do not see, the inverse depth. Here m = 1 / z (units^-1): far layers count less than near ones, so a
capture's distant background, which a pixel sees through several soft layers, does not dominate the term. A loss
multiplies the map by the square of a length of the scene (surface_terms.py uses its radius) to make it unitless.
"""

from __future__ import annotations

import torch

from ...camera import Camera


def inverse_depths(means: torch.Tensor, camera: Camera, near: float) -> torch.Tensor:
    """[N] 1 / camera z of each Gaussian's centre, with gradients to the means. A centre nearer than the near plane
    (culled, never composited) is held at it, so that its gradient is zero rather than undefined."""
    world_to_camera = camera.world_to_camera.to(dtype=means.dtype, device=means.device)
    z = means @ world_to_camera[2, :3] + world_to_camera[2, 3]
    return 1.0 / z.clamp_min(near)


def distortion_from_sums(alpha: torch.Tensor, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
    """[H, W] sum_{i<j} w_i w_j (m_i - m_j)^2 from A = sum w_i, S1 = sum w_i m_i, S2 = sum w_i m_i^2. Not clamped:
    rounding may leave it a little below zero where every layer lies at one depth, which a loss does not mind."""
    return alpha * second - first * first
