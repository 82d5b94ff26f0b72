"""`extract(model, views)`: a trained model's surface as a coloured triangle mesh.

    render every view's median (or planar) depth  ->  render each view again, keep the pixels whose depth enough
    of its nearest views confirm, fuse them with the colour into a truncated signed distance volume, each view's
    empty space only in front of its clear depth  ->  marching cubes  ->  drop the small pieces

Pixels whose accumulated alpha stays below `alpha_min` fuse nothing (they show no surface), and their colour is the
foreground's own (the background taken out and divided by alpha). Everything but marching cubes runs on the model's
device.
"""

from __future__ import annotations

import time
from typing import Sequence

import torch
import trimesh
from tqdm import tqdm

from ..camera import Camera
from ..errors import MCSplatError
from ..render import GaussiansLike, render
from .clean import drop_small_pieces
from .clear_space import clear_depth, raised_opacities
from .consistency import KeptDepth, consistent_depth, nearest_views
from .fusion import TSDFVolume
from .grid import check_memory, choose_grid, object_box
from .options import MeshOptions
from .marching_cubes import zero_surface


@torch.no_grad()
def extract(model: GaussiansLike, views: Sequence, options: MeshOptions = MeshOptions(), *,
            sh_degree: int | None = None, progress: bool = False) -> trimesh.Trimesh:
    """The surface that `views` (scene Views or Cameras) see of `model`, as a Trimesh with vertex colours, in the
    scene's world coordinates. `mesh.metadata["mcsplat"]` tells the grid and the time of each stage."""
    cameras: list[Camera] = [getattr(view, "camera", view) for view in views]
    if not cameras:
        raise MCSplatError("no views to fuse: the run's scene has no training views")
    device = model.means.device
    grid = choose_grid(*object_box(model.means, model.opacities, cameras), options.voxel_size,
                       options.voxel_budget, options.truncation)
    check_memory(grid, device)
    seconds = {}
    started = time.perf_counter()
    checking = options.consistent_views > 0 and len(cameras) > 1
    kept = []
    for camera in tqdm(cameras if checking else [], desc="rendering depths", unit="view", disable=not progress,
                       leave=False):
        camera = camera.to(device)
        kept.append(KeptDepth(camera, surface_of_view(model, camera, options.alpha_min, sh_degree, options.depth)[0]))
    neighbours = nearest_views(cameras) if checking else [[] for _ in cameras]
    seconds["depths"] = time.perf_counter() - started
    started = time.perf_counter()
    volume = TSDFVolume(grid, device, options.free_weight)
    raised = raised_opacities(model, options.clear_alpha)
    surface_pixels = fused_pixels = 0
    for index, camera in enumerate(tqdm(cameras, desc="fusing views", unit="view", disable=not progress,
                                        leave=False)):
        on_device = camera.to(device)
        depth, rgb = surface_of_view(model, on_device, options.alpha_min, sh_degree, options.depth)
        surface_pixels += int(torch.isfinite(depth).sum())
        need = min(options.consistent_views, len(neighbours[index]))
        confirmed = consistent_depth(depth, on_device, [kept[j] for j in neighbours[index]], need)
        fused_pixels += int(torch.isfinite(confirmed).sum())
        volume.integrate(camera, confirmed, rgb, clear_depth(raised, on_device, depth))
    del kept
    if surface_pixels == 0:
        raise MCSplatError(f"no pixel of any view reaches --alpha-min {options.alpha_min}: nothing to fuse; lower it")
    if fused_pixels == 0:
        raise MCSplatError(f"no pixel's depth is confirmed by {options.consistent_views} of its nearest views: "
                           f"nothing to fuse; lower --consistent-views (0 fuses every pixel)")
    volume.fill_gaps()
    seconds["fusion"] = time.perf_counter() - started
    started = time.perf_counter()
    vertices, faces, colors = zero_surface(volume, progress)
    del volume
    if len(faces) == 0:
        raise MCSplatError(f"the fused volume ({grid.describe()}) holds no surface; lower --voxel-size or "
                           f"--alpha-min")
    seconds["marching_cubes"] = time.perf_counter() - started
    started = time.perf_counter()
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=colors)  # merges the blocks' seams
    mesh = drop_small_pieces(mesh, options.min_component)
    seconds["cleaning"] = time.perf_counter() - started
    mesh.metadata["mcsplat"] = {"grid": grid, "seconds": seconds, "views": len(cameras),
                                "fused_share": fused_pixels / surface_pixels}
    return mesh


def surface_of_view(model: GaussiansLike, camera: Camera, alpha_min: float, sh_degree: int | None,
                    which: str = "median") -> tuple[torch.Tensor, torch.Tensor]:
    """(the `which` depth [H, W], -inf where alpha < alpha_min or there is none; foreground colour [H, W, 3]) of one
    view."""
    planar = which == "planar"
    # Black background: rgb is the foreground.
    out = render(model, camera, None, sh_degree, outputs={"planar_depth" if planar else "median_depth"})
    surface = out.planar_depth if planar else out.median_depth
    depth = torch.where((out.alpha >= alpha_min) & (surface > 0), surface, torch.full_like(surface, -float("inf")))
    rgb = out.rgb / out.alpha.clamp(min=1e-6)[..., None]
    return depth, rgb

