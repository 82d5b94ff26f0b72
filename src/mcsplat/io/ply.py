"""Gaussians as a .ply in the exact layout of the original 3DGS code, which every 3DGS viewer opens.

Vertex properties, all float32: x y z, nx ny nz (zeros), f_dc_0..2, f_rest_0..(3*(K-1)-1) channel-major (all rest
coefficients of red, then green, then blue), opacity (logit), scale_0..2 (log), rot_0..3 (w x y z, not normalised).
Parameters are exchanged as a dict with the keys of GaussianModel.params.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from ..errors import MCSplatError
from .atomic import atomic_write

PARAM_KEYS = ("means", "log_scales", "quats", "opacity_logits", "sh0", "shN")
_REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}  # number of f_rest_* -> SH degree


def write_ply(path: str | os.PathLike, params: dict[str, torch.Tensor], keep: torch.Tensor | None = None) -> int:
    """Write Gaussians (optionally only rows where `keep` is True) atomically; returns how many were written."""
    p = {k: params[k].detach().float().cpu() for k in PARAM_KEYS}
    if keep is not None:
        keep = keep.detach().cpu()
        p = {k: v[keep] for k, v in p.items()}
    n = p["means"].shape[0]
    rest = p["shN"].transpose(1, 2).reshape(n, -1)  # [N, 3 * (K - 1)], channel-major as 3DGS stores it
    columns = ([("x", p["means"][:, 0]), ("y", p["means"][:, 1]), ("z", p["means"][:, 2])]
               + [(f"n{a}", torch.zeros(n)) for a in "xyz"]
               + [(f"f_dc_{i}", p["sh0"][:, 0, i]) for i in range(3)]
               + [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
               + [("opacity", p["opacity_logits"])]
               + [(f"scale_{i}", p["log_scales"][:, i]) for i in range(3)]
               + [(f"rot_{i}", p["quats"][:, i]) for i in range(4)])
    vertices = np.empty(n, dtype=[(name, "f4") for name, _ in columns])
    for name, values in columns:
        vertices[name] = values.numpy()
    atomic_write(path, lambda tmp: PlyData([PlyElement.describe(vertices, "vertex")]).write(str(tmp)),
                 size_hint=vertices.nbytes)
    return n


def read_ply(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """Read a 3DGS .ply (ours or another tool's) into parameters; SH degree follows the number of f_rest fields."""
    path = Path(path)
    if not path.is_file():
        raise MCSplatError(f"{path}: no such .ply file")
    try:
        ply = PlyData.read(str(path))
        vertex = ply["vertex"]
    except Exception as error:  # plyfile raises several types for damaged files
        raise MCSplatError(f"{path}: not a readable .ply file ({error})") from None
    names = set(vertex.data.dtype.names)
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{i}" for i in range(3)] \
        + [f"rot_{i}" for i in range(4)]
    missing = [r for r in required if r not in names]
    if missing:
        raise MCSplatError(f"{path}: not a 3D Gaussian Splatting .ply (missing {', '.join(missing)})")
    rest_names = sorted((n for n in names if n.startswith("f_rest_")), key=lambda s: int(s.split("_")[-1]))
    if len(rest_names) not in _REST_COUNTS:
        raise MCSplatError(f"{path}: {len(rest_names)} f_rest fields do not match SH degree 0-3 (0, 9, 24 or 45)")

    def col(*fields):
        return torch.from_numpy(np.stack([np.asarray(vertex[f], dtype=np.float32) for f in fields], axis=-1))

    n = len(vertex.data)
    per_channel = len(rest_names) // 3
    shN = col(*rest_names).reshape(n, 3, per_channel).transpose(1, 2) if rest_names else torch.zeros(n, 0, 3)
    params = {
        "means": col("x", "y", "z"),
        "log_scales": col("scale_0", "scale_1", "scale_2"),
        "quats": col("rot_0", "rot_1", "rot_2", "rot_3"),
        "opacity_logits": col("opacity")[:, 0],
        "sh0": col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :],
        "shN": shN.contiguous(),
    }
    bad = [k for k, v in params.items() if not torch.isfinite(v).all()]
    if bad:
        raise MCSplatError(f"{path}: NaN or infinite values in {', '.join(bad)}")
    return params
