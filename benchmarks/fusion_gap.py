"""Where a mesh loses what its depth maps had (issue 59): the mesh export's stages one by one, each scored against the
SfM points, and the same depth maps fused by Open3D's TSDF integration (GOF's VoxelBlockGrid; 2DGS and PGSR use
its ScalableTSDFVolume).

    .venv/bin/python benchmarks/fusion_gap.py                          # mesh_quality.py's cup-mcmc and cup-adc runs
    .venv/bin/python benchmarks/fusion_gap.py --runs RUN [RUN ...]     # other runs of a COLMAP scene
    .venv/bin/python benchmarks/fusion_gap.py --report                 # rebuild results from the records

Open3D is optional and used by this benchmark only (`.venv/bin/python -m pip install open3d==0.20.0`); without it
the Open3D rows are skipped with one line. The runs are fused on the CPU in the first run's voxel size (as
mesh_quality.py does: the later runs wait for the first and take the voxel size it recorded) with `mcsplat export`'s
defaults, stage by stage as `mcsplat.mesh.pipeline` does:

    depth        every training view's median depth where alpha >= 0.5: at each SfM point in front of the view and
                 inside it, the depth at its pixel minus the point's depth (pairs beyond 5% of R left out, as in
                 sfm_depth.py: the point is hidden in that view); and the SfM points with at least one such pair
    confirmed    the same after the consistency check (4 of the 6 nearest views)
    (clear)      every view's clear depth (mcsplat.mesh.clear_space): the fusion takes its empty space only from
                 in front of it
    volume       the fused truncated signed distance at each SfM point: inside the grid, observed, within the band
    mesh         SfM point to mesh distance (median, p90, within 1% of R) after marching cubes, then after dropping
                 the small pieces (the exported mesh: mesh_quality.py's measure), over all points and over the
                 points the depth has (those with a pair in the first stage)
                 (and, fused with a view's empty space weighing 0.1 and 0.01 of a depth: MeshOptions.free_weight;
                 and as before 2026-11-29, each view's empty space reaching to its median depth's band),
                 and mesh vertex to nearest SfM point (median: an accuracy proxy)
    Open3D       VoxelBlockGrid TSDF integration fed the same depth maps (raw, and as confirmed) and colours, at the
                 same voxel size and band; its mesh scored alike, whole and cut to our grid's box

Records (a row per run and stage): results/mesh_quality/fusion_gap.jsonl, table: results/mesh_quality/fusion_gap.md;
with --picture, a test view of each run's SfM points coloured by their distance to the mesh
(results/mesh_quality/fusion-gap-*.png). A run already recorded is not measured again (--rerun measures it again).
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import tyro
from scipy.spatial import cKDTree

import _common as C
from framework import Arm, Common, recorded
from mesh_quality import distance_to_mesh

RUNS = C.RESULTS / "mesh_quality" / "runs"
DEFAULT_RUNS = (RUNS / "cup-mcmc", RUNS / "cup-adc")
HIDDEN = 0.05     # pairs beyond this share of R: the point is hidden in that view (sfm_depth.py)
CLOSE = 0.01      # "within 1% of R"
FREE_WEIGHTS = (0.1, 0.01)  # MeshOptions.free_weight tried beside the default 1
OPEN3D_BLOCK_SIDE = 8     # voxels along a block's side: with 16 (GOF's), the mesh extraction of the cup's raw depths
#                           (33k blocks at 0.45% R) crashed (a segmentation fault); 8^3 blocks hold a third of the
#                           voxels
OPEN3D_BLOCKS = 120_000  # blocks allocated up front (the cup's raw depths touch 97k)
OPEN3D_HINT = "open3d is missing: the Open3D rows are skipped (`.venv/bin/python -m pip install open3d==0.20.0`)"
RESULTS = "mesh_quality/fusion_gap"  # beside the runs it measures
KEY = ("run",)
ROW_KEY = ("stage",)  # a record per stage of a run


@dataclass(frozen=True)
class Options:
    """Where a mesh loses what its depth maps had: the export's stages one by one against the SfM points."""

    runs: tuple[Path, ...] = ()
    """Runs of a COLMAP scene (default: mesh_quality.py's cup-mcmc and cup-adc)."""
    picture: bool = False
    """Also draw each run's SfM points by distance."""
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def arms(options: Options) -> list[Arm]:
    """An arm per run; the later ones wait for the first: they fuse in its voxel size."""
    runs = options.runs or DEFAULT_RUNS
    return [Arm(run.name, {"run": run.name, "run_folder": str(run)}, after=(runs[0].name,) if index else ())
            for index, run in enumerate(runs)]


