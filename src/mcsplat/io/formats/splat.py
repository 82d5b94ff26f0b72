"""The `.splat` format of antimatter15's WebGL viewer, read by most web splat viewers (SuperSplat, gsplat.js, ...).

No header: the file is N records of 32 bytes, little-endian:

    offset  type      field
     0      3 x f32   position x, y, z
    12      3 x f32   scale x, y, z (exp of the log-scales: standard deviations)
    24      4 x u8    colour r, g, b = clip(0.5 + 0.28209479 * f_dc) * 255 (rounded); a = sigmoid(opacity) * 255
    28      4 x u8    rotation w, x, y, z = clip(q / |q| * 128 + 128) (rounded)

Records are sorted by decreasing opacity * volume, as antimatter15's converter does (viewers that stream the file
show the large, opaque Gaussians first). No view-dependent colour: the SH degree is 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import MCSplatError
from ..atomic import atomic_write_bytes
from .common import SH_C0, check_params, logit, normalized_quats, read_bytes, sigmoid

RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])
assert RECORD.itemsize == 32


def _to_u8(values: np.ndarray) -> np.ndarray:
    return np.clip(np.round(values), 0, 255).astype(np.uint8)


def write_splat(path: Path, params: dict[str, np.ndarray]) -> None:
    n = check_params(params)
    opacity = sigmoid(params["opacity_logits"])
    order = np.argsort(-(np.exp(params["log_scales"].astype(np.float64).sum(axis=1)) * opacity), kind="stable")
    records = np.empty(n, dtype=RECORD)
    records["position"] = params["means"][order]
    records["scale"] = np.exp(params["log_scales"][order].astype(np.float64))
    colour = 0.5 + SH_C0 * params["sh0"][order, 0, :].astype(np.float64)
    records["rgba"][:, :3] = _to_u8(np.clip(colour, 0.0, 1.0) * 255.0)
    records["rgba"][:, 3] = _to_u8(opacity[order] * 255.0)
    records["rotation"] = _to_u8(normalized_quats(params["quats"][order]) * 128.0 + 128.0)
    atomic_write_bytes(path, records.tobytes())


def read_splat(path: Path) -> dict[str, np.ndarray]:
    data = read_bytes(path)
    if len(data) % RECORD.itemsize:
        raise MCSplatError(f"{path}: {len(data)} bytes is not a whole number of 32-byte .splat records")
    records = np.frombuffer(data, dtype=RECORD)
    n = len(records)
    quats = (records["rotation"].astype(np.float64) - 128.0) / 128.0
    return {
        "means": records["position"].astype(np.float32),
        "log_scales": np.log(np.maximum(records["scale"].astype(np.float64), 1e-30)).astype(np.float32),
        "quats": normalized_quats(quats).astype(np.float32),
        "opacity_logits": logit(records["rgba"][:, 3] / 255.0).astype(np.float32),
        "sh0": ((records["rgba"][:, None, :3] / 255.0 - 0.5) / SH_C0).astype(np.float32),
        "shN": np.zeros((n, 0, 3), dtype=np.float32),
    }
