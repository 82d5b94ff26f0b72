"""The zero level set of a fused volume as triangles (marching cubes, scikit-image's Lewiner variant), with colours.

Only cubes whose eight corners were all observed are meshed: between a seen and a never-seen grid point there is no
evidence of a surface, only of the edge of what the views covered. The volume goes to the CPU a block of slabs at a
time; the blocks share their boundary plane, whose vertices the caller merges (trimesh does on construction).
"""

from __future__ import annotations

import numpy as np
import torch
from tqdm import tqdm

from .fusion import TSDFVolume

BLOCK_SLABS = 32  # slabs of the first axis per marching cubes call


def observed_cubes(weight: torch.Tensor) -> torch.Tensor:
    """[nx, ny, nz] bool: the cube that spans i-1..i, j-1..j, k-1..k (scikit-image's `mask` names a cube by its far
    corner) has all eight corners observed."""
    seen = weight > 0
    nx, ny, nz = seen.shape
    cubes = torch.zeros_like(seen)
    inner = cubes[1:, 1:, 1:]
    inner.copy_(seen[1:, 1:, 1:])
    for corner in range(1, 8):
        dx, dy, dz = (corner >> 2) & 1, (corner >> 1) & 1, corner & 1
        inner &= seen[1 - dx:nx - dx, 1 - dy:ny - dy, 1 - dz:nz - dz]
    return cubes


def zero_surface(volume: TSDFVolume, progress: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices [V, 3] float32 world, faces [F, 3] int64, colours [V, 3] uint8) of the volume's zero level set;
    faces wind counter-clockwise seen from outside (the positive side)."""
    cubes = observed_cubes(volume.weight)
    vertices, faces, count = [], [], 0
    starts = range(0, volume.grid.shape[0] - 1, BLOCK_SLABS)
    for x0 in tqdm(starts, desc="marching cubes", unit="block", disable=not progress, leave=False):
        found = _block_surface(volume, cubes, x0)
        if found is None:
            continue
        block_vertices, block_faces = found
        block_vertices[:, 0] += x0
        vertices.append(block_vertices)
        faces.append(block_faces + count)
        count += block_vertices.shape[0]
    if not faces:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8)
    points = torch.from_numpy(np.concatenate(vertices)).to(volume.device)
    colors = trilinear(volume.color, points).clamp(0, 1).mul(255).round().to(torch.uint8)
    world = volume.grid.to_world(points.double()).float()
    return world.cpu().numpy(), np.concatenate(faces).astype(np.int64), colors.cpu().numpy()


def _block_surface(volume: TSDFVolume, cubes: torch.Tensor, x0: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices in the block's grid coordinates, faces) of the block of slabs from x0, or None without a surface."""
    from skimage.measure import marching_cubes

    x1 = min(volume.grid.shape[0], x0 + BLOCK_SLABS + 1)  # one plane shared with the next block
    mask = cubes[x0:x1].cpu().numpy()
    if not mask[1:].any():
        return None
    values = volume.tsdf[x0:x1].cpu().numpy()
    seen = values[volume.weight[x0:x1].cpu().numpy() > 0]
    if seen.min() > 0 or seen.max() < 0:
        return None
    try:
        block_vertices, block_faces, _, _ = marching_cubes(values, 0.0, mask=mask)
    except (ValueError, RuntimeError):  # "no surface found" within the observed cubes
        return None
    return block_vertices.astype(np.float32), block_faces


def trilinear(volume: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """[nx, ny, nz, C] sampled at [P, 3] fractional grid coordinates -> [P, C] float32."""
    size = torch.tensor(volume.shape[:3], device=points.device)
    low = points.floor().long().clamp(min=torch.zeros_like(size), max=size - 2)
    fraction = (points - low.float()).clamp(0, 1)
    result = torch.zeros(points.shape[0], volume.shape[3], device=points.device)
    for corner in range(8):
        offset = torch.tensor([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1], device=points.device)
        weight = torch.where(offset.bool(), fraction, 1 - fraction).prod(dim=1)
        index = low + offset
        result += weight[:, None] * volume[index[:, 0], index[:, 1], index[:, 2]].float()
    return result
