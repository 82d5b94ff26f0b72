"""What a report shows of a run, read from its directory: config.json, metrics.json, log.jsonl and the final
Gaussians' opacities and scales from checkpoint.pt. Nothing here trains or renders."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..errors import MCSplatError
from ..gaussians import DEAD_OPACITY
from ..planning import settings_of
from ..run.folder import RunDir


@dataclass
class RunRecord:
    path: Path
    name: str
    config: dict  # config.json's settings, each the value the run trained with (its plan's: settings_of)
    metrics: dict
    log: list[dict]
    opacities: np.ndarray  # of the final Gaussians
    max_scales: np.ndarray  # largest standard deviation of each final Gaussian
    per_view_psnr: dict[str, float] = field(default_factory=dict)

    def series(self, key: str) -> tuple[np.ndarray, np.ndarray]:
        """(steps, values) of the log records that have `key`."""
        rows = [(r["step"], r[key]) for r in self.log if key in r]
        return (np.array([s for s, _ in rows]), np.array([v for _, v in rows], dtype=float)) if rows \
            else (np.zeros(0), np.zeros(0))

    @property
    def dead_fraction(self) -> float:
        return float((self.opacities <= DEAD_OPACITY).mean()) if self.opacities.size else 0.0


def read_log(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    records = []
    for line in path.read_text().splitlines():
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:  # a run killed mid-write leaves a partial last line
            continue
    return records


def load_run(path: Path) -> RunRecord:
    run = RunDir(path)
    if not run.config_file.is_file() or not run.checkpoint_file.is_file():
        raise MCSplatError(f"{run.path}: not a run directory (needs {run.config_file.name} and "
                           f"{run.checkpoint_file.name}); train one with `mcsplat train DATA --out {run.path}`")
    metrics = run.read_metrics()
    model = run.read_checkpoint()["model"]  # GaussianModel.state_dict(): "params.<name>"
    opacities = torch.sigmoid(model["params.opacity_logits"].float()).numpy()
    max_scales = torch.exp(model["params.log_scales"].float().max(dim=1).values).numpy()
    saved = json.loads(run.config_file.read_text())
    try:
        settings = settings_of(saved)
    except MCSplatError:  # edited by hand, or another version's: the report shows what it can read as it is
        settings = saved
    return RunRecord(path=run.path, name=run.path.resolve().name, config=settings, metrics=metrics,
                     log=read_log(run.log_file), opacities=opacities, max_scales=max_scales,
                     per_view_psnr=metrics.get("per_view_psnr", {}))
