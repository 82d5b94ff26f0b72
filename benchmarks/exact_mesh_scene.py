"""A Blender/NeRF-synthetic scene whose surface is known exactly, to score exported meshes against (Chamfer distance:
chamfer.py, mesh_chamfer.py). The captures' SfM points are sparse and noisy; here the truth is the mesh itself.

    .venv/bin/python benchmarks/exact_mesh_scene.py FOLDER                      # 80 train + 20 test views, 200x200
    .venv/bin/python benchmarks/exact_mesh_scene.py FOLDER --train 8 --test 2 --size 64 --voxel 0.025

The shape, about one unit across and centred near the origin (z up): a rounded box (flat faces, rounded edges) with a
spherical dent in its top (a concave bowl), a ball and a standing ring (a torus: saddle-shaped inside, a hole to see
through) sunk a little into its top, so that the union has concave creases too. It is one signed distance function,
meshed by marching cubes on a fine grid (`--voxel`): a closed surface without the hidden inner faces that glued
primitives would leave, small even triangles, and flat faces that stay exactly flat (marching cubes interpolates a
linear function exactly). That mesh is the truth: the pictures are rendered from it, not from the formulas.

Its colour is a solid texture, unlit and the same from every side: cubes of CELL on a side, each a colour of PALETTE
picked by a hash of the cube and darkened on alternate cubes, evaluated at each pixel's surface point (so the edges
stay sharp whatever the triangles) -- detail everywhere for the photometric loss. The views orbit the origin at
DISTANCE, spread by a Fibonacci spiral over heights from LOW to HIGH of the sphere (below the equator too: the box's
underside is part of the truth that completeness counts), and are rendered with mcsplat.mesh.raster at SUPERSAMPLE x
SUPERSAMPLE samples a pixel, averaged: the alpha is the share of samples on the object (antialiased edges).

The folder: transforms_train.json and transforms_test.json (camera_angle_x; frames with file_path without the
ending and the 4x4 camera-to-world in Blender's camera axes: x right, y up, looking along -z), train/ and test/ RGBA
PNGs on a transparent background, and mesh.ply (the true mesh, vertex colours from the texture).
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import trimesh
import tyro
from PIL import Image

# The shape, in scene units, z up.
BOX_CENTRE, BOX_HALF, BOX_ROUNDING = np.array([0.0, 0.0, -0.15]), np.array([0.5, 0.35, 0.18]), 0.07
BALL_CENTRE, BALL_RADIUS = np.array([-0.24, -0.02, 0.2]), 0.19         # 0.02 sunk into the box's top
RING_CENTRE, RING_RADII = np.array([0.25, 0.0, 0.22]), (0.16, 0.05)     # in the x-z plane, 0.02 sunk into the top
DENT_CENTRE, DENT_RADIUS = np.array([0.02, 0.15, 0.08]), 0.12           # cut out of the top: a bowl 0.09 deep
VOXEL = 1 / 160           # marching cubes' grid step for the true mesh (188,724 faces)
# The texture.
CELL = 0.08
PALETTE = np.array([[0.90, 0.30, 0.25], [0.95, 0.75, 0.20], [0.35, 0.70, 0.30], [0.25, 0.55, 0.90],
                    [0.65, 0.35, 0.85], [0.95, 0.55, 0.70], [0.30, 0.80, 0.80], [0.85, 0.85, 0.80]])
DARKER = 0.45             # the alternate cubes' brightness
# The cameras.
DISTANCE = 2.3            # from the origin (the shape fills up to 0.8 of the image's half-width)
CAMERA_ANGLE_X = 0.6911   # horizontal field of view, radians (NeRF-synthetic's)
LOW, HIGH = -0.7, 0.92    # heights (z on the unit sphere) the views spread over
SUPERSAMPLE = 3
TRAIN_VIEWS, TEST_VIEWS, SIZE = 80, 20, 200


class SceneError(ValueError):
    """Bad input to the scene writer, said in one line."""


@dataclass(frozen=True)
class Options:
    """A scene whose surface is known exactly."""

    folder: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="FOLDER")]
    """A new (or empty) folder for the scene."""
    train: int = TRAIN_VIEWS
    """Training views."""
    test: int = TEST_VIEWS
    """Test views."""
    size: int = SIZE
    """Image side in pixels."""
    voxel: float = VOXEL
    """The true mesh's grid step."""
    supersample: int = SUPERSAMPLE
    """Samples per pixel along each axis."""


