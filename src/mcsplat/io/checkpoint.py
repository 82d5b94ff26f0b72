"""Checkpoints: everything needed to continue a run exactly, written atomically (temp file + rename)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from ..errors import MCSplatError
from .atomic import atomic_write

CHECKPOINT_VERSION = 1


def save_checkpoint(path: str | os.PathLike, state: dict[str, Any]) -> None:
    """Save `state` (tensors, numbers, strings, lists and dicts of them) so that a kill never corrupts `path`."""
    payload = {"version": CHECKPOINT_VERSION, **state}
    atomic_write(path, lambda tmp: torch.save(payload, tmp))


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise MCSplatError(f"{path}: no checkpoint there")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for damaged archives
        raise MCSplatError(f"{path}: damaged checkpoint ({type(error).__name__}); delete it to fall back to an "
                           f"older one or start again with --overwrite") from None
    if not isinstance(state, dict) or state.get("version") != CHECKPOINT_VERSION:
        raise MCSplatError(f"{path}: not an mcsplat checkpoint of version {CHECKPOINT_VERSION}")
    return state