def run(arm: Arm, options: Options, folder: Path) -> list[dict]:
    """The run's stages, a row each."""
    voxel_size = recorded("fusion_gap", folder).of(arm.after[0])[0]["voxel_size"] if arm.after else None
    return measure(Path(arm.labels["run_folder"]), voxel_size, folder / f"fusion-gap-{arm.name}.png"
                   if options.picture else None)


# ------------------------------------------------------------------------------------------------ the stages
@torch.no_grad()
def depth_maps(trained, cameras, options) -> tuple[list, list, list, list]:
    """(raw depth maps, confirmed depth maps, colours, clear depths) of every view, as extract() fuses them."""
    from mcsplat.mesh.clear_space import clear_depth, raised_opacities
    from mcsplat.mesh.consistency import KeptDepth, consistent_depth, nearest_views
    from mcsplat.mesh.pipeline import surface_of_view

    raw, colours, clears = [], [], []
    raised = raised_opacities(trained.model, options.clear_alpha)
    for camera in cameras:
        depth, rgb = surface_of_view(trained.model, camera, options.alpha_min, trained.sh_degree, options.depth)
        raw.append(depth)
        colours.append(rgb)
        clears.append(clear_depth(raised, camera, depth))
    kept = [KeptDepth(camera, depth) for camera, depth in zip(cameras, raw)]
    neighbours = nearest_views(cameras)
    confirmed = [consistent_depth(depth, camera, [kept[j] for j in near], min(options.consistent_views, len(near)))
                 for camera, depth, near in zip(cameras, raw, neighbours)]
    return raw, confirmed, colours, clears


