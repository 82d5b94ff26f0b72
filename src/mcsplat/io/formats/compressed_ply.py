"""The compressed `.ply` of PlayCanvas / SuperSplat (about 4x smaller than the 3DGS .ply, read by SuperSplat, the
PlayCanvas engine and @playcanvas/splat-transform).

A binary little-endian PLY with three elements:

    element chunk  ceil(N / 256) rows, 18 x float32: min_x min_y min_z max_x max_y max_z,
                   min_scale_x .. max_scale_z (bounds of the log-scales, clamped to [-20, 20]),
                   min_r min_g min_b max_r max_g max_b (bounds of colour = 0.5 + 0.28209479 * f_dc)
    element vertex N rows, 4 x uint32 (Gaussian i belongs to chunk i // 256):
        packed_position  x 11 bits << 21 | y 10 bits << 11 | z 11 bits, each (v - min) / (max - min) of its chunk
        packed_rotation  2-bit index (bits 30-31) of the largest |component| of q / |q| in the order w, x, y, z
                         (the 3DGS rot_0..rot_3), q negated so that it is positive; the other three components in
                         that order, first in the highest bits, 10 bits each as v * sqrt(2)/2 + 0.5
        packed_scale     log-scales x 11 | y 10 | z 11 bits within the chunk's bounds
        packed_color     r 8 << 24 | g 8 << 16 | b 8 << 8 | alpha 8, colour within the chunk's bounds,
                         alpha = sigmoid(opacity)
    element sh     N rows of uchar f_rest_0 .. f_rest_{3(K-1)-1} in the 3DGS .ply order (channel-major), each
                   trunc((v / 8 + 0.5) * 256) clamped to 0..255; absent at SH degree 0

A b-bit field stores round(t * (2^b - 1)) for t in [0, 1]. Gaussians are written in Morton order of their
positions (10 bits per axis over the scene's bounds) so that each chunk of 256 is compact in space and its bounds
tight. The vertex count is N: the last chunk's bounds cover only its real Gaussians.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ...errors import MCSplatError
from ..atomic import atomic_write_bytes
from .common import SH_C0, check_params, logit, normalized_quats, read_bytes, sigmoid

CHUNK = 256
CHUNK_FIELDS = [f"{m}_{a}" for m in ("min", "max") for a in "xyz"] \
    + [f"{m}_scale_{a}" for m in ("min", "max") for a in "xyz"] + [f"{m}_{c}" for m in ("min", "max") for c in "rgb"]
VERTEX_FIELDS = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
LOG_SCALE_LIMIT = 20.0
_ROOT_HALF = np.sqrt(2.0) * 0.5


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """10-bit integers -> bits spread 3 apart, for Morton codes."""
    v = v.astype(np.uint64) & 0x3FF
    v = (v | (v << 16)) & 0x030000FF
    v = (v | (v << 8)) & 0x0300F00F
    v = (v | (v << 4)) & 0x030C30C3
    return (v | (v << 2)) & 0x09249249


def morton_order(means: np.ndarray) -> np.ndarray:
    lo, hi = means.min(axis=0), means.max(axis=0)
    cells = np.floor((means - lo) / np.where(hi > lo, hi - lo, 1.0) * 1023.0).astype(np.int64)
    code = _spread_bits(cells[:, 0]) | (_spread_bits(cells[:, 1]) << 1) | (_spread_bits(cells[:, 2]) << 2)
    return np.argsort(code, kind="stable")


def _unorm(t: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return np.clip(np.floor(t * top + 0.5), 0, top).astype(np.uint32)


def _from_unorm(v: np.ndarray, bits: int) -> np.ndarray:
    return v.astype(np.float64) / ((1 << bits) - 1)


def _chunk_bounds(values: np.ndarray, chunks: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    lo = np.full((count, values.shape[1]), np.inf)
    hi = np.full((count, values.shape[1]), -np.inf)
    np.minimum.at(lo, chunks, values)
    np.maximum.at(hi, chunks, values)
    return lo, hi


def _normalize(values, lo, hi):
    span = hi - lo
    return np.where(span > 0, (values - lo) / np.where(span > 0, span, 1.0), 0.0)


def _pack_11_10_11(t: np.ndarray) -> np.ndarray:
    return (_unorm(t[:, 0], 11) << 21) | (_unorm(t[:, 1], 10) << 11) | _unorm(t[:, 2], 11)


def _unpack_11_10_11(v: np.ndarray) -> np.ndarray:
    return np.stack([_from_unorm(v >> 21, 11), _from_unorm((v >> 11) & 0x3FF, 10), _from_unorm(v & 0x7FF, 11)], 1)


def _pack_rotation(quats: np.ndarray) -> np.ndarray:
    q = normalized_quats(quats)
    largest = np.argmax(np.abs(q), axis=1)
    q = q * np.where(q[np.arange(len(q)), largest] < 0, -1.0, 1.0)[:, None]
    packed = largest.astype(np.uint32)
    for i in range(4):
        others = largest != i
        packed = np.where(others, (packed << 10) | _unorm(q[:, i] * _ROOT_HALF + 0.5, 10), packed)
    return packed


def _unpack_rotation(v: np.ndarray) -> np.ndarray:
    largest = (v >> 30).astype(np.int64)
    three = np.stack([(_from_unorm((v >> shift) & 0x3FF, 10) - 0.5) / _ROOT_HALF for shift in (20, 10, 0)], 1)
    q = np.zeros((len(v), 4))
    rows = np.arange(len(v))
    slot = np.zeros(len(v), dtype=np.int64)
    for i in range(4):
        others = largest != i
        q[rows[others], i] = three[rows[others], slot[others]]
        slot += others
    q[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - (three ** 2).sum(axis=1)))
    return q


def write_compressed_ply(path: Path, params: dict[str, np.ndarray]) -> None:
    n = check_params(params)
    order = morton_order(params["means"].astype(np.float64))
    means = params["means"][order].astype(np.float64)
    log_scales = np.clip(params["log_scales"][order].astype(np.float64), -LOG_SCALE_LIMIT, LOG_SCALE_LIMIT)
    colour = 0.5 + SH_C0 * params["sh0"][order, 0, :].astype(np.float64)
    alpha = sigmoid(params["opacity_logits"][order])
    chunks = np.arange(n) // CHUNK
    count = int(chunks[-1]) + 1
    bounds = [_chunk_bounds(v, chunks, count) for v in (means, log_scales, colour)]
    chunk_rows = np.concatenate([np.concatenate(b, axis=1) for b in bounds], axis=1).astype("<f4")

    def normalized(values, which):
        lo, hi = bounds[which]
        return _normalize(values, lo[chunks], hi[chunks])

    vertices = np.empty((n, 4), dtype="<u4")
    vertices[:, 0] = _pack_11_10_11(normalized(means, 0))
    vertices[:, 1] = _pack_rotation(params["quats"][order])
    vertices[:, 2] = _pack_11_10_11(normalized(log_scales, 1))
    rgb = normalized(colour, 2)
    vertices[:, 3] = ((_unorm(rgb[:, 0], 8) << 24) | (_unorm(rgb[:, 1], 8) << 16) | (_unorm(rgb[:, 2], 8) << 8)
                      | _unorm(alpha, 8))
    rest = params["shN"][order].astype(np.float64)
    rest = rest.transpose(0, 2, 1).reshape(n, -1)  # channel-major, as the 3DGS .ply's f_rest_*
    sh_bytes = np.clip(np.trunc((rest / 8.0 + 0.5) * 256.0), 0, 255).astype(np.uint8)

    header = ["ply", "format binary_little_endian 1.0", "comment written by mcsplat", f"element chunk {count}"]
    header += [f"property float {name}" for name in CHUNK_FIELDS]
    header += [f"element vertex {n}"] + [f"property uint {name}" for name in VERTEX_FIELDS]
    if rest.shape[1]:
        header += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(rest.shape[1])]
    header += ["end_header"]
    blob = ("\n".join(header) + "\n").encode("ascii") + chunk_rows.tobytes() + vertices.tobytes() + sh_bytes.tobytes()
    atomic_write_bytes(path, blob)


def read_compressed_ply(path: Path) -> dict[str, np.ndarray]:
    data = read_bytes(path)
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise MCSplatError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii", "replace")
    elements = dict((name, int(count)) for name, count in re.findall(r"element (\w+) (\d+)", header))
    if "chunk" not in elements or "vertex" not in elements or "packed_position" not in header:
        raise MCSplatError(f"{path}: not a compressed PLY (no chunk element or packed vertex properties)")
    count, n = elements["chunk"], elements["vertex"]
    rest_count = len(re.findall(r"property uchar f_rest_", header))
    offset = end + len(b"end_header\n")
    chunk_rows = np.frombuffer(data, dtype="<f4", count=count * 18, offset=offset).reshape(count, 18).astype(np.float64)
    offset += count * 18 * 4
    vertices = np.frombuffer(data, dtype="<u4", count=n * 4, offset=offset).reshape(n, 4)
    offset += n * 16
    sh_bytes = np.frombuffer(data, dtype=np.uint8, count=n * rest_count, offset=offset).reshape(n, rest_count)
    chunks = np.arange(n) // CHUNK

    def denormalized(t, first):
        lo, hi = chunk_rows[chunks, first:first + 3], chunk_rows[chunks, first + 3:first + 6]
        return lo + t * (hi - lo)

    colour_t = np.stack([_from_unorm((vertices[:, 3] >> s) & 0xFF, 8) for s in (24, 16, 8)], 1)
    colour = denormalized(colour_t, 12)
    alpha = _from_unorm(vertices[:, 3] & 0xFF, 8)
    rest = (sh_bytes.astype(np.float64) + 0.5) / 256.0 * 8.0 - 4.0  # the middle of each quantisation step
    shN = rest.reshape(n, 3, rest_count // 3).transpose(0, 2, 1) if rest_count else np.zeros((n, 0, 3))
    return {
        "means": denormalized(_unpack_11_10_11(vertices[:, 0]), 0).astype(np.float32),
        "log_scales": denormalized(_unpack_11_10_11(vertices[:, 2]), 6).astype(np.float32),
        "quats": _unpack_rotation(vertices[:, 1]).astype(np.float32),
        "opacity_logits": logit(alpha).astype(np.float32),
        "sh0": ((colour - 0.5) / SH_C0)[:, None, :].astype(np.float32),
        "shN": np.ascontiguousarray(shN, dtype=np.float32),
    }
