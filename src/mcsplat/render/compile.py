"""Compiling the Warp kernels ahead of the first step, so that a caller can say so while it happens.

A fresh machine compiles every kernel module once (tens of seconds on two cores for the SIMD snippets); later runs
load them from Warp's kernel cache, which Warp keys by the module's contents and, on the CPU, by the host's ISA
(-march=native), so a binary built for one CPU is never loaded on another. render() compiles on demand and prints
nothing; `mcsplat train` calls `compile_kernels` first and tells the user when a compile is under way.
"""

from __future__ import annotations

import os

import torch
import warp as wp

from .runtime import ensure_warp, warp_device


def _training_kernels(device: torch.device, dtype: torch.dtype) -> list:
    from .. import ssim_cpu
    from . import binning, kernels, project_kernel
    from .cpu import composite
    from .runtime import warp_scalar

    scalar = warp_scalar(dtype)
    found = [*project_kernel.projection_kernels(scalar), binning._count_pairs, binning._write_pairs]
    if device.type == "cpu" and dtype == torch.float32:
        found += [composite.composite_forward_simd, composite.composite_backward_simd,
                  ssim_cpu._pass1, ssim_cpu._pass2, ssim_cpu._pass3, ssim_cpu._pass4]
    else:
        found += list(kernels.composite_kernels(scalar))
    return found


def _modules(device: torch.device, dtype: torch.dtype) -> list:
    unique = {}
    for kernel in _training_kernels(device, dtype):
        unique[id(kernel.module)] = kernel.module
    return list(unique.values())


def _is_cached(module, device) -> bool:
    """Whether Warp's kernel cache already holds this module's binary for the device (Warp 1.19's own layout)."""
    try:
        folder = os.path.join(wp.config.kernel_cache_dir, module.get_module_identifier())
        return os.path.exists(os.path.join(folder, module._get_compile_output_name(device)))
    except Exception:  # a Warp whose internals differ: assume a compile may follow
        return False


def modules_to_compile(device: torch.device, dtype: torch.dtype = torch.float32) -> int:
    """How many of the training kernels' modules are not yet in Warp's cache for this device."""
    ensure_warp()
    wp_device = wp.get_device(str(device) if device.type == "cpu" else warp_device(device))
    return sum(not _is_cached(m, wp_device) for m in _modules(device, dtype))


def compile_kernels(device: torch.device, dtype: torch.dtype = torch.float32) -> None:
    """Compile (or load from the cache) every kernel a training step launches on this device."""
    ensure_warp()
    wp_device = wp.get_device(str(device) if device.type == "cpu" else warp_device(device))
    for module in _modules(device, dtype):
        module.load(wp_device)
