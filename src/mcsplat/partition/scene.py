"""The scene a block's run trains on: the views the plan gives the block, the scene's points in its region, and a
thin sample of the points beyond it, so that what its views see outside the region (the other blocks' ground, far
buildings) starts as Gaussians at about the right depth rather than as floaters inside the region. Those outside
Gaussians are trained and then left out of the merge."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import torch

from ..capture.triangulate import triangulated_points
from ..data import Scene, View
from ..data.scene import camera_radius
from ..errors import MCSplatError
from .blocks_file import Block, PlanError, read_plan

OUTSIDE_SHARE = 0.1  # the points kept beyond the region, as a share of those inside it


def parse_block(spec: str) -> tuple[Path, int]:
    """'PLAN_FILE#INDEX' (how a run's configuration names its block) -> (plan file, index)."""
    path, _, index = str(spec).rpartition("#")
    if not path or not index.isdigit():
        raise MCSplatError(f"block {spec!r} is not PLAN_FILE#INDEX")
    return Path(path), int(index)


def block_scene(scene: Scene, spec: str, run_folder: Path) -> Scene:
    """`scene` cut to the block `spec` names ('PLAN_FILE#INDEX', the plan's path from `run_folder`, the run's)."""
    path, index = parse_block(spec)
    path = Path(os.path.normpath(run_folder / path))  # "block_03/../blocks.json", even before block_03 exists
    plan = read_plan(path)
    block = plan.block(index)
    train, test = block_views(scene, block, path)
    points, colors = scene_points(scene)
    whole = None if points is None else points.shape[0]
    if points is not None:
        inside = block.region.contains(plan.ground.coordinates(points))
        keep = inside | _thin(~inside, int(inside.sum()))
        points, colors = points[keep], colors[keep]
    note = (f"block {index} of {len(plan.blocks)} ({path}): {len(train)} of {len(scene.train)} training views"
            + ("" if points is None else f", {points.shape[0]:,} of {whole:,} points"))
    return dataclasses.replace(scene, train=train, test=test, points=points, point_colors=colors,
                               radius=camera_radius([view.camera for view in train]), notes=[*scene.notes, note])


def block_views(scene: Scene, block: Block, plan_file: Path) -> tuple[list[View], list[View]]:
    """The scene's views that `block` trains and is scored on. A PlanError for a name the scene lacks, and for a
    test view among its training views (or a training view among its test views): the blocks, and the merged model,
    are scored on the scene's test views, which a block that trained on one would score too well."""
    train_views = {view.name: view for view in scene.train}
    test_views = {view.name: view for view in scene.test}
    for name in block.train_views + block.test_views:
        if name not in train_views and name not in test_views:
            raise PlanError(f"{plan_file}: block {block.index} names the view {name!r}, which the scene {scene.root} "
                            f"does not have (the scene changed since the plan was made?); make the plan again")
    for name in block.train_views:
        if name in test_views:
            raise PlanError(f"{plan_file}: block {block.index} trains on {name!r}, one of the scene's test views, "
                            f"which the blocks and the merged model are scored on; take it out of the block's "
                            f"train_views")
    for name in block.test_views:
        if name in train_views:
            raise PlanError(f"{plan_file}: block {block.index} is scored on {name!r}, one of the scene's training "
                            f"views; take it out of the block's test_views")
    return [train_views[name] for name in block.train_views], [test_views[name] for name in block.test_views]


def scene_points(scene: Scene) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """(points [P, 3], colours [P, 3] in [0, 1]) the blocks are cut by and start from: the scene's SfM points, or for
    a real capture without them the points triangulated from its known poses (cached; what `mcsplat train` would
    start from); (None, None) for a synthetic scene (random points in a cube) or where triangulation fails."""
    if scene.points is not None:
        return scene.points, scene.point_colors
    if scene.alpha or len(scene.train) < 2:
        return None, None
    try:
        found = triangulated_points(scene.train, progress=False)
    except MCSplatError:
        return None, None
    return torch.from_numpy(found.xyz).float(), torch.from_numpy(found.rgb).float() / 255.0


def _thin(outside: torch.Tensor, inside_count: int) -> torch.Tensor:
    """[N] bool: an evenly spaced sample of the `outside` points, OUTSIDE_SHARE of `inside_count` of them at most."""
    where = outside.nonzero().squeeze(1)
    wanted = int(OUTSIDE_SHARE * inside_count)
    chosen = torch.zeros_like(outside)
    if wanted > 0 and where.numel():
        step = max(1, where.numel() // wanted)
        chosen[where[::step][:wanted]] = True
    return chosen
