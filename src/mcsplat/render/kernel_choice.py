"""Which kernels the renderer runs: one choice for the CPU and one for CUDA, read by every stage.

On the CPU, 'simd' (the default) runs the CPU's own kernels (each stage's cpu_*.py): the SIMD projection and compositing
for float32 tensors (float64 gets the scalar Warp kernels) and the binning's C++ loops. 'scalar' runs the Warp kernels
instead (the projection and binning as CUDA runs them, the scalar compositing): the benchmarks' in-process baseline and
the tests' second opinion. 'tile' is 'scalar' with CUDA's tile compositing run as cooperative fibers (how the tests
check it without a GPU). On CUDA, 'tile' (the default) or 'tile-all' compositing, or 'scalar' (the GPU benchmarks'
in-process baseline).
"""

from __future__ import annotations

import torch

CPU_KERNELS = ("simd", "scalar", "tile")
# "tile-all": the tile backward without its skip of pairs no pixel of a warp uses (composite/warp_tiles.py's
# backward_kernel).
CUDA_KERNELS = ("tile", "tile-all", "scalar")
# The choice per kind of device (the keys name it in errors) and the names it may take.
_chosen = {"CPU": "simd", "CUDA": "tile"}
_CHOICES = {"CPU": CPU_KERNELS, "CUDA": CUDA_KERNELS}


def _choose(device: str, name: str) -> None:
    if name not in _CHOICES[device]:
        raise ValueError(f"{device} kernels must be one of {', '.join(_CHOICES[device])}, got {name!r}")
    _chosen[device] = name


def set_cpu_kernels(name: str) -> None:
    """'simd' (the default), 'scalar' or 'tile' (the CUDA kernels on CPU fibers, for tests): which kernels float32
    renders on the CPU use."""
    _choose("CPU", name)


def cpu_kernels() -> str:
    return _chosen["CPU"]


def set_cuda_kernels(name: str) -> None:
    """'tile' (the default), 'tile-all' or 'scalar': which compositing kernels CUDA renders use."""
    _choose("CUDA", name)


def cuda_kernels() -> str:
    return _chosen["CUDA"]


def kernels_for(tensor: torch.Tensor, cpu_choice: str | None = None) -> str:
    """'simd', 'scalar', 'tile' or 'tile-all': the kernels a render of `tensor` runs (`cpu_choice` overrides the
    CPU's)."""
    if tensor.device.type == "cuda":
        return _chosen["CUDA"]
    chosen = cpu_choice or _chosen["CPU"]
    return "scalar" if chosen == "simd" and tensor.dtype != torch.float32 else chosen


def simd_serves(*tensors: torch.Tensor) -> bool:
    """Whether the CPU's own SIMD kernels serve these tensors: float32 and contiguous, where renders of them run
    'simd' (not while the CPU stands in for CUDA's kernels)."""
    return (kernels_for(tensors[0]) == "simd"
            and all(t.dtype == torch.float32 and t.is_contiguous() for t in tensors))
