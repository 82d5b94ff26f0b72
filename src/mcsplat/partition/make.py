"""The plan made from a scene: cut its ground plane into cells of equal point counts, grow each into its region,
give each block the views that see its region and a cap in proportion to the points it trains from."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import torch

from ..config import TrainConfig
from ..data import Scene, View
from ..errors import MCSplatError
from .cells import Cell, bounds, split_cells
from .ground import GroundFrame, ground_of
from .memory import estimated_bytes, format_bytes, gaussians_that_fit
from .blocks_file import Block, BlockPlan
from .scene import scene_points

MOST_BLOCKS = 256
SAMPLED_POINTS = 50_000  # points projected into each view to tell which blocks it sees
MIN_TRAIN_VIEWS = 10  # a block trains on at least the views that see most of it


def make_plan(scene: Scene, training: TrainConfig, count: int | None = None, memory: int | None = None,
              margin: float = 0.2, min_view_share: float = 0.25) -> BlockPlan:
    """The plan of `scene` in `count` blocks, or in as few as let each block's run fit in `memory` bytes."""
    check_plan_options(training, count, memory, margin, min_view_share)
    total = total_cap(training)
    pixels = max(view.camera.width * view.camera.height for view in scene.train)
    if memory is not None and gaussians_that_fit(memory, pixels) < 1:
        raise MCSplatError(f"--memory {format_bytes(memory)} holds no run at all: one that trains on images of "
                           f"{pixels / 1e6:.1f} MP needs {format_bytes(estimated_bytes(1, pixels))} before its first "
                           f"Gaussian")
    points = scene_points(scene)[0]
    scene = dataclasses.replace(scene, points=points)  # the cut and the views' shares read them from here
    points = points if points is not None else _centres(scene.train)
    ground = ground_of([view.camera for view in scene.train], points)
    uv = ground.coordinates(points)
    # What each view sees does not depend on the cut: found once, whatever number of blocks is tried.
    seen = (_sightings(scene.train, scene, ground), _sightings(scene.test, scene, ground))
    for tried in ([count] if count is not None else range(1, MOST_BLOCKS + 1)):
        blocks = _blocks(scene, uv, seen, tried, total, margin, min_view_share)
        plan = BlockPlan(scene=Path(scene.root), ground=ground, margin=margin, min_view_share=min_view_share,
                         memory_limit=memory, total_cap=total, training=training, blocks=tuple(blocks))
        if memory is None or all(block.memory <= memory for block in blocks):
            return plan
        if count is not None:
            worst = max(blocks, key=lambda block: block.memory)
            raise MCSplatError(f"block {worst.index} of {count} needs about {format_bytes(worst.memory)} (cap "
                               f"{worst.cap:,}) but --memory is {format_bytes(memory)}; give more blocks, or leave "
                               f"--count out to find how many fit")
    raise MCSplatError(f"no cut into {MOST_BLOCKS} blocks or fewer fits each block in {format_bytes(memory)} (a run "
                       f"with images of {pixels / 1e6:.1f} MP holds {gaussians_that_fit(memory, pixels):,} Gaussians "
                       f"at most there); give more --memory or a lower --cap-max")


def check_plan_options(training: TrainConfig, count: int | None, memory: int | None, margin: float,
                       min_view_share: float) -> None:
    """A one-line error for options no plan can be made with. None needs the scene, so `blocks plan` checks them
    before loading it (whether --memory holds a run at all depends on its images: make_plan checks that)."""
    total_cap(training)
    if count is None and memory is None:
        raise MCSplatError("give the number of blocks (--count) or the memory each block's run may hold (--memory)")
    if count is not None and not 1 <= count <= MOST_BLOCKS:
        raise MCSplatError(f"--count must be between 1 and {MOST_BLOCKS}")
    if not margin >= 0 or not 0 <= min_view_share < 1:
        raise MCSplatError("--margin must be 0 or more and --min-view-share within [0, 1)")


def total_cap(training: TrainConfig) -> int:
    """The Gaussians of the whole scene: the training options' cap (blocks share it)."""
    if training.cap_max == "auto":
        raise MCSplatError("--cap-max auto grows one run as its gradients ask; blocks need a number to share "
                           "out: give --cap-max N for the whole scene")
    if training.max_gaussians is None:
        raise MCSplatError("blocks share out a cap: give ADC's --cap-max N for the whole scene")
    return training.max_gaussians