def pairs(points: torch.Tensor, cameras, depths, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(point index, depth at the point's pixel - the point's depth) over every view's point-view pairs with a
    surface at the pixel, those beyond HIDDEN * R left out."""
    indices, differences = [], []
    for camera, depth in zip(cameras, depths):
        local = camera.to_camera_space(points)
        u, v, inside = camera.pixels_of(local)
        which = inside.nonzero().squeeze(1)
        found = depth[v[which].long(), u[which].long()]
        difference = found - local[which, 2]
        keep = torch.isfinite(found) & (difference.abs() < HIDDEN * radius)
        indices.append(which[keep].numpy())
        differences.append(difference[keep].numpy())
    return np.concatenate(indices), np.concatenate(differences)


def see_through(points: torch.Tensor, cameras, depths, band: float) -> dict:
    """Over every pair with a surface at the point's pixel (none left out): the share whose depth lies more than the
    fusion's band behind the point (the view sees through where the point is: to the fusion, it is empty there) and
    more than the band in front (hidden there, or a floater)."""
    behind = in_front = total = 0
    for camera, depth in zip(cameras, depths):
        local = camera.to_camera_space(points)
        u, v, inside = camera.pixels_of(local)
        which = inside.nonzero().squeeze(1)
        found = depth[v[which].long(), u[which].long()]
        seen = torch.isfinite(found)
        difference = found[seen] - local[which[seen], 2]
        behind, in_front = behind + int((difference > band).sum()), in_front + int((difference < -band).sum())
        total += int(seen.sum())
    return {"all_pairs": total, "seen_through": behind / total, "in_front": in_front / total}


def pair_figures(indices: np.ndarray, differences: np.ndarray, radius: float, num_points: int) -> dict:
    magnitude = np.abs(differences) / radius
    return {"pairs": int(len(magnitude)), "pair_median": float(np.median(magnitude)),
            "pair_p90": float(np.quantile(magnitude, 0.9)), "pair_signed": float(np.median(differences / radius)),
            "pair_close": float((magnitude <= CLOSE).mean()),
            "points_with_pair": float(len(np.unique(indices)) / num_points),
            "points_with_close_pair": float(len(np.unique(indices[magnitude <= CLOSE])) / num_points)}


def fuse(grid, cameras, depths, colours, clears: list | None, free_weight: float = 1.0):
    """The volume extract() fuses; with `clears` None, each view's empty space reaches to its depth's band."""
    from mcsplat.mesh.fusion import TSDFVolume

    volume = TSDFVolume(grid, torch.device("cpu"), free_weight)
    for index, (camera, depth, rgb) in enumerate(zip(cameras, depths, colours)):
        volume.integrate(camera, depth, rgb, None if clears is None else clears[index])
    volume.fill_gaps()
    return volume


def volume_figures(volume, points: torch.Tensor, has_depth: np.ndarray) -> dict:
    """The fused volume at the SfM points: inside the grid, observed (all 8 surrounding grid points), within the
    band, and |signed distance| (world units, at most the band) of the points the depth has."""
    from mcsplat.mesh.marching_cubes import trilinear

    grid = volume.grid
    position = ((points.double() - torch.tensor(grid.origin, dtype=torch.float64)) / grid.voxel_size).float()
    shape = torch.tensor(grid.shape)
    inside = ((position >= 0) & (position <= (shape - 1).float())).all(dim=1)
    low = position.floor().long().clamp(min=torch.zeros(3, dtype=torch.long), max=shape - 2)
    observed = torch.ones(len(points), dtype=torch.bool)
    for corner in range(8):
        offset = torch.tensor([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
        index = low + offset
        observed &= volume.weight[index[:, 0], index[:, 1], index[:, 2]] > 0
    observed &= inside
    tsdf = trilinear(volume.tsdf[..., None], position)[:, 0].abs()
    in_band = observed & (tsdf < 1)
    distance = (tsdf.clamp(max=1) * grid.truncation).numpy()
    chosen = observed.numpy() & has_depth
    return {"in_grid": float(inside.float().mean()), "observed": float(observed.float().mean()),
            "in_band": float(in_band.float().mean()),
            "sdf_median_depth_points": float(np.median(distance[chosen])) if chosen.any() else float("nan")}


def mesh_figures(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, radius: float,
                 has_depth: np.ndarray) -> tuple[dict, np.ndarray]:
    distance = distance_to_mesh(points, vertices, faces) / radius
    used = vertices[np.unique(faces)]
    to_points = cKDTree(points).query(used)[0] / radius
    return ({"faces": int(len(faces)), "mesh_to_points_median": float(np.median(to_points)),
             "mesh_median": float(np.median(distance)),
             "mesh_p90": float(np.quantile(distance, 0.9)), "mesh_close": float((distance <= CLOSE).mean()),
             "mesh_median_depth_points": float(np.median(distance[has_depth])),
             "mesh_close_depth_points": float((distance[has_depth] <= CLOSE).mean())}, distance)


def our_mesh(volume) -> tuple:
    """(mesh after marching cubes, after dropping the small pieces), as extract() makes them."""
    import trimesh

    from mcsplat.mesh.clean import drop_small_pieces
    from mcsplat.mesh import MeshOptions
    from mcsplat.mesh.marching_cubes import zero_surface

    vertices, faces, colours = zero_surface(volume)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=colours)
    return mesh, drop_small_pieces(mesh, MeshOptions().min_component)


def open3d_mesh(cameras, depths, colours, voxel_size: float, truncation_voxels: float):
    """(vertices, faces) of Open3D's fusion of the depth maps, or None without open3d. It runs in a process of its
    own: in the process that rendered the views, open3d 0.20's mesh extraction crashed (a segmentation fault in its
    TBB threads), alone it does not."""
    try:
        import open3d  # noqa: F401
    except ImportError:
        return None
    with tempfile.TemporaryDirectory() as folder:
        inputs, outputs = Path(folder) / "views.npz", Path(folder) / "mesh.npz"
        np.savez(inputs, voxel_size=voxel_size, truncation_voxels=truncation_voxels,
                 K=np.stack([c.K.double().numpy() for c in cameras]),
                 world_to_camera=np.stack([c.world_to_camera.double().numpy() for c in cameras]),
                 depth=np.stack([torch.where(torch.isfinite(d), d, 0.0).numpy() for d in depths]),
                 rgb=np.stack([c.clamp(0, 1).numpy() for c in colours]))
        subprocess.run([sys.executable, __file__, "--open3d-worker", str(inputs), str(outputs)], check=True,
                       stdout=sys.stderr)  # stdout carries the arm's answer
        made = np.load(outputs)
        return made["vertices"], made["faces"]


def open3d_worker(inputs: Path, outputs: Path) -> None:
    """Open3D's VoxelBlockGrid TSDF integration (GOF's fusion) of the views in `inputs`, its mesh at Open3D's
    default weight threshold (3 views) into `outputs`. (0.20's ScalableTSDFVolume, 2DGS's, fused nothing here, not
    even a plane seen squarely: its volume stays empty.)"""
    import open3d as o3d
    import open3d.core as o3c

    views = np.load(inputs)
    voxel_size, truncation = float(views["voxel_size"]), float(views["truncation_voxels"])
    grid = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight", "color"),
                                         attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
                                         attr_channels=((1), (1), (3)), voxel_size=voxel_size,
                                         block_resolution=OPEN3D_BLOCK_SIDE,
                                         block_count=OPEN3D_BLOCKS, device=o3c.Device("CPU:0"))
    far = float(views["depth"].max()) + 1.0
    for K, w2c, depth, rgb in zip(views["K"], views["world_to_camera"], views["depth"], views["rgb"]):
        depth, colour = o3d.t.geometry.Image(o3c.Tensor(depth)), o3d.t.geometry.Image(o3c.Tensor(rgb))
        intrinsic, extrinsic = o3c.Tensor(K), o3c.Tensor(w2c)
        blocks = grid.compute_unique_block_coordinates(depth, intrinsic, extrinsic, depth_scale=1.0, depth_max=far,
                                                       trunc_voxel_multiplier=truncation)
        grid.integrate(blocks, depth, colour, intrinsic, intrinsic, extrinsic, depth_scale=1.0, depth_max=far,
                       trunc_voxel_multiplier=truncation)
    mesh = grid.extract_triangle_mesh().to_legacy()
    np.savez(outputs, vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.triangles))


def in_box(vertices: np.ndarray, faces: np.ndarray, grid) -> np.ndarray:
    """The faces whose three vertices lie in `grid`'s box."""
    low = np.asarray(grid.origin)
    high = low + (np.asarray(grid.shape) - 1) * grid.voxel_size
    inside = ((vertices >= low) & (vertices <= high)).all(axis=1)
    return faces[inside[faces].all(axis=1)]


