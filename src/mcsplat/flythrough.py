"""Smooth camera paths for videos: a closed loop through given cameras, positions on a Catmull-Rom spline,
orientations by quaternion slerp."""

from __future__ import annotations

import torch

from .camera import Camera


def _matrix_to_quat(m: torch.Tensor) -> torch.Tensor:
    """3x3 rotation -> unit quaternion (w, x, y, z), float64."""
    m = m.double()
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = torch.stack([1 + trace, 1 + m[0, 0] - m[1, 1] - m[2, 2], 1 - m[0, 0] + m[1, 1] - m[2, 2],
                              1 - m[0, 0] - m[1, 1] + m[2, 2]])
    k = int(torch.argmax(candidates))
    s = torch.sqrt(candidates[k]) * 2  # = 4 * |component k|
    if k == 0:
        q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        q = [(m[2, 1] - m[1, 2]) / s, s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s]
    else:
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4]
    q = torch.stack(q)
    return q / q.norm()


def _quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = (q / q.norm()).tolist()
    return torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], dtype=torch.float64)


def _slerp(a: torch.Tensor, b: torch.Tensor, t: float) -> torch.Tensor:
    dot = float(torch.dot(a, b))
    if dot < 0:  # take the short way round
        b, dot = -b, -dot
    if dot > 0.9995:
        q = a + t * (b - a)
        return q / q.norm()
    theta = torch.arccos(torch.tensor(dot, dtype=torch.float64))
    return (torch.sin((1 - t) * theta) * a + torch.sin(t * theta) * b) / torch.sin(theta)


def loop_path(cameras: list[Camera], frames: int) -> list[Camera]:
    """`frames` cameras along a closed loop through `cameras` (in the order given), intrinsics of the first one."""
    if len(cameras) < 2:
        raise ValueError("a camera path needs at least two cameras")
    if frames < 2:
        raise ValueError("a camera path needs at least two frames")
    c2w = [torch.linalg.inv(c.world_to_camera.double()) for c in cameras]
    centers = [m[:3, 3] for m in c2w]
    quats = [_matrix_to_quat(m[:3, :3]) for m in c2w]
    n = len(cameras)
    path = []
    for f in range(frames):
        u = f * n / frames
        i, t = int(u) % n, u - int(u)
        p0, p1, p2, p3 = (centers[(i + k) % n] for k in (-1, 0, 1, 2))
        # Uniform Catmull-Rom: passes through every camera centre with a continuous tangent.
        center = 0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t ** 2
                        + (-p0 + 3 * p1 - 3 * p2 + p3) * t ** 3)
        rotation = _quat_to_matrix(_slerp(quats[i], quats[(i + 1) % n], t))
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3] = rotation.T
        w2c[:3, 3] = -rotation.T @ center
        first = cameras[0]
        path.append(Camera(K=first.K.clone(), world_to_camera=w2c.float(), width=first.width, height=first.height))
    return path
