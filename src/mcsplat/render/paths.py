"""The stages render() runs, as one value that callers can choose: the kernel path every command uses, and the torch
baseline the speed benchmarks compare against in the same process.

    project    (means, quats, scales, opacities, sh, camera, sh_degree, sh_rest=, near=, far=, eps2d=,
                opacity_aware_radius=, antialiased=) -> (Projection, colours [N, 3])
    bin        (tile_min, tile_max, depths, radii, tiles_x, tiles_y, means2d=, alpha_extent=) -> TileBins
    composite  (means2d, conics, opacities, colours, depths, background, bins, width, height[, median_gaussian=True])
               -> (rgb, alpha, accumulated depth, contributed[, median Gaussian per pixel])

`use_render_path(path)` makes `path` the one render() takes in the current thread or task (a benchmark wraps the
stages with timers this way); `render(..., path=...)` chooses it for one call.
"""

from __future__ import annotations

import contextlib
import functools
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Callable, Iterator

from .bin.torch_oracle import torch_bin_gaussians
from .bin.warp_kernels import bin_gaussians
from .composite.function import composite
from .project.torch_autograd import project_and_shade_torch
from .project.warp_kernel import project_and_shade

__all__ = ["RenderPath", "KERNEL_PATH", "TORCH_BASELINE_PATH", "current_render_path", "use_render_path"]


@dataclass(frozen=True)
class RenderPath:
    project: Callable
    bin: Callable
    composite: Callable


# Projection and SH in one Warp kernel, binning in Warp, compositing in the SIMD (CPU, float32) or scalar kernels.
KERNEL_PATH = RenderPath(project=project_and_shade, bin=bin_gaussians, composite=composite)
# The render path as it was before the CPU kernels: torch projection, SH and binning, scalar Warp compositing.
TORCH_BASELINE_PATH = RenderPath(project=project_and_shade_torch, bin=torch_bin_gaussians,
                                 composite=functools.partial(composite, cpu_kernels="scalar"))

_current: ContextVar[RenderPath] = ContextVar("mcsplat_render_path", default=KERNEL_PATH)


def current_render_path() -> RenderPath:
    return _current.get()


@contextlib.contextmanager
def use_render_path(path: RenderPath) -> Iterator[RenderPath]:
    """Within the block, render() takes `path` (in this thread or task only)."""
    token = _current.set(path)
    try:
        yield path
    finally:
        _current.reset(token)