# ------------------------------------------------------------------------------------------------ one run
def measure(run: Path, voxel_size: float | None, picture: Path | None) -> list[dict]:
    from mcsplat.run import trained as trained_run
    from mcsplat.mesh import DEFAULT_VOXEL_BUDGET, MeshOptions
    from mcsplat.mesh.grid import choose_grid, object_box

    trained = trained_run.load(run, torch.device("cpu"))
    scene, radius = trained.scene, trained.scene.radius
    if scene.points is None:
        raise SystemExit(f"{run}: its scene has no SfM points")
    options = MeshOptions() if voxel_size is None else \
        MeshOptions(voxel_size=voxel_size, voxel_budget=4 * DEFAULT_VOXEL_BUDGET)
    cameras = [view.camera for view in scene.train]
    grid = choose_grid(*object_box(trained.model.means, trained.model.opacities, cameras), options.voxel_size,
                       options.voxel_budget, options.truncation)
    points = scene.points.float()
    points_np = scene.points.double().numpy()
    started = time.perf_counter()
    raw, confirmed, colours, clears = depth_maps(trained, cameras, options)
    base = {"strategy": trained.config.strategy, "radius": radius, "voxel_size": grid.voxel_size,
            "grid": list(grid.shape), "sfm_points": len(points)}
    records = []

    def add(stage: str, **figures) -> None:
        records.append({**base, "stage": stage, **figures})

    raw_index, raw_difference = pairs(points, cameras, raw, radius)
    has_depth = np.zeros(len(points), dtype=bool)
    has_depth[raw_index] = True
    surface = sum(int(torch.isfinite(d).sum()) for d in raw)
    add("depth (alpha >= 0.5)", pixels=surface, **pair_figures(raw_index, raw_difference, radius, len(points)),
        **see_through(points, cameras, raw, grid.truncation))
    kept_index, kept_difference = pairs(points, cameras, confirmed, radius)
    add("confirmed (4 of 6)", pixels=sum(int(torch.isfinite(d).sum()) for d in confirmed),
        pixel_share=sum(int(torch.isfinite(d).sum()) for d in confirmed) / surface,
        **pair_figures(kept_index, kept_difference, radius, len(points)),
        **see_through(points, cameras, confirmed, grid.truncation))
    volume = fuse(grid, cameras, confirmed, colours, clears)
    add("volume", **volume_figures(volume, points, has_depth))
    before, after = our_mesh(volume)
    del volume
    figures, _ = mesh_figures(np.asarray(before.vertices), np.asarray(before.faces), points_np, radius, has_depth)
    add("mesh: marching cubes", **figures)
    figures, distance = mesh_figures(np.asarray(after.vertices), np.asarray(after.faces), points_np, radius,
                                     has_depth)
    add("mesh: small pieces dropped (exported)", **figures)
    ours_seconds = time.perf_counter() - started
    before, after = our_mesh(fuse(grid, cameras, confirmed, colours, None))
    add("mesh: exported, empty space up to the median depth (before 2026-11-29)",
        **mesh_figures(np.asarray(after.vertices), np.asarray(after.faces), points_np, radius, has_depth)[0])
    for free_weight in FREE_WEIGHTS:
        before, after = our_mesh(fuse(grid, cameras, confirmed, colours, clears, free_weight))
        add(f"mesh: marching cubes, free-space weight {free_weight:g}",
            **mesh_figures(np.asarray(before.vertices), np.asarray(before.faces), points_np, radius, has_depth)[0])
        add(f"mesh: exported, free-space weight {free_weight:g}",
            **mesh_figures(np.asarray(after.vertices), np.asarray(after.faces), points_np, radius, has_depth)[0])
    if picture:
        draw(trained, distance, has_depth, picture)
    for name, depths in (("raw", raw), ("confirmed", confirmed)):
        started = time.perf_counter()
        made = open3d_mesh(cameras, depths, colours, grid.voxel_size, grid.truncation_voxels)
        if made is None:
            print(OPEN3D_HINT)
            break
        vertices, faces = made
        add(f"Open3D, {name} depths", seconds=round(time.perf_counter() - started, 1),
            **mesh_figures(vertices, faces, points_np, radius, has_depth)[0])
        add(f"Open3D, {name} depths, cut to our box",
            **mesh_figures(vertices, in_box(vertices, faces, grid), points_np, radius, has_depth)[0])
    records[0]["seconds_ours"] = round(ours_seconds, 1)
    return records