def _blocks(scene: Scene, uv: torch.Tensor, seen: tuple[Sightings, Sightings], count: int, total: int,
            margin: float, min_view_share: float) -> list[Block]:
    extent = bounds(uv)
    cores = split_cells(uv, count)
    # The margin is a share of the typical cell's size, the same for every cell: a large cell of sparse points at
    # the edge would otherwise reach with its margin into the dense middle.
    sizes = torch.tensor([core.size_within(extent) for core in cores], dtype=torch.float64)
    pad = sizes.median(dim=0).values * margin
    regions = [core.grown((float(pad[0]), float(pad[1]))) for core in cores]
    in_region = [region.contains(uv) for region in regions]
    train_sees, test_sees = (sightings.shares(regions) for sightings in seen)
    blocks = []
    for index, (core, region) in enumerate(zip(cores, regions)):
        train = _seeing(scene.train, train_sees, index, min_view_share, MIN_TRAIN_VIEWS)
        if not train:
            raise MCSplatError(f"block {index} of {count} is seen by no training view; give fewer blocks")
        test = _seeing(scene.test, test_sees, index, min_view_share, 1)
        points = int(in_region[index].sum())
        blocks.append(Block(index=index, core=core, region=region, cap=max(1, round(total * points / len(uv))),
                            points=points, pixels=max(view.camera.width * view.camera.height for view in train),
                            train_views=tuple(view.name for view in train),
                            test_views=tuple(view.name for view in test)))
    return blocks


def _seeing(views: list[View], shares: list[list[float]], index: int, min_share: float, at_least: int
            ) -> list[View]:
    """The views that train (or test) block `index`: those of which at least `min_share` see its region, and at
    least the `at_least` that see most of it (a block in the middle of many is never left with too few), in the
    scene's order; never one that sees nothing of it."""
    ranked = sorted(range(len(views)), key=lambda i: -shares[i][index])
    chosen = {i for i in ranked if shares[i][index] >= min_share} | set(ranked[:at_least])
    return [views[i] for i in sorted(chosen) if shares[i][index] > 0]


@dataclass(frozen=True)
class Sightings:
    """What a list of views sees: where a sample of the scene's points stands on the ground, and for each view the
    sample's points that project into its image. For a scene without points, each view sees its camera's centre."""

    uv: torch.Tensor                 # [S, 2]
    seen: list[torch.Tensor]         # per view, indices into the sample

    def shares(self, regions: list[Cell]) -> list[list[float]]:
        """For each view, the share of what it sees that lies in each region."""
        members = torch.stack([region.contains(self.uv) for region in regions], dim=1).to(torch.float64)
        return [[0.0] * len(regions) if not len(indices) else (members[indices].sum(dim=0) / len(indices)).tolist()
                for indices in self.seen]


def _sightings(views: list[View], scene: Scene, ground: GroundFrame) -> Sightings:
    if scene.points is None:
        centres = _centres(views) if views else torch.zeros(0, 3, dtype=torch.float64)
        return Sightings(ground.coordinates(centres), [torch.tensor([i]) for i in range(len(views))])
    step = max(1, scene.points.shape[0] // SAMPLED_POINTS)
    points = scene.points[::step].to(torch.float64)
    return Sightings(ground.coordinates(points), [_in_image(view, points).nonzero().squeeze(1) for view in views])


def _in_image(view: View, points: torch.Tensor) -> torch.Tensor:
    """[P] bool: the points in front of the view's camera that project inside its image."""
    camera = view.camera
    return camera.pixels_of(camera.to_camera_space(points.to(torch.float64)), near=1e-6)[2]


def _centres(views: list[View]) -> torch.Tensor:
    return torch.stack([view.camera.center.to(torch.float64) for view in views])


def plan_table(plan: BlockPlan) -> str:
    """The plan as a few lines a user reads before training: each block's views, cap and memory."""
    lines = [f"{len(plan.blocks)} blocks of {plan.scene} (margin {plan.margin:.0%}, cap {plan.total_cap:,} in all)",
             "block  train views  test views   points        cap   memory (estimated)"]
    for block in plan.blocks:
        lines.append(f"{block.index:>5}  {len(block.train_views):>11}  {len(block.test_views):>10}  "
                     f"{block.points:>7,}  {block.cap:>9,}   {format_bytes(block.memory)}")
    if plan.memory_limit is not None:
        lines.append(f"each block's run is given {format_bytes(plan.memory_limit)}")
    return "\n".join(lines)

