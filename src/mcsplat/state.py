"""What a training run carries from one step to the next, how it starts (fresh from the scene or restored from a
checkpoint) and what a checkpoint holds of it.

Restoring and continuing is exact on the CPU: the model, every Adam state, the strategy's statistics, the run's
generator and the view order are all in the checkpoint, so a resumed run takes bit for bit the steps an
uninterrupted one would have taken (same seed and thread count).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from .appearance import Compensation, check_fits, make_appearance
from .config import TrainConfig
from .data import Scene
from .distributed import Team
from .errors import MCSplatError
from .gaussians import GaussianModel
from .initialization import initial_model
from .optim import make_optimizers
from .planning import Plan, make_strategy
from .pose_refinement import PoseRefinement
from .run_dir import background_of
from .strategy import Strategy


class ViewSampler:
    """Training views in random order, each once per pass (as 3DGS pops cameras from a shuffled copy)."""

    def __init__(self, count: int, seed: int):
        self.count = count
        self.generator = torch.Generator().manual_seed(seed)
        self.order: list[int] = []

    def next(self) -> int:
        if not self.order:
            self.order = torch.randperm(self.count, generator=self.generator).tolist()
        return self.order.pop()

    def take(self, count: int) -> list[int]:
        """The next `count` indices (one per process when several train together: each takes its own)."""
        return [self.next() for _ in range(count)]

    def upcoming(self, count: int) -> list[int]:
        """The next `count` indices `next()` will return within this pass (fewer near its end), for prefetching."""
        return self.order[-1:-count - 1:-1]

    def state_dict(self) -> dict:
        return {"generator": self.generator.get_state(), "order": list(self.order)}

    def load_state_dict(self, state: dict) -> None:
        self.generator.set_state(state["generator"])
        self.order = list(state["order"])


@dataclass
class TrainingState:
    model: GaussianModel
    optimizers: dict[str, torch.optim.Optimizer]
    strategy: Strategy
    generator: torch.Generator  # relocation, growth and noise draw from it
    sampler: ViewSampler
    step: int = 0  # steps done
    train_seconds: float = 0.0  # time spent in steps (pauses, evaluations and consumers not counted)
    wall_seconds: float = 0.0  # time spent in the training loop, pauses not counted (what --budget counts)
    compensation: Compensation | None = None  # --appearance: the per-image colour transforms and their Adam
    poses: PoseRefinement | None = None  # --pose-opt: the per-image pose corrections and their Adam

    def checkpoint(self, saved_config: dict[str, Any], strategies: list[dict]) -> dict[str, Any]:
        """What checkpoint.pt holds; `saved_config` is config.json's content (the configuration and the plan it was
        trained with), `strategies` every process's strategy state (rank 0's first)."""
        return {"step": self.step, "train_seconds": self.train_seconds, "wall_seconds": self.wall_seconds,
                "model": self.model.state_dict(),
                "optimizers": {name: opt.state_dict() for name, opt in self.optimizers.items()},
                "strategy": strategies[0], "strategy_per_process": strategies if len(strategies) > 1 else None,
                "generator": self.generator.get_state(), "sampler": self.sampler.state_dict(),
                "appearance": self.compensation.state_dict() if self.compensation is not None else None,
                "poses": self.poses.state_dict() if self.poses is not None else None,
                "config": saved_config}


def start(config: TrainConfig, plan: Plan, scene: Scene, device: torch.device, team: Team,
          checkpoint: dict[str, Any] | None = None, progress: bool = False) -> tuple[TrainingState, str]:
    """(the state of step 0, or the one `checkpoint` holds; a note on where it came from), with the optimisers and
    the strategy of `plan`. Every process calls it; a fresh model is rank 0's on all of them."""
    check_fits(config.appearance, len(scene.train), device, config.appearance_grid_shape)  # before any work
    torch.manual_seed(config.seed)
    generator = torch.Generator(device=device).manual_seed(config.seed)
    sampler = ViewSampler(len(scene.train), config.seed)
    radius, pixels = scene.radius, scene.train_image_pixels
    white = tuple(background_of(config, scene)) == (1.0, 1.0, 1.0)
    if checkpoint is None:
        model, note = initial_model(config, scene, device, generator, progress)
        team.share_parameters(model)
        optimizers = make_optimizers(model, plan.optim, radius)
        strategy = make_strategy(config, plan, radius, generator, pixels, white)
        state = TrainingState(model, optimizers, strategy, generator, sampler)
    else:
        model = GaussianModel.from_state_dict(checkpoint["model"]).to(device)
        optimizers = make_optimizers(model, plan.optim, radius)
        for name, opt in optimizers.items():
            opt.load_state_dict(checkpoint["optimizers"][name])
        strategy = make_strategy(config, plan, radius, generator, pixels, white)
        strategy.load_state_dict((checkpoint.get("strategy_per_process") or [checkpoint["strategy"]])[team.rank])
        generator.set_state(checkpoint["generator"])
        sampler.load_state_dict(checkpoint["sampler"])
        state = TrainingState(model, optimizers, strategy, generator, sampler, step=checkpoint["step"],
                              train_seconds=checkpoint["train_seconds"],
                              wall_seconds=checkpoint.get("wall_seconds", checkpoint["train_seconds"]))
        note = f"resumed at step {state.step:,}"
    model.antialiased = config.antialiased
    state.compensation = _compensation(config, len(scene.train), device)
    if state.compensation is not None and checkpoint is not None:
        saved = checkpoint.get("appearance")
        if saved is None or saved.get("mode", "affine") != config.appearance:
            trained = "without it" if saved is None else f"with --appearance {saved.get('mode', 'affine')}"
            raise MCSplatError(f"--appearance {config.appearance}: the checkpoint was trained {trained}; resume "
                               "with the run's own --appearance, or train a new run")
        state.compensation.load_state_dict(saved)
    if config.pose_opt:
        state.poses = PoseRefinement(len(scene.train), radius, device, config.pose_opt_lr, config.pose_opt_reg)
        if checkpoint is not None:
            if checkpoint.get("poses") is None:
                raise MCSplatError("--pose-opt: the checkpoint was trained without it; resume without --pose-opt, "
                                   "or train a new run")
            state.poses.load_state_dict(checkpoint["poses"])
    strategy.collective = team.collective
    return state, note


def _compensation(config: TrainConfig, images: int, device: torch.device) -> Compensation | None:
    transforms = make_appearance(config.appearance, images, device, config.appearance_reg, config.appearance_grid_tv,
                                 config.appearance_grid_shape)
    if transforms is None:
        return None
    return Compensation(transforms, config.appearance_lr, config.appearance_lr_final)
