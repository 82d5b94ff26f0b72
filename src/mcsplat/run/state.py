"""What a training run carries from one step to the next, how it starts (fresh from the scene or restored from a
checkpoint) and what a checkpoint holds of it.

Restoring and continuing is exact on the CPU: the model, every Adam state, the strategy's statistics, the run's
generator and the view order are all in the checkpoint, so a resumed run takes bit for bit the steps an
uninterrupted one would have taken (same seed and thread count).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from ..config import TrainConfig, feature_groups
from ..data import Scene
from ..distributed import Team
from ..features import FeatureParts, FeatureStart, features_named
from ..gaussians import GaussianModel
from ..initialization import initial_model
from ..loss_terms import LossTerm, standard_terms
from ..optim import make_optimizers, portable_state_dict
from ..per_image import PerImageModule
from ..planning import Plan, make_strategy
from .scene import Background
from ..strategy import Strategy


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
    # Learned per training image with the scene (per_image.py): --appearance's colour transforms, --pose-opt's
    # pose corrections, each with its own Adam and its own entry in the checkpoint.
    modules: list[PerImageModule] = field(default_factory=list)
    loss_terms: list[LossTerm] = field(default_factory=list)  # what the step sums (loss_terms.py)

    def module(self, key: str) -> PerImageModule | None:
        """The module saved under `key` ("appearance", "poses"), if the run has it."""
        return next((module for module in self.modules if module.key == key), None)

    def checkpoint(self, saved_config: dict[str, Any], strategies: list[dict]) -> dict[str, Any]:
        """What checkpoint.pt holds; `saved_config` is config.json's content (the configuration and the plan it was
        trained with), `strategies` every process's strategy state (rank 0's first)."""
        return {"step": self.step, "train_seconds": self.train_seconds, "wall_seconds": self.wall_seconds,
                "model": self.model.state_dict(),
                "optimizers": {name: portable_state_dict(opt) for name, opt in self.optimizers.items()},
                "strategy": strategies[0], "strategy_per_process": strategies if len(strategies) > 1 else None,
                "generator": self.generator.get_state(), "sampler": self.sampler.state_dict(),
                **{module.key: module.state_dict() for module in self.modules}, "config": saved_config}


def start(config: TrainConfig, plan: Plan, scene: Scene, background: Background, device: torch.device, team: Team,
          checkpoint: dict[str, Any] | None = None, progress: bool = False) -> tuple[TrainingState, str]:
    """(the state of step 0, or the one `checkpoint` holds; a note on where it came from), with the optimisers and
    the strategy of `plan`, and what each feature of `config` adds (features.py). Every process calls it; a fresh
    model is rank 0's on all of them."""
    torch.manual_seed(config.seed)
    generator = torch.Generator(device=device).manual_seed(config.seed)
    sampler = ViewSampler(len(scene.train), config.seed)
    radius, pixels = scene.radius, scene.train_image_pixels
    white = tuple(background) == (1.0, 1.0, 1.0)
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
    parts = feature_parts(config, FeatureStart(scene, model, device, team.world_size))
    state.modules = parts.modules
    if checkpoint is not None:
        for module in state.modules:
            module.load_state_dict(checkpoint.get(module.key))  # refuses a checkpoint trained without it
    state.loss_terms = standard_terms(config.ssim_weight, strategy, state.modules) + parts.loss_terms
    strategy.collective = team.collective
    return state, note


def feature_facts(config: TrainConfig, modules: list[PerImageModule]) -> dict[str, Any]:
    """What the features of `config` add to metrics.json at the end of the run (their `facts`)."""
    return {key: value for group in features_named(feature_groups(config), "facts")
            for key, value in group.facts(modules).items()}


def feature_parts(config: TrainConfig, start: FeatureStart) -> FeatureParts:
    """What the features of `config` add to the run, in the order of their groups: the per-image modules in the
    order a step applies them and takes their Adam steps, the loss terms in the order they are summed."""
    parts = FeatureParts()
    for group in features_named(feature_groups(config), "setup"):
        added = group.setup(start)
        parts.modules += added.modules
        parts.loss_terms += added.loss_terms
    return parts
