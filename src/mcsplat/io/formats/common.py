"""Small pieces the format modules share."""

from __future__ import annotations

import numpy as np

from ...errors import MCSplatError

SH_C0 = 0.28209479177387814  # the degree-0 SH basis value: colour = 0.5 + SH_C0 * f_dc (geometry/sh.py)
# The 3DGS frame (y down, z forward) turned 180 degrees about x into a y-up one (.spz, glTF): y -> -y, z -> -z, and
# the sign change of each SH rest coefficient (3DGS order) under it: odd total power of y and z.
AXES_FLIP = np.array([1.0, -1.0, -1.0])
SH_FLIP = np.array([-1, -1, 1,  -1, 1, 1, -1, 1,  -1, 1, -1, -1, 1, -1, 1], dtype=np.float64)


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x.astype(np.float64)))


def logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p.astype(np.float64), 1e-6, 1.0 - 1e-6)
    return np.log(p / (1.0 - p))


def normalized_quats(quats: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(quats.astype(np.float64), axis=1, keepdims=True)
    return np.where(norm > 0, quats / np.maximum(norm, 1e-30), np.array([1.0, 0.0, 0.0, 0.0]))


def check_params(params: dict[str, np.ndarray]) -> int:
    n = params["means"].shape[0]
    if n == 0:
        raise MCSplatError("nothing to export: no Gaussian is left (lower --min-opacity)")
    return n


def sh_degree_of(shN: np.ndarray) -> int:
    return {0: 0, 3: 1, 8: 2, 15: 3}[shN.shape[1]]


def bases_of(degree: int) -> int:
    return (degree + 1) ** 2 - 1


def read_bytes(path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise MCSplatError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise MCSplatError(f"{path}: a folder, not a file") from None
    except OSError as error:  # unreadable (permissions, a device): the file's name and why, in one line
        raise MCSplatError(f"{path}: cannot be read ({error.strerror or error})") from None
