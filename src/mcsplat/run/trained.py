"""A trained run read back from its folder: what eval, render, export, view and report need of it (`load`)."""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from pathlib import Path

import torch

from ..config import TrainConfig
from ..data import Scene
from ..gaussians import GaussianModel
from ..planning import Plan
from .folder import RunDir
from .scene import Background, background_of, scene_of


@dataclass
class TrainedRun:
    """A finished (or stopped) run, read back from its folder: what eval, render, export, view and report need."""

    folder: RunDir
    config: TrainConfig
    plan: Plan
    model: GaussianModel
    step: int  # steps done
    device: torch.device

    @property
    def sh_degree(self) -> int:
        """The SH degree the model was last trained with."""
        return self.plan.final_sh_degree(self.step)

    @functools.cached_property
    def scene(self) -> Scene:
        """The run's scene, loaded on first use (MCSplatError when its folder is gone or changed); a block's run
        finds its plan from where its folder is now."""
        return scene_of(dataclasses.replace(self.config, out=self.folder.path))

    @property
    def background(self) -> Background:
        return background_of(self.config, self.scene)


def load(path: str | Path, device: torch.device) -> TrainedRun:
    """The run in `path`: its configuration and the model of its checkpoint, on `device`."""
    folder = RunDir(path)
    config, plan = folder.read_plan()
    state = folder.read_checkpoint()
    model = GaussianModel.from_state_dict(state["model"]).to(device)
    model.antialiased = config.antialiased
    return TrainedRun(folder=folder, config=config, plan=plan, model=model, step=int(state["step"]), device=device)