# ------------------------------------------------------------------------------------------------ the shape
def signed_distance(points: np.ndarray) -> np.ndarray:
    """[N] signed distance (negative inside) of the shape at `points` [N, 3]: exact near the surface of each part;
    the union (min) and the cut (max with the negated dent) keep the zero set exact, which is all marching cubes
    needs."""
    q = np.abs(points - BOX_CENTRE) - (BOX_HALF - BOX_ROUNDING)
    box = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0) - BOX_ROUNDING
    ball = np.linalg.norm(points - BALL_CENTRE, axis=1) - BALL_RADIUS
    p = points - RING_CENTRE
    ring = np.hypot(np.hypot(p[:, 0], p[:, 2]) - RING_RADII[0], p[:, 1]) - RING_RADII[1]
    dent = np.linalg.norm(points - DENT_CENTRE, axis=1) - DENT_RADIUS
    return np.maximum(np.minimum(np.minimum(box, ball), ring), -dent)


def shape_box() -> tuple[np.ndarray, np.ndarray]:
    """(lowest, highest) corner of a box that holds the shape (from the parts' own extents)."""
    low = np.minimum.reduce([BOX_CENTRE - BOX_HALF, BALL_CENTRE - BALL_RADIUS,
                             RING_CENTRE - np.array([sum(RING_RADII), RING_RADII[1], sum(RING_RADII)])])
    high = np.maximum.reduce([BOX_CENTRE + BOX_HALF, BALL_CENTRE + BALL_RADIUS,
                              RING_CENTRE + np.array([sum(RING_RADII), RING_RADII[1], sum(RING_RADII)])])
    return low, high


def texture(points: np.ndarray) -> np.ndarray:
    """[N, 3] colour in [0, 1] at surface points [N, 3]: the solid checker of the module docstring. A hashed colour
    per cube, not just two, so that no two neighbouring cubes look alike and a view has no repeating pattern to
    confuse."""
    cells = np.floor(points / CELL).astype(np.int64)
    hashed = (cells[:, 0] * 73856093) ^ (cells[:, 1] * 19349663) ^ (cells[:, 2] * 83492791)
    colour = PALETTE[hashed % len(PALETTE)]
    return np.where((cells.sum(axis=1) % 2 == 1)[:, None], colour * DARKER, colour)