@torch.no_grad()
def draw(trained, distance: np.ndarray, has_depth: np.ndarray, path: Path) -> None:
    """A test view with the SfM points drawn in their distance to the mesh: green within 1% of R, yellow to 3%,
    red beyond; points no depth map has are drawn blue."""
    from PIL import Image

    from mcsplat.render import render

    views = trained.scene.test or trained.scene.train
    camera = views[len(views) // 2].camera
    image = (render(trained.model, camera, trained.background, trained.sh_degree).rgb.clamp(0, 1) * 160
             ).byte().numpy()
    local = camera.to_camera_space(trained.scene.points.float())
    u, v, inside = camera.pixels_of(local)
    order = np.argsort(-local[:, 2].numpy())  # far first, near drawn over them
    colours = np.where(distance[:, None] <= CLOSE, [40, 220, 40], np.where(distance[:, None] <= 3 * CLOSE,
                                                                           [250, 220, 0], [240, 30, 30]))
    colours[~has_depth] = [40, 120, 255]
    for i in order:
        if inside[i]:
            row, column = int(v[i]), int(u[i])
            image[max(0, row - 1):row + 2, max(0, column - 1):column + 2] = colours[i]
    Image.fromarray(image).save(path, optimize=True)


# ------------------------------------------------------------------------------------------------ report
def report(rows: list[dict], folder: Path) -> str:
    """fusion_gap.md: a row per run and stage."""

    def pct(key, spec=".2f"):
        return lambda r: f"{100 * r[key]:{spec}}" if key in r else ""

    columns = [("run", "run", ""), ("stage", "stage", ""),
               ("pairs", "", lambda r: f"{r['pairs']:,}" if "pairs" in r else ""),
               ("pair |d| median / p90 %R", "",
                lambda r: f"{100 * r['pair_median']:.2f} / {100 * r['pair_p90']:.2f}" if "pairs" in r else ""),
               ("pairs within 1% R", "", pct("pair_close", ".1f")),
               ("SfM points with a pair / a pair within 1% R", "",
                lambda r: f"{100 * r['points_with_pair']:.1f}% / {100 * r['points_with_close_pair']:.1f}%"
                if "pairs" in r else ""),
               ("all pairs: depth a band behind / in front", "",
                lambda r: f"{100 * r['seen_through']:.1f}% / {100 * r['in_front']:.1f}%" if "all_pairs" in r else ""),
               ("in grid / observed / in band", "",
                lambda r: f"{100 * r['in_grid']:.1f}% / {100 * r['observed']:.1f}% / {100 * r['in_band']:.1f}%"
                if "in_grid" in r else ""),
               ("|sdf| median %R (points with a depth)", "",
                lambda r: f"{100 * r['sdf_median_depth_points'] / r['radius']:.2f}" if "in_grid" in r else ""),
               ("faces", "", lambda r: f"{r['faces']:,}" if "faces" in r else ""),
               ("SfM->mesh median / p90 %R", "",
                lambda r: f"{100 * r['mesh_median']:.2f} / {100 * r['mesh_p90']:.2f}" if "faces" in r else ""),
               ("within 1% R", "", pct("mesh_close", ".1f")),
               ("mesh->SfM median %R", "", pct("mesh_to_points_median")),
               ("points with a depth: median %R, within 1% R", "",
                lambda r: f"{100 * r['mesh_median_depth_points']:.2f}, {100 * r['mesh_close_depth_points']:.1f}%"
                if "faces" in r else "")]
    return ("# Where the mesh loses the depth (fusion_gap.py)\n\n" + C.markdown_table(rows, columns) +
            "\n\nDistances in % of the scene radius R, against the COLMAP points. Pairs: (SfM point, training view) "
            "with a depth at the point's pixel within 5% of R of the point's own. \"Points with a depth\": the SfM "
            "points with at least one such pair in the first stage.\n")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--open3d-worker"]:  # open3d_mesh()'s process of its own
        sys.exit(open3d_worker(Path(sys.argv[2]), Path(sys.argv[3])))
    import framework
    sys.exit(framework.script("fusion_gap"))
