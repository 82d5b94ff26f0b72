"""Pose conventions: every loader ends with an OpenCV world-to-camera matrix (x right, y down, z forward)."""

from __future__ import annotations

import numpy as np
import torch

from ..camera import Camera
from ..errors import DataError

# Column signs that take OpenGL/Blender camera axes (x right, y up, looking along -z) to OpenCV ones.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def rigid_rotation(rotation: np.ndarray, where: str) -> np.ndarray:
    """`rotation` as an exact rotation matrix; DataError if it has NaN/inf or is far from one.

    `where` names the file and entry for the message. A tiny drift from float rounding in text files is removed
    (nearest rotation by SVD); scale or shear is an error, because world_to_camera must be rigid.
    """
    rotation = np.asarray(rotation, dtype=np.float64)
    if not np.isfinite(rotation).all():
        raise DataError(f"{where} has NaN or infinite values in its rotation; fix or remove that pose")
    u, s, vt = np.linalg.svd(rotation)
    if np.abs(s - 1.0).max() > 1e-2 or np.linalg.det(rotation) <= 0:
        raise DataError(f"{where} is not a rotation (singular values {np.round(s, 4).tolist()}, det "
                        f"{np.linalg.det(rotation):.3g}); poses must be rigid camera-to-world transforms")
    return u @ vt


def check_translation(translation: np.ndarray, where: str) -> np.ndarray:
    translation = np.asarray(translation, dtype=np.float64).reshape(3)
    if not np.isfinite(translation).all():
        raise DataError(f"{where} has NaN or infinite values in its translation; fix or remove that pose")
    return translation


def world_to_camera_from_c2w(rotation_c2w: np.ndarray, position: np.ndarray) -> np.ndarray:
    """4x4 world-to-camera from a camera-to-world rotation (OpenCV axes as columns) and the camera position."""
    w2c = np.eye(4)
    w2c[:3, :3] = rotation_c2w.T
    w2c[:3, 3] = -rotation_c2w.T @ position
    return w2c


def opengl_c2w_to_opencv_w2c(c2w: np.ndarray, where: str) -> np.ndarray:
    """Blender/NeRF camera-to-world (3x4 or 4x4, OpenGL camera axes) -> OpenCV world-to-camera 4x4."""
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape not in ((3, 4), (4, 4)):
        raise DataError(f"{where} must be a 4x4 (or 3x4) matrix, got shape {list(c2w.shape)}")
    if not np.isfinite(c2w).all():
        raise DataError(f"{where} has NaN or infinite values; fix or remove that frame")
    rotation = rigid_rotation(c2w[:3, :3], where) @ _GL_TO_CV
    return world_to_camera_from_c2w(rotation, check_translation(c2w[:3, 3], where))


def llff_to_opencv_w2c(pose: np.ndarray, where: str) -> np.ndarray:
    """LLFF 3x4 camera-to-world with columns [down, right, backwards | position] -> OpenCV world-to-camera 4x4."""
    if not np.isfinite(pose).all():
        raise DataError(f"{where} has NaN or infinite values; fix or remove that pose")
    down, right, backwards, position = (pose[:, i] for i in range(4))
    rotation = rigid_rotation(np.stack([right, down, -backwards], axis=1), where)
    return world_to_camera_from_c2w(rotation, check_translation(position, where))


def make_camera(K: np.ndarray, world_to_camera: np.ndarray, width: int, height: int) -> Camera:
    return Camera(K=torch.as_tensor(np.asarray(K, dtype=np.float64), dtype=torch.float32).clone(),
                  world_to_camera=torch.as_tensor(np.asarray(world_to_camera, dtype=np.float64),
                                                  dtype=torch.float32).clone(),
                  width=int(width), height=int(height))


def scale_intrinsics(K: np.ndarray, from_size: tuple[int, int], to_size: tuple[int, int]) -> np.ndarray:
    """K of a from_size (w, h) image for the same image resized to to_size (pixel-corner convention: cx scales)."""
    K = np.array(K, dtype=np.float64)
    K[0, :] *= to_size[0] / from_size[0]
    K[1, :] *= to_size[1] / from_size[1]
    return K


def intrinsic_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)
