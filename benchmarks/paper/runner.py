"""Train one run of experiments.py and record its figures (records.jsonl: one line per finished run, the last
line of a name wins)."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import torch

import _common as C
import framework
from _common import test_subset
from framework import NotReady  # noqa: F401  (the runs' NotReady is the framework's)
import mcsplat.run.folder as run_folders
from mcsplat.config import ModelConfig, TrainConfig, config_of
from mcsplat.planning import settings_of
from mcsplat.strategy.adc import ADCConfig
from mcsplat.strategy.mcmc import MCMCConfig
from mcsplat.train import train

from .experiments import Run, Scale

NESTED = {"model": ModelConfig, "mcmc": MCMCConfig, "adc": ADCConfig}


class Records(framework.Records):
    """records.jsonl of a scale: the last record of every run name."""

    def __init__(self, folder: Path) -> None:
        super().__init__(folder / "records.jsonl")

    @property
    def by_name(self) -> dict[str, dict]:
        return {name: record for (name,), record in self.by_key.items()}


def resolve_cap(run: Run, records: Records) -> int | None:
    """The run's cap: a number, or the final count of the run it names (of the same seed where that has run)."""
    if not isinstance(run.cap, str):
        return run.cap
    name = run.cap.removeprefix("count:")
    reference = records.get(f"{name}-seed{run.seed}" if run.seed else name) or records.get(name)
    if reference is None:
        raise NotReady(f"its cap is the final count of {name}, which has not run (leave it in --only)")
    return int(reference["num_gaussians"])


def check_options(run: Run) -> None:
    """Every option of the run is one this checkout's configuration has."""
    known = {"": {f.name for f in dataclasses.fields(TrainConfig)},
             **{group: {f.name for f in dataclasses.fields(cls)} for group, cls in NESTED.items()}}
    for option, _ in run.options:
        group, _, key = option.rpartition(".")
        if key not in known.get(group, ()):
            raise NotReady(f"this checkout has no option {option}")


def make_config(run: Run, scale: Scale, cap: int | None, run_dir: Path, resume: bool) -> TrainConfig:
    setting = scale.scenes[run.scene]
    nested: dict[str, dict[str, Any]] = {key: {} for key in NESTED}
    top: dict[str, Any] = {}
    for option, value in run.options:
        group, _, key = option.rpartition(".")
        (nested[group] if group else top)[key] = value
    nested["model"].setdefault("init", "random" if run.init == "random" else "auto")
    nested["mcmc"].setdefault("relocation", "paper")  # the paper's method: its relocation and growth to the cap
    nested["model"].setdefault("num_init_points", scale.random_points)
    steps = top.pop("steps", scale.steps)
    return config_of(
        data=C.DATA_ROOT / setting.folder, out=run_dir, strategy=run.strategy, cap_max=cap, steps=steps,
        downscale=setting.downscale, seed=run.seed, quiet=True, lpips_net="vgg", save_renders=False,
        save_every=max(1, steps // 4), save_every_minutes=0, resume=resume, overwrite=not resume,
        **top, **{key: cls(**nested[key]) for key, cls in NESTED.items()})


def train_run(run: Run, scale: Scale, folder: Path, records: Records, machine: dict) -> dict:
    """Train `run` (resuming a checkpoint left by an interrupted one) and record it."""
    check_options(run)
    run_dir = folder / "runs" / run.name
    cap = resolve_cap(run, records)
    resume = run_folders.RunDir(run_dir).checkpoint_file.is_file() and not (run_dir / "metrics.json").is_file()
    config = make_config(run, scale, cap, run_dir, resume)
    started = time.perf_counter()
    with test_subset(scale.scenes[run.scene].test_stride, 0):
        metrics = train(config)
    record = {
        "name": run.name, "base_name": run.base_name, "scene": run.scene, "strategy": run.strategy,
        "init": run.init, "variant": run.variant, "seed": run.seed, "cap": cap,
        "options": {key: value for key, value in run.options},
        "psnr": round(metrics["psnr"], 3), "ssim": round(metrics["ssim"], 4),
        "lpips": round(metrics["lpips"], 4) if metrics.get("lpips") is not None else None,
        "num_gaussians": metrics["num_gaussians"], "steps": metrics["steps"],
        "train_seconds": metrics["train_seconds"],
        "ms_per_step": round(1000.0 * metrics["train_seconds"] / max(1, metrics["steps"]), 1),
        "test_views": metrics.get("test_views"), "size": scale.scenes[run.scene].size, "scale": scale.name,
        "device": metrics.get("device"), "threads": torch.get_num_threads(), "resumed": resume,
        "wall_seconds": round(time.perf_counter() - started, 1), "machine": machine, "commit": C.git_commit(),
        "date": C.timestamp(), **churn(run_dir),
    }
    records.add(record)
    return record


def churn(run_dir: Path) -> dict:
    """How often MCMC moved its Gaussians: the relocations of the whole run (log.jsonl sums them between its lines),
    per Gaussian of the final count, and the share of the Gaussians found dead at a refine step once the count had
    reached its cap (each dead one is relocated, so relocations / (refine steps x count) over those lines)."""
    lines = [line for line in C.read_jsonl(run_dir / "log.jsonl") if "num_gaussians" in line]
    relocated = sum(int(line.get("relocated") or 0) for line in lines)
    count = lines[-1]["num_gaussians"] if lines else 0
    config = run_dir / "config.json"
    mcmc = settings_of(json.loads(config.read_text())).get("mcmc") if config.is_file() else None  # the plan's
    moved = slots = 0
    for before, line in zip(lines, lines[1:] if mcmc else ()):
        if before["num_gaussians"] != count:  # still growing: relocations there are not a share of the cap
            continue
        refines = sum(1 for step in range(before["step"] + 1, line["step"] + 1)
                      if mcmc["refine_start"] < step < mcmc["refine_stop"] and step % mcmc["refine_every"] == 0)
        moved, slots = moved + int(line.get("relocated") or 0), slots + refines * count
    return {"relocated_total": relocated, "relocated_per_gaussian": round(relocated / count, 2) if count else None,
            "dead_per_refine": round(moved / slots, 4) if slots else None}


def short(record: dict) -> str:
    return json.dumps({k: record[k] for k in ("name", "cap", "psnr", "ssim", "lpips", "num_gaussians",
                                              "train_seconds")})
