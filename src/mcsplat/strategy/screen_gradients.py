"""The per-Gaussian screen-space gradient statistic of 3DGS's densification, shared by ADC and MCMC's automatic cap.

After each backward, every Gaussian visible in the view adds the norm of its 2D position gradient, in the units of
3DGS's threshold: render_result.means2d.grad is per pixel, and 3DGS's rasterizer reports it per NDC unit, i.e. x
multiplied by width / 2 and y by height / 2. Its mean over the views it was seen in is what 3DGS compares with its
densification threshold (0.0002).
"""

from __future__ import annotations

from typing import Any

import torch

__all__ = ["ndc_gradient_norms", "ScreenGradients"]


def ndc_gradient_norms(render_result: Any, num_gaussians: int, width: int, height: int
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """(visible [N] bool, [N] the NDC gradient norm of each Gaussian, 0 where not visible) of one render after its
    backward; dense, so that nothing waits to count the visible ones."""
    grad = render_result.means2d.grad
    if grad is None:
        raise RuntimeError("the screen-space gradient statistic needs render_result.means2d.grad: call it after "
                           "loss.backward() on a render of parameters that require gradients")
    if grad.shape[0] != num_gaussians:
        raise ValueError(f"the render has {grad.shape[0]} Gaussians but the model {num_gaussians}")
    visible = render_result.radii > 0
    ndc = torch.stack([grad[:, 0] * (0.5 * width), grad[:, 1] * (0.5 * height)], dim=-1)  # no tensor to upload
    norms = torch.linalg.vector_norm(ndc, dim=-1)
    return visible, torch.where(visible, norms, torch.zeros_like(norms))


class ScreenGradients:
    """Sums of NDC gradient norms and view counts per Gaussian since the last reset."""

    def __init__(self) -> None:
        self.total: torch.Tensor | None = None  # [N] float32
        self.views: torch.Tensor | None = None  # [N] int32

    def reset(self, n: int, device: torch.device) -> None:
        """Zeros for `n` Gaussians, in the same tensors where they fit (a step replayed as a CUDA graph adds to the
        ones its capture found)."""
        if self.total is not None and self.total.shape[0] == n and self.total.device == torch.device(device):
            self.total.zero_()
            self.views.zero_()
            return
        self.total = torch.zeros(n, dtype=torch.float32, device=device)
        self.views = torch.zeros(n, dtype=torch.int32, device=device)

    @torch.no_grad()
    def add(self, render_result: Any, num_gaussians: int, width: int, height: int) -> torch.Tensor:
        """Add one render's norms; returns which Gaussians it saw ([N] bool)."""
        visible, norms = ndc_gradient_norms(render_result, num_gaussians, width, height)
        if self.total is None or self.total.shape[0] != num_gaussians:
            self.reset(num_gaussians, visible.device)
        self.total += norms.to(self.total.dtype)
        self.views += visible
        return visible

    def to(self, device: torch.device) -> None:
        """Move the sums to `device` (a checkpoint loads on the CPU)."""
        if self.total is not None and self.total.device != device:
            self.total, self.views = self.total.to(device), self.views.to(device)

    def means(self) -> torch.Tensor | None:
        """[N] mean norm over the views each Gaussian was seen in (0 where never seen), or None before any add."""
        if self.total is None:
            return None
        return torch.where(self.views > 0, self.total / self.views.clamp(min=1), torch.zeros_like(self.total))

    def state_dict(self) -> dict:
        return {"total": None if self.total is None else self.total.clone(),
                "views": None if self.views is None else self.views.clone()}

    def load_state_dict(self, state: dict) -> None:
        total, views = state.get("total"), state.get("views")
        self.total = None if total is None else total.clone()
        self.views = None if views is None else views.clone()
