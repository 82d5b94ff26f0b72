"""A small depth-buffer rasterizer for triangle meshes, in torch: the pictures of a mesh (the report, the README)
and its depth from a camera (the tests compare it with the splats' median depth).

Every triangle is tested at the pixel centres of its bounding box (pixel centres at +0.5, OpenCV axes, as the
Gaussian rasterizer); the depth is interpolated perspective-correctly (1/z is linear on the screen) and the nearest
triangle wins each pixel. Triangles are taken in chunks so that the (triangle, pixel) pairs stay within PAIRS_PER_CHUNK.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..camera import Camera
from ..data.images import uint8_pixels
from ..render.constants import NEAR_PLANE

PAIRS_PER_CHUNK = 1 << 22
# The pictures' light: from the upper left behind the camera (camera axes: x right, y down, z forward). Grey pictures
# show the shape, so mostly by the slant to this light; coloured ones mostly by their colours.
LIGHT = (-0.4, -0.6, -0.7)
AMBIENT_GREY, AMBIENT_COLOUR = 0.15, 0.6


@dataclass
class MeshRaster:
    depth: torch.Tensor  # [H, W] camera depth of the nearest surface, inf where none
    face: torch.Tensor   # [H, W] int64 index of that triangle, -1 where none


@torch.no_grad()
def rasterize(vertices: torch.Tensor, faces: torch.Tensor, camera: Camera) -> MeshRaster:
    """Depth and triangle index per pixel of `camera` for the mesh (vertices [V, 3] world, faces [F, 3])."""
    device = vertices.device
    width, height = camera.width, camera.height
    w2c = camera.world_to_camera.to(device, torch.float64)
    points = vertices.double() @ w2c[:3, :3].T + w2c[:3, 3]
    z = points[:, 2]
    screen = torch.stack([points[:, 0] / z * camera.fx + camera.cx, points[:, 1] / z * camera.fy + camera.cy], 1)
    faces = faces.to(device).long()
    faces = faces[(z[faces] > NEAR_PLANE).all(dim=1)]  # a triangle crossing the camera plane is left out
    corners = screen[faces]  # [F, 3, 2]
    # Pixel centres p + 0.5 inside the bounding box: p from ceil(min - 0.5) to floor(max - 0.5).
    first = (corners.amin(dim=1) - 0.5).ceil().clamp(min=0)
    last = (corners.amax(dim=1) - 0.5).floor().clamp(max=torch.tensor([width - 1.0, height - 1.0], device=device,
                                                                          dtype=torch.float64))
    span = (last - first + 1).clamp(min=0).long()  # [F, 2]
    pairs = span[:, 0] * span[:, 1]
    depth = torch.full((height * width,), float("inf"), dtype=torch.float64, device=device)
    best = torch.full((height * width,), -1, dtype=torch.int64, device=device)
    ends = torch.cumsum(pairs, 0)
    start = 0
    while start < faces.shape[0]:
        # The chunk's faces: as many as fit in PAIRS_PER_CHUNK pairs (at least one).
        done_before = ends[start - 1] if start else 0
        stop = max(start + 1, int(torch.searchsorted(ends, done_before + PAIRS_PER_CHUNK, right=True)))
        chunk = torch.arange(start, min(stop, faces.shape[0]), device=device)
        _draw(chunk, faces, corners, z, first, span, pairs, width, depth, best)
        start = int(chunk[-1]) + 1
    return MeshRaster(depth=depth.reshape(height, width).float(), face=best.reshape(height, width))


def _draw(chunk, faces, corners, z, first, span, pairs, width, depth, best) -> None:
    """The chunk's triangles into the depth buffer `depth` and `best` (flat, updated in place)."""
    counts = pairs[chunk]
    owner = torch.repeat_interleave(chunk, counts)
    if owner.numel() == 0:
        return
    offsets = torch.cumsum(counts, 0) - counts
    local = torch.arange(owner.numel(), device=owner.device) - torch.repeat_interleave(offsets, counts)
    columns = span[owner, 0]
    px = first[owner, 0] + (local % columns).double()
    py = first[owner, 1] + (local // columns).double()
    a, b, c = corners[owner, 0], corners[owner, 1], corners[owner, 2]
    centre_x, centre_y = px + 0.5, py + 0.5

    def edge(p, q):  # twice the signed area of (p, q, pixel centre)
        return (q[:, 0] - p[:, 0]) * (centre_y - p[:, 1]) - (q[:, 1] - p[:, 1]) * (centre_x - p[:, 0])

    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    weights = torch.stack([edge(b, c), edge(c, a), edge(a, b)], dim=1) / area[:, None]
    inside = (weights >= 0).all(dim=1) & (area.abs() > 1e-12)
    inverse_z = (weights / z[faces[owner]]).sum(dim=1)
    pixel_depth = 1.0 / inverse_z
    inside &= pixel_depth > NEAR_PLANE
    pixel = (py * width + px).long()[inside]
    pixel_depth, owner = pixel_depth[inside], owner[inside]
    depth.scatter_reduce_(0, pixel, pixel_depth, reduce="amin")
    nearest = pixel_depth == depth[pixel]
    best.scatter_reduce_(0, pixel[nearest], owner[nearest], reduce="amax")


def face_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """[F, 3] unit normals, by the winding (counter-clockwise seen from the side they point to)."""
    v = vertices.double()[faces.long()]
    normals = torch.linalg.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    return normals / normals.norm(dim=1, keepdim=True).clamp(min=1e-20)


@torch.no_grad()
def picture(vertices: torch.Tensor, faces: torch.Tensor, camera: Camera, colors: torch.Tensor | None = None,
            background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """uint8 [H, W, 3]: the mesh in its vertex colours [V, 3] (uint8, or floats in [0, 1]), or in grey without them,
    lit by LIGHT (both sides of a triangle alike)."""
    raster = rasterize(vertices, faces, camera)
    hit = raster.face >= 0
    face = raster.face[hit]
    device = vertices.device
    rotation = camera.world_to_camera[:3, :3].to(device, torch.float64)
    light = torch.nn.functional.normalize(rotation.T @ torch.tensor(LIGHT, dtype=torch.float64, device=device), dim=0)
    slant = (face_normals(vertices, faces)[face] @ -light).abs()
    if colors is None:
        albedo = torch.full((face.shape[0], 3), 0.85, dtype=torch.float64, device=device)
        ambient = AMBIENT_GREY
    else:
        scale = 255.0 if colors.dtype == torch.uint8 else 1.0
        albedo = colors.to(device).double()[faces.long()[face]].mean(dim=1) / scale
        ambient = AMBIENT_COLOUR
    shade = ambient + (1 - ambient) * slant
    image = torch.tensor(background, dtype=torch.float64, device=device).expand(camera.height, camera.width, 3).clone()
    image[hit] = albedo * shade[:, None]
    return uint8_pixels(image)
