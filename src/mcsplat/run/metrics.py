"""metrics.json: what a run records of itself at its end, and the part of it `mcsplat eval` measures again. Its
layout is spelled here only (docs/architecture.md, "The run folder", lists its keys)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from .evaluation import Evaluation


@dataclass(frozen=True)
class RunFacts:
    """What only the training run knows at its end (`mcsplat eval` measures the scores and counts alone)."""

    exported_gaussians: int
    train_seconds: float
    wall_seconds: float
    device: str
    strategy: str
    sh_degree: int
    processes: int
    invisible_gaussians: dict[str, int]
    budget_seconds: float | None = None  # --budget
    # MCMC asking the scene (no --cap-max, or relocation alive): (where growth stopped or None, the most allowed)
    auto_cap: tuple[int | None, int] | None = None
    features: dict[str, Any] = field(default_factory=dict)  # what the run's features add (features.py: facts())


def metrics(evaluation: Evaluation | None, lpips_net: str, steps: int, num_gaussians: int,
            run: RunFacts | None = None) -> dict[str, Any]:
    """metrics.json's content: the scores of `evaluation` (None: the scene has no test views, so no scores) and the
    counts they were measured with; with `run`, the whole record of a finished training run, else the part `mcsplat
    eval` replaces."""
    scores = _scores(evaluation)
    record = {**{key: scores[key] for key in ("psnr", "ssim", "lpips")}, "lpips_net": lpips_net,
              "num_gaussians": num_gaussians}
    if run is None:
        return {**record, "steps": steps, "test_views": scores["test_views"], **scores["masked"],
                **scores["compensated"], "per_view_psnr": scores["per_view_psnr"]}
    return {**record, "exported_gaussians": run.exported_gaussians, "steps": steps,
            "train_seconds": round(run.train_seconds, 2), "device": run.device, "strategy": run.strategy,
            "test_views": scores["test_views"], "sh_degree": run.sh_degree, "processes": run.processes,
            "wall_seconds": round(run.wall_seconds, 2),
            **({"budget_seconds": run.budget_seconds} if run.budget_seconds is not None else {}),
            "invisible_gaussians": run.invisible_gaussians,
            # Where growth stopped as the scene asked for no more (None: it asked to the end, the ceiling decided)
            **({"auto_cap": run.auto_cap[0], "auto_cap_ceiling": run.auto_cap[1]} if run.auto_cap else {}),
            **scores["masked"], **scores["compensated"],
            **run.features,
            "per_view_psnr": scores["per_view_psnr"]}


def _scores(evaluation: Evaluation | None) -> dict[str, Any]:
    """What metrics.json records of an evaluation: None scores and no views when there was none."""
    if evaluation is None:
        return {"psnr": None, "ssim": None, "lpips": None, "test_views": 0, "masked": {}, "compensated": {},
                "per_view_psnr": {}}
    return {"psnr": evaluation.psnr, "ssim": evaluation.ssim, "lpips": evaluation.lpips, "test_views": evaluation.views,
            "masked": evaluation.masked(), "compensated": evaluation.compensated(),
            "per_view_psnr": evaluation.per_view_psnr}
