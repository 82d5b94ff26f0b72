"""Niantic's `.spz`: the attributes quantised into six blocks, in the container of version 3 (one gzip stream, read by
every .spz reader) or 4 (zstd streams, about a third smaller, read by newer ones): spz_container.py. The blocks:

    positions  N x 3 x 24-bit signed fixed point (little-endian, 2^-12 units), x y z of each point in turn
    alphas     N x u8   round(sigmoid(opacity) * 255)
    colours    N x 3 u8 round(f_dc * 0.15 * 255 + 127.5)   (the SH DC coefficient, not the colour)
    scales     N x 3 u8 round((log-scale + 10) * 16)
    rotations  N x 4 bytes: u32 smallest-three: bits 30-31 index of the largest |component| of q / |q| in the
               order x, y, z, w; the other three in that order, first in the highest bits, 10 bits each:
               a sign bit (set when its sign differs from the largest's) then 9 bits round(|v| / sqrt(1/2) * 511)
    SH         N x (K-1) x 3 u8, per point coefficient-major then r g b: round(v * 128) + 128, rounded to
               multiples of 8 (5 bits) for degree 1 and of 16 (4 bits) for degrees 2-3, as Niantic's writer does

The header says N, the SH degree, 12 fractional bits and the flags (1 = antialiased training, else 0).

Axes: SPZ stores RUB coordinates (x right, y up, z back) and the 3DGS .ply RDF (y down, z forward), so the writer
turns the scene 180 degrees about x (y -> -y, z -> -z, quaternion (w, x, -y, -z), and the SH coefficients whose
basis function is odd in y and z change sign), as Niantic's converter does; the reader turns it back. (PlayCanvas's
splat-transform reads .spz without that turn, as if it held the .ply's axes: there the scene is upside down.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import MCSplatError
from ..atomic import atomic_write_bytes
from .common import (AXES_FLIP, SH_FLIP, bases_of, check_params, logit, normalized_quats,
                     read_bytes, sh_degree_of, sigmoid)
from .spz_container import VERSIONS, SpzHeader, pack, unpack

# Version 3 by default: PlayCanvas's splat-transform (3.7.0) and three.js's SPZLoader (0.186 on) read 3 and 4 alike,
# but Spark (2.2.0) and tools built on Niantic's library before its version 4 read .spz only as a gzip stream.
DEFAULT_VERSION = 3
FRACTIONAL_BITS = 12
COLOUR_SCALE = 0.15
FLAG_ANTIALIASED = 1  # the scene was trained with Mip-Splatting's 2D filter: viewers should draw it with the filter


def _u8(values: np.ndarray) -> np.ndarray:
    return np.clip(np.round(values), 0, 255).astype(np.uint8)


def _quantize_sh(rest: np.ndarray) -> np.ndarray:
    q = np.clip(np.round(rest * 128.0) + 128.0, 0, 255)
    bucket = np.where(np.arange(rest.shape[1]) < 3, 8, 16)[None, :, None]
    return np.clip(np.floor((q + bucket / 2) / bucket) * bucket, 0, 255).astype(np.uint8)


def _pack_rotations(quats_wxyz: np.ndarray) -> np.ndarray:
    q = normalized_quats(quats_wxyz)[:, [1, 2, 3, 0]]  # x y z w
    largest = np.argmax(np.abs(q), axis=1)
    negative = q[np.arange(len(q)), largest] < 0
    packed = largest.astype(np.uint32)
    mask = (1 << 9) - 1
    for i in range(4):
        others = largest != i
        sign = ((q[:, i] < 0) ^ negative).astype(np.uint32)
        magnitude = np.clip(np.floor(mask * np.abs(q[:, i]) / np.sqrt(0.5) + 0.5), 0, mask).astype(np.uint32)
        packed = np.where(others, (packed << 10) | (sign << 9) | magnitude, packed)
    return packed.astype("<u4")


def _unpack_rotations(packed: np.ndarray) -> np.ndarray:
    largest = (packed >> 30).astype(np.int64)
    mask = (1 << 9) - 1
    q = np.zeros((len(packed), 4))
    rest = packed.astype(np.uint64)
    for i in (3, 2, 1, 0):  # the last component written is in the lowest bits
        others = largest != i
        value = np.sqrt(0.5) * (rest & mask) / mask * np.where((rest >> 9) & 1, -1.0, 1.0)
        q[others, i] = value[others]
        rest = np.where(others, rest >> 10, rest)
    rows = np.arange(len(packed))
    q[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - (q ** 2).sum(axis=1)))
    return q[:, [3, 0, 1, 2]]  # w x y z


def write_spz(path: Path, params: dict[str, np.ndarray], antialiased: bool = False,
              spz_version: int = DEFAULT_VERSION) -> None:
    if spz_version not in VERSIONS:
        raise MCSplatError(f"--spz-version {spz_version}: .spz versions {' and '.join(map(str, VERSIONS))} are "
                           "written")
    n = check_params(params)
    degree = sh_degree_of(params["shN"])
    means = params["means"].astype(np.float64) * AXES_FLIP
    fixed = np.round(means * (1 << FRACTIONAL_BITS)).astype(np.int64)
    if np.abs(fixed).max() >= 1 << 23:
        raise MCSplatError("a position is beyond +-2048 units, which .spz's 24-bit positions cannot hold; "
                           "export as ply or splat instead")
    positions = (fixed & 0xFFFFFF).astype("<u4").view(np.uint8).reshape(n, 3, 4)[:, :, :3]
    quats = params["quats"].astype(np.float64) * np.array([1.0, 1.0, -1.0, -1.0])
    rest = params["shN"].astype(np.float64) * SH_FLIP[:bases_of(degree), None]
    blocks = [
        positions.tobytes(),
        _u8(sigmoid(params["opacity_logits"]) * 255.0).tobytes(),
        _u8(params["sh0"][:, 0, :].astype(np.float64) * (COLOUR_SCALE * 255.0) + 127.5).tobytes(),
        _u8((params["log_scales"].astype(np.float64) + 10.0) * 16.0).tobytes(),
        _pack_rotations(quats).tobytes(),
        _quantize_sh(rest).tobytes(),
    ]
    header = SpzHeader(spz_version, n, degree, FRACTIONAL_BITS, FLAG_ANTIALIASED if antialiased else 0)
    atomic_write_bytes(path, pack(header, blocks))


def read_spz(path: Path) -> dict[str, np.ndarray]:
    """Versions 3 and 4 (spz_container.py); a damaged file is one MCSplatError naming it."""
    header, blocks = unpack(path, read_bytes(path))
    n, k = header.count, bases_of(header.sh_degree)
    positions, alphas, colours, scales, rotations, sh = (np.frombuffer(block, dtype=np.uint8) for block in blocks)
    raw = np.zeros((n * 3, 4), dtype=np.uint8)
    raw[:, :3] = positions.reshape(n * 3, 3)
    fixed = raw.view("<u4")[:, 0].astype(np.int64)
    fixed = np.where(fixed >= 1 << 23, fixed - (1 << 24), fixed)
    means = fixed.reshape(n, 3) / float(1 << header.fractional_bits) * AXES_FLIP
    quats = _unpack_rotations(rotations.view("<u4")) * np.array([1.0, 1.0, -1.0, -1.0])
    rest = (sh.reshape(n, k, 3).astype(np.float64) - 128.0) / 128.0 * SH_FLIP[:k, None]
    return {
        "means": means.astype(np.float32),
        "log_scales": (scales.reshape(n, 3) / 16.0 - 10.0).astype(np.float32),
        "quats": quats.astype(np.float32),
        "opacity_logits": logit(alphas / 255.0).astype(np.float32),
        "sh0": ((colours.reshape(n, 1, 3) - 127.5) / (COLOUR_SCALE * 255.0)).astype(np.float32),
        "shN": rest.astype(np.float32),
    }
