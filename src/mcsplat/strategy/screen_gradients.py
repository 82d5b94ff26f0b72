"""The per-Gaussian screen-space gradient statistic of 3DGS's densification, shared by ADC and MCMC's automatic cap.

After each backward, every Gaussian visible in the view adds the norm of its 2D position gradient, in the units of
3DGS's threshold: render_result.means2d.grad is per pixel, and 3DGS's rasterizer reports it per NDC unit, i.e. x
multiplied by width / 2 and y by height / 2. Its mean over the views it was seen in is what 3DGS compares with its
densification threshold (0.0002).
"""

from __future__ import annotations

from typing import Any

import torch
import warp as wp

from ..compute.cpp_snippets import read_snippet
from ..compute.runtime import ensure_warp, flat_view, run_ranges
from ..render.kernel_choice import simd_serves

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


ROWS_PER_THREAD = 1024
_floats, _ints = wp.array(dtype=wp.float32), wp.array(dtype=wp.int32)


@wp.func_native(read_snippet(__package__, "screen_gradients_add.cpp", {"ROWS": ROWS_PER_THREAD}))
def _add_norms(block: int, n: int, grad: _floats, radii: _ints, total: _floats, views: _ints, half_width: float,
               half_height: float): ...


@wp.kernel
def add_norms_cpu(first_block: int, n: int, grad: _floats, radii: _ints, total: _floats, views: _ints,
                  half_width: float, half_height: float):
    """One thread per ROWS_PER_THREAD Gaussians: `ScreenGradients.add` on the CPU."""
    _add_norms(first_block + wp.tid(), n, grad, radii, total, views, half_width, half_height)


def _one_pass(render_result: Any, num_gaussians: int) -> bool:
    """Whether add_norms_cpu serves this render: float32 on the CPU with the CPU's own kernels (kernel_choice)."""
    grad = render_result.means2d.grad
    return (grad is not None and tuple(grad.shape) == (num_gaussians, 2) and simd_serves(grad)
            and render_result.radii.dtype == torch.int32)


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
        if self.total is None or self.total.shape[0] != num_gaussians:
            self.reset(num_gaussians, render_result.radii.device)
        if _one_pass(render_result, num_gaussians):  # the CPU's float32 runs: one loop in place of seven operators
            ensure_warp()
            arguments = [num_gaussians, *(flat_view(t) for t in (render_result.means2d.grad, render_result.radii,
                                                                 self.total, self.views)), 0.5 * width, 0.5 * height]
            run_ranges(add_norms_cpu, -(-num_gaussians // ROWS_PER_THREAD), self.total.device, arguments, 16)
            return render_result.radii > 0
        visible, norms = ndc_gradient_norms(render_result, num_gaussians, width, height)
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
