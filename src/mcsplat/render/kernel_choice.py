"""Which kernels the renderer runs: one choice for the CPU and one for CUDA, read by every stage.

float32 tensors on the CPU get the CPU's own kernels ('simd': the SIMD projection and compositing of render/cpu/ and
the binning's C++ loops); float64 on the CPU the scalar Warp kernels; CUDA the tile kernels (a block of threads per
tile). `set_cpu_kernels("scalar")` puts the Warp kernels CUDA runs on the CPU too (the benchmarks' in-process
baseline, the tests' second opinion), `set_cpu_kernels("tile")` runs the CUDA tile kernels on the CPU as cooperative
fibers (how the tests check them without a GPU), and `set_cuda_kernels("scalar")` puts the scalar compositing
kernels back on CUDA (the GPU benchmarks' in-process baseline).
"""

from __future__ import annotations

import torch

CPU_KERNELS = ("simd", "scalar", "tile")
# "tile-all": the tile backward without its skip of pairs no pixel of a warp uses (tile_kernels.backward_kernel).
CUDA_KERNELS = ("tile", "tile-all", "scalar")
_cpu_kernels = "simd"
_cuda_kernels = "tile"


def set_cpu_kernels(name: str) -> None:
    """'simd' (the default), 'scalar' or 'tile' (the CUDA kernels on CPU fibers, for tests): which kernels float32
    renders on the CPU use."""
    global _cpu_kernels
    if name not in CPU_KERNELS:
        raise ValueError(f"CPU kernels must be one of {', '.join(CPU_KERNELS)}, got {name!r}")
    _cpu_kernels = name


def cpu_kernels() -> str:
    return _cpu_kernels


def set_cuda_kernels(name: str) -> None:
    """'tile' (the default), 'tile-all' or 'scalar': which compositing kernels CUDA renders use."""
    global _cuda_kernels
    if name not in CUDA_KERNELS:
        raise ValueError(f"CUDA kernels must be one of {', '.join(CUDA_KERNELS)}, got {name!r}")
    _cuda_kernels = name


def cuda_kernels() -> str:
    return _cuda_kernels


def kernels_for(tensor: torch.Tensor, cpu_choice: str | None = None) -> str:
    """'simd', 'scalar', 'tile' or 'tile-all': the kernels a render of `tensor` runs (`cpu_choice` overrides the
    CPU's)."""
    if tensor.device.type == "cuda":
        return _cuda_kernels
    chosen = cpu_choice or _cpu_kernels
    return "scalar" if chosen == "simd" and tensor.dtype != torch.float32 else chosen
