"""Compiling Warp kernel modules ahead of their first launch, so that a caller can say so while it happens.

A fresh machine compiles every kernel module once (tens of seconds on two cores for the SIMD snippets); later runs
load them from Warp's kernel cache, which Warp keys by the module's contents and, on the CPU, by the host's ISA
(-march=native), so a binary built for one CPU is never loaded on another. Kernels compile on demand at their first
launch and print nothing; the trainer gathers the kernels a step launches (render.training_kernels,
losses.training_kernels), asks `modules_to_compile` how many are missing and tells the user before `compile_kernels`.
"""

from __future__ import annotations

import os
from typing import Sequence

import torch
import warp as wp

from .runtime import ensure_warp, warp_device


def _modules(kernels: Sequence) -> list:
    """(module, block size) pairs: a tile kernel names its block size (`launch_block_dim`), and Warp builds a module
    once per block size it is launched with; None is Warp's default."""
    unique = {}
    for kernel in kernels:
        block_dim = getattr(kernel, "launch_block_dim", None)
        unique[(id(kernel.module), block_dim)] = (kernel.module, block_dim)
    return list(unique.values())


def _is_cached(module, device, block_dim=None) -> bool:
    """Whether Warp's kernel cache already holds this module's binary for the device (Warp 1.19's own layout)."""
    try:
        folder = os.path.join(wp.config.kernel_cache_dir, module.get_module_identifier(block_dim=block_dim))
        return os.path.exists(os.path.join(folder, module._get_compile_output_name(device, block_dim=block_dim)))
    except Exception:  # a Warp whose internals differ: assume a compile may follow
        return False


def _warp_device(device: torch.device):
    return wp.get_device(str(device) if device.type == "cpu" else warp_device(device))


def modules_to_compile(kernels: Sequence, device: torch.device) -> int:
    """How many of the modules holding `kernels` are not yet in Warp's cache for this device."""
    ensure_warp()
    wp_device = _warp_device(device)
    return sum(not _is_cached(m, wp_device, b) for m, b in _modules(kernels))


def compile_kernels(kernels: Sequence, device: torch.device) -> None:
    """Compile (or load from the cache) the modules holding `kernels` for this device."""
    ensure_warp()
    wp_device = _warp_device(device)
    for module, block_dim in _modules(kernels):
        module.load(wp_device, block_dim)
