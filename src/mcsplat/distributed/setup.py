"""What every process of one run must agree on before it trains (team.check_same_setup compares them)."""

from __future__ import annotations

from typing import Any

import torch

from .. import __version__
from ..config import TrainConfig, resume_policy, to_jsonable
from ..data import Scene


def setup_of(config: TrainConfig) -> dict[str, Any]:
    """The options (not the per-process ones, nor the data path, which may differ between machines, but those that
    decide when the processes talk) and the versions that compute the steps."""
    options = {key: value for key, value in to_jsonable(config).items()
               if resume_policy(key) != "process" and key not in ("data", "out")}
    return {**options, "eval_every": config.eval_every, "save_every": config.save_every, "device": config.device,
            "mcsplat": __version__, "torch": torch.__version__}


def scene_summary(scene: Scene) -> dict[str, Any]:
    """Enough of the loaded scene to tell two copies of one scene from two scenes."""
    return {"scene views": [(v.name, v.camera.width, v.camera.height) for v in scene.train + scene.test],
            "scene radius": round(float(scene.radius), 6)}
