"""The seam a feature of a training run attaches through: its options are a group of TrainConfig, declared in the
feature's own module, and the group itself says what the feature adds to a run.

A group may have any of:

    check_processes(world_size) -> None          refuses, before anything is made, a number of training processes
                                                 it does not work with
    setup(start: FeatureStart) -> FeatureParts   its per-image modules and loss terms, made as the run starts
    per_view_input() -> options | None           the per-view input it needs loaded beside the photos
                                                 (data/attachments: masks, depth maps)
    facts(modules) -> dict                       what it adds to metrics.json at the end of the run
    unused_options() -> tuple[str, ...]          its options that would be ignored as the others are set (a new
                                                 run refuses them when the command line names them)

`run/state.py`'s `start`, `run/scene.py`'s `scene_of` and the end of a run ask every group of the configuration
(`config.feature_groups`) in the order TrainConfig declares them, which is the order of their modules in a step and
of their loss terms in the sum. docs/extending.md adds a feature this way.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the types only: the option groups import this module, and the CLI imports them to start
    import torch

    from .data import Scene
    from .gaussians import GaussianModel
    from .loss_terms import LossTerm
    from .per_image import PerImageModule


@dataclass(frozen=True)
class FeatureStart:
    """What a feature's `setup` is handed."""

    scene: Scene
    model: GaussianModel  # the run's model, fresh or restored (its parameters are those of the first step)
    device: torch.device
    world_size: int  # processes training together


@dataclass
class FeatureParts:
    """What a feature adds to a run's step."""

    modules: list[PerImageModule] = field(default_factory=list)  # learned per training image (per_image.py)
    loss_terms: list[LossTerm] = field(default_factory=list)  # summed after the photometric and per-image terms


def features_named(groups: list[Any], method: str) -> list[Any]:
    """The groups that have `method` (a feature need not have every part)."""
    return [group for group in groups if callable(getattr(group, method, None))]
