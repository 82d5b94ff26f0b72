"""Which torch device a command runs on: `--device auto|cpu|cuda`, how much memory it has free, and copies to it
that do not make the host wait."""

from __future__ import annotations

import os

import torch

from ..errors import MCSplatError


def resolve_device(name: str) -> torch.device:
    """auto: CUDA when torch sees a GPU, else the CPU; cuda without a GPU is a one-line error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise MCSplatError("--device cuda: no CUDA device is available here; use --device cpu (or auto)")
    return torch.device(name)


def upload(values: torch.Tensor, device: torch.device | str) -> torch.Tensor:
    """Host tensor `values` on `device` without the host waiting: to a GPU from pinned memory (a copy from pageable
    memory waits for the GPU's queue), on the CPU as they are."""
    if torch.device(device).type == "cuda" and not values.is_pinned():
        values = values.pin_memory()
    return values.to(device, non_blocking=True)


def free_memory(device: torch.device) -> int | None:
    """Bytes free on `device` (None where it cannot be told)."""
    if device.type == "cuda":
        return torch.cuda.mem_get_info(device)[0]
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None
