"""Which torch device a command runs on: `--device auto|cpu|cuda`."""

from __future__ import annotations

import torch

from ..errors import MCSplatError


def resolve_device(name: str) -> torch.device:
    """auto: CUDA when torch sees a GPU, else the CPU; cuda without a GPU is a one-line error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise MCSplatError("--device cuda: no CUDA device is available here; use --device cpu (or auto)")
    return torch.device(name)
