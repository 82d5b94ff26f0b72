"""Between viser's camera (a camera-to-world pose as quaternion + position in the OpenCV axes, vertical field of
view) and ours (world-to-camera matrix and pixel intrinsics)."""

from __future__ import annotations

import math

import numpy as np
import torch

from ..camera import Camera, intrinsics


def quat_to_matrix(wxyz: np.ndarray) -> np.ndarray:
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrix -> (w, x, y, z), by the largest-diagonal branch (stable for every rotation)."""
    m = np.asarray(r, dtype=np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q / np.linalg.norm(q)


def camera_from_pose(wxyz, position, fov_y: float, width: int, height: int) -> Camera:
    """Our camera for a camera-to-world pose (OpenCV axes) and a vertical field of view in radians."""
    rotation = quat_to_matrix(np.asarray(wxyz))
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = rotation.T
    world_to_camera[:3, 3] = -rotation.T @ np.asarray(position, dtype=np.float64)
    focal = 0.5 * height / math.tan(0.5 * fov_y)
    return Camera(K=intrinsics(focal, focal, 0.5 * width, 0.5 * height),
                  world_to_camera=torch.tensor(world_to_camera, dtype=torch.float32), width=width, height=height)


def pose_of(camera: Camera) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(wxyz, position, vertical fov, aspect) of one of our cameras, for frustums and the initial view."""
    w2c = camera.world_to_camera.detach().cpu().double().numpy()
    rotation = w2c[:3, :3].T
    position = -rotation @ w2c[:3, 3]
    fov_y = 2.0 * math.atan(0.5 * camera.height / camera.fy)
    return matrix_to_quat(rotation), position, fov_y, camera.width / camera.height


def image_size(client_width: int, client_height: int, longest_side: int) -> tuple[int, int]:
    """The browser's viewport scaled so that its longest side is at most `longest_side` (never upscaled)."""
    scale = min(1.0, longest_side / max(client_width, client_height, 1))
    return max(8, round(client_width * scale)), max(8, round(client_height * scale))
