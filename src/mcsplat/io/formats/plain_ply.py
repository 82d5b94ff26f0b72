"""The plain 3DGS .ply (io/ply.py, the file training writes) as one format of this package's table: numpy arrays in
and out, like the others."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..ply import read_ply, write_ply


def write_plain_ply(path: Path, params: dict[str, np.ndarray]) -> None:
    write_ply(path, {key: torch.from_numpy(values) for key, values in params.items()})


def read_plain_ply(path: Path) -> dict[str, np.ndarray]:
    return {key: values.numpy() for key, values in read_ply(path).items()}
