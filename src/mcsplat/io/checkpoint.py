"""Checkpoints: everything needed to continue a run exactly, written atomically (temp file + rename), with a checksum
of the whole payload.

torch's archive does not check its tensors' bytes when loading, so a damaged file can load and hand back wrong
numbers (an evaluation of garbage, an export of NaN); the checksum, verified on every load, turns that into an error.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

import torch

from ..errors import MCSplatError
from .atomic import atomic_write

CHECKPOINT_VERSION = 2  # 2: with "checksum"; version 1 files (no checksum) still load
READABLE_VERSIONS = (1, 2)


class DamagedCheckpoint(MCSplatError):
    """The file cannot be read, or its contents are not what was written."""


def save_checkpoint(path: str | os.PathLike, state: dict[str, Any]) -> None:
    """Save `state` (tensors, numbers, strings, lists and dicts of them) so that a kill never corrupts `path`."""
    digest = hashlib.blake2b(digest_size=16)
    size = _feed(digest, state)
    payload = {"version": CHECKPOINT_VERSION, **state, "checksum": digest.hexdigest()}
    atomic_write(path, lambda tmp: torch.save(payload, tmp), size_hint=size)


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise MCSplatError(f"{path}: no checkpoint there")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for damaged archives
        raise DamagedCheckpoint(f"{path}: damaged checkpoint ({type(error).__name__})") from None
    if not isinstance(state, dict) or state.get("version") not in READABLE_VERSIONS:
        raise MCSplatError(f"{path}: not an mcsplat checkpoint of version {CHECKPOINT_VERSION}")
    version, stored = state.pop("version"), state.pop("checksum", None)
    if version >= 2 and stored != payload_checksum(state):
        raise DamagedCheckpoint(f"{path}: damaged checkpoint (its contents do not match the checksum written with "
                                f"them)")
    return {"version": version, **state}


def payload_checksum(value: Any) -> str:
    """A hash of every tensor's bytes, dtype and shape and of every other value, in the order of the structure."""
    digest = hashlib.blake2b(digest_size=16)
    _feed(digest, value)
    return digest.hexdigest()


def _feed(digest, value: Any) -> int:
    """Hash `value` into `digest`; returns the bytes of its tensors (about the size of the file torch writes)."""
    if isinstance(value, torch.Tensor):
        data = value.detach().cpu().contiguous().reshape(-1)
        digest.update(f"tensor {data.dtype} {tuple(value.shape)};".encode())
        digest.update(memoryview(data.view(torch.uint8).numpy()))
        return data.numel() * data.element_size()
    if isinstance(value, dict):
        digest.update(f"dict {len(value)};".encode())
        return sum(_feed(digest, key) + _feed(digest, item) for key, item in value.items())
    if isinstance(value, (list, tuple)):  # a tuple may come back as a list: the same value to the hash
        digest.update(f"list {len(value)};".encode())
        return sum(_feed(digest, item) for item in value)
    digest.update(f"{type(value).__name__} {value!r};".encode())
    return 0