def true_mesh(voxel: float = VOXEL) -> trimesh.Trimesh:
    """The shape's surface by marching cubes on a grid of step `voxel`, outward-facing, with the texture's vertex
    colours. The grid is shifted by an odd share of a step so that no sample lies exactly on a flat face (a zero
    sample makes degenerate triangles)."""
    from skimage.measure import marching_cubes

    if not 0 < voxel <= 0.05:
        raise SceneError(f"--voxel {voxel:g}: the true mesh's grid step must be in (0, 0.05] scene units")
    low, high = shape_box()
    origin = low - (2 + 0.37) * voxel
    counts = np.ceil((high + 2 * voxel - origin) / voxel).astype(int) + 1
    axes = [origin[i] + voxel * np.arange(counts[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = -signed_distance(grid).reshape(*counts)  # positive inside: marching cubes' default orientation
    vertices, faces, _, _ = marching_cubes(inside, 0.0, spacing=(voxel, voxel, voxel), allow_degenerate=False)
    vertices = vertices.astype(np.float64) + origin
    colours = np.round(texture(vertices) * 255).astype(np.uint8)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=colours, process=False)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


# ------------------------------------------------------------------------------------------------ the cameras
def orbit(count: int, turn: float = 0.0) -> list[np.ndarray]:
    """`count` camera-to-world 4x4 matrices in Blender's camera axes, at DISTANCE from the origin and looking at it,
    spread evenly over heights LOW..HIGH by a Fibonacci spiral (`turn` rotates the spiral: the test views lie
    between the training ones)."""
    step = np.arange(count) + 0.5
    height = LOW + (HIGH - LOW) * step / count
    azimuth = step * math.pi * (3 - math.sqrt(5)) + turn
    across = np.sqrt(1 - height ** 2)
    poses = []
    for h, a, r in zip(height, azimuth, across):
        back = np.array([r * math.cos(a), r * math.sin(a), h])  # the camera's +z: from the origin to the camera
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
        pose[:3, 3] = DISTANCE * back
        poses.append(pose)
    return poses


def camera_of(pose: np.ndarray, size: int, angle_x: float = CAMERA_ANGLE_X):
    """The mcsplat Camera (OpenCV axes: y and z of Blender's camera flipped) of a Blender camera-to-world pose, for a
    square image of `size` pixels. Worked out here rather than by the loader's code, so that the tests' comparison
    with a loaded scene checks both."""
    from mcsplat.camera import Camera, intrinsics

    opencv = pose @ np.diag([1.0, -1.0, -1.0, 1.0])
    focal = 0.5 * size / math.tan(0.5 * angle_x)
    return Camera(K=intrinsics(focal, focal, size / 2, size / 2),
                  world_to_camera=torch.from_numpy(np.linalg.inv(opencv)).float(), width=size, height=size)


# ------------------------------------------------------------------------------------------------ rendering
def render(mesh: trimesh.Trimesh, pose: np.ndarray, size: int, supersample: int = SUPERSAMPLE) -> np.ndarray:
    """uint8 [size, size, 4]: the mesh seen from `pose`, its colour the texture at each sample's surface point (the
    point back-projected from the rasterizer's depth), straight (not premultiplied) alpha = the share of a pixel's
    samples that hit."""
    from mcsplat.mesh.raster import rasterize

    fine = size * supersample
    camera = camera_of(pose, fine)
    raster = rasterize(torch.from_numpy(np.asarray(mesh.vertices)), torch.from_numpy(np.asarray(mesh.faces)), camera)
    depth = raster.depth.double().numpy()
    hit = raster.face.numpy() >= 0
    rows, columns = np.nonzero(hit)
    z = depth[hit]
    in_camera = np.stack([(columns + 0.5 - camera.cx) / camera.fx * z, (rows + 0.5 - camera.cy) / camera.fy * z, z], 1)
    c2w = np.linalg.inv(camera.world_to_camera.double().numpy())
    colour = np.zeros((fine, fine, 3))
    colour[hit] = texture(in_camera @ c2w[:3, :3].T + c2w[:3, 3])
    blocks = (size, supersample, size, supersample)
    covered = hit.reshape(blocks).sum(axis=(1, 3))
    summed = colour.reshape(*blocks, 3).sum(axis=(1, 3))
    rgb = summed / np.maximum(covered, 1)[..., None]
    alpha = covered / supersample ** 2
    return np.round(np.concatenate([rgb, alpha[..., None]], axis=2) * 255).astype(np.uint8)


# ------------------------------------------------------------------------------------------------ the folder
def check_folder(folder: Path) -> None:
    """A one-line error when `folder` holds anything: the scene is never written over other files."""
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise SceneError(f"{folder} exists and is not an empty folder; give a new folder (the scene is never written "
                         f"over other files)")


def write_split(folder: Path, split: str, poses: list[np.ndarray], mesh: trimesh.Trimesh, size: int,
                supersample: int) -> None:
    """The split's PNGs, then its transforms_<split>.json."""
    (folder / split).mkdir(parents=True, exist_ok=True)
    frames = []
    for index, pose in enumerate(poses):
        Image.fromarray(render(mesh, pose, size, supersample), "RGBA").save(folder / split / f"r_{index}.png")
        frames.append({"file_path": f"./{split}/r_{index}", "transform_matrix": pose.round(9).tolist()})
    listed = ",\n  ".join(json.dumps(frame) for frame in frames)  # a frame a line
    text = f'{{"camera_angle_x": {CAMERA_ANGLE_X},\n "frames": [\n  {listed}\n ]\n}}\n'
    (folder / f"transforms_{split}.json").write_text(text)


def write_scene(folder: Path, train: int = TRAIN_VIEWS, test: int = TEST_VIEWS, size: int = SIZE,
                voxel: float = VOXEL, supersample: int = SUPERSAMPLE) -> trimesh.Trimesh:
    """The scene folder of the module docstring; returns the true mesh. Refuses a folder that holds anything. The
    test split's transforms are written last, so a folder that has them is complete."""
    from mcsplat.mesh import write_mesh

    folder = Path(folder)
    check_folder(folder)
    if train < 1 or test < 0:
        raise SceneError(f"--train {train} --test {test}: a scene needs a training view, and no negative count")
    if size < 8 or supersample < 1:
        raise SceneError(f"--size {size} --supersample {supersample}: the images need 8 pixels a side or more, and "
                         f"one sample a pixel or more")
    mesh = true_mesh(voxel)
    folder.mkdir(parents=True, exist_ok=True)
    write_mesh(folder / "mesh.ply", mesh)
    write_split(folder, "train", orbit(train), mesh, size, supersample)
    write_split(folder, "test", orbit(test, turn=math.pi / max(train, 1)), mesh, size, supersample)
    return mesh


def main(argv: list[str] | None = None) -> None:
    args = tyro.cli(Options, args=argv, description=__doc__)
    try:
        mesh = write_scene(args.folder, args.train, args.test, args.size, args.voxel, args.supersample)
    except SceneError as error:
        sys.exit(f"exact_mesh_scene.py: {error}")
    print(f"wrote {args.folder}: {args.train} + {args.test} views of {args.size}x{args.size}, true mesh of "
          f"{len(mesh.faces):,} faces")


if __name__ == "__main__":
    main()
