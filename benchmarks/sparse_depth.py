"""What `--sparse-depth` costs the picture and gives the depth, over several seeds: the cup and the bird, each seed
trained without it and with it on each schedule asked for.

    .venv/bin/python benchmarks/sparse_depth.py                                  # cup and bird, seeds 0-3, 3 arms
    .venv/bin/python benchmarks/sparse_depth.py --seeds 0 1 2 3 4 5 --arms off half-way
    .venv/bin/python benchmarks/sparse_depth.py --report                         # results.md from the records

Every run trains `mcsplat train CAPTURE --downscale 4 --steps 2000 --cap-max 30000 --seed S` (about a minute each
on a 2-core CPU) with one arm's options:

    off              no sparse depth
    half-way         --sparse-depth 0.1 --sparse-depth-from 0.5 --sparse-depth-final 1 (from half the run, held)
    first-step       the same from the first step (--sparse-depth-from 0)
    fade-out         from half the run, falling to 0 at the last step (--sparse-depth-final 0: the default)
    light            half-way at a weight of 0.03

Recorded per run: the test PSNR, and the depth error: over the test views, the rendered expected depth at the SfM
points each test image saw (where the render's alpha is at least 0.5), its median relative error against the
points' depths. Those points are seen by training views too, so the error says the geometry holds, not that it
generalises.

A seed's runs start alike: sparse depth from half way leaves the first half of a run as the run without it, so the
arms of one seed differ only by what the term did. Where seeds move a capture's PSNR far (the bird's spread 2.7 dB
over eight seeds), the difference at one seed is much finer (its standard deviation 0.3-0.4 dB); the cup's seeds
spread little, and there pairing gains nothing. The summary gives, for each arm, the mean over seeds of its PSNR
minus the same seed's run without sparse depth, with the standard error of that mean.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tyro

import _common as C
from framework import Arm, Common

SCENES = {"cup": "colmap_cup", "bird": "colmap_bird"}
# Each schedule in full, so that an arm means the same whatever the defaults are.
HALF_WAY = {"sparse_depth": 0.1, "sparse_depth_from": 0.5, "sparse_depth_final": 1.0}
ARMS = {"off": {}, "half-way": HALF_WAY, "first-step": {**HALF_WAY, "sparse_depth_from": 0.0},
        "fade-out": {**HALF_WAY, "sparse_depth_final": 0.0}, "light": {**HALF_WAY, "sparse_depth": 0.03}}
DEFAULT_ARMS = ("off", "half-way", "fade-out")
STEPS, DOWNSCALE, CAP = 2000, 4, 30_000
KEY = ("scene", "arm", "seed", "steps")


@dataclass(frozen=True)
class Options:
    """--sparse-depth against the same seeds without it."""

    scenes: tuple[Literal[tuple(SCENES)], ...] = tuple(SCENES)
    arms: tuple[Literal[tuple(ARMS)], ...] = DEFAULT_ARMS
    seeds: tuple[int, ...] = (0, 1, 2, 3)
    steps: int = STEPS
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def arms(options: Options) -> list[Arm]:
    return [Arm(f"{scene}-{arm}-seed{seed}-{options.steps}",
                {"scene": scene, "arm": arm, "seed": seed, "steps": options.steps},
                {"steps": options.steps, "downscale": DOWNSCALE, "cap_max": CAP, "seed": seed, **ARMS[arm]})
            for scene in options.scenes for seed in options.seeds for arm in options.arms]


def run(arm: Arm, options: Options, folder: Path) -> dict:
    from mcsplat.train import train

    data = options.common.data_root / SCENES[arm.labels["scene"]]
    out = folder / "runs" / arm.name
    config = C.make_config(data=data, out=out, overwrite=True, quiet=True, save_renders=False, save_every=0,
                           threads=options.common.threads, **arm.config)
    metrics = train(config)
    return {"psnr": metrics["psnr"], "ssim": metrics["ssim"], "num_gaussians": metrics["num_gaussians"],
            "train_seconds": metrics["train_seconds"], "depth_error": depth_error(out, data)}


def depth_error(run: Path, data: Path) -> float:
    """The median relative error of the run's expected depth at the SfM points its test images saw."""
    import torch

    from mcsplat.data.sfm_tracks import points_seen
    from mcsplat.depth_supervision.terms import MIN_ALPHA, project, sample_depth
    from mcsplat.render import render
    from mcsplat.run.scene import scene_of
    from mcsplat.run.trained import load

    trained = load(run, torch.device("cpu"))
    scene = scene_of(trained.config)
    seen = points_seen(data)
    errors = []
    with torch.no_grad():
        for view in scene.test:
            if view.name not in seen:
                continue
            points = torch.as_tensor(seen[view.name], dtype=torch.float32)
            u, v, z = project(points, view.camera)
            out = render(trained.model, view.camera, None, trained.sh_degree)
            depth, alpha = sample_depth(out.depth, out.alpha, u, v)
            covered = alpha >= MIN_ALPHA  # where the loss term reads the render's depth
            errors.append(((depth - z).abs() / z)[covered].numpy())
    values = np.concatenate(errors) if errors else np.array([])
    return float(np.median(values)) if values.size else float("nan")


def report(records: list[dict], folder: Path) -> str:
    columns = [("scene", "scene", ""), ("arm", "arm", ""), ("seed", "seed", ""), ("test PSNR", "psnr", ".2f"),
               ("PSNR - off, same seed", "psnr_minus_off", "+.2f"),
               ("depth error at the test views' SfM points", "depth_error_percent", ".1f"),
               ("Gaussians", "num_gaussians", ","), ("training s", "train_seconds", ".0f")]
    off = {(r["scene"], r["seed"], r["steps"]): r["psnr"] for r in records if r["arm"] == "off"}
    rows = []
    for record in sorted(records, key=lambda r: (r["scene"], list(ARMS).index(r["arm"]), r["seed"])):
        baseline = None if record["arm"] == "off" else off.get((record["scene"], record["seed"], record["steps"]))
        rows.append({**record, "depth_error_percent": 100 * record["depth_error"],
                     "psnr_minus_off": None if baseline is None else record["psnr"] - baseline})
    page = C.results_page("Sparse depth: test PSNR and depth error over seeds, against the same seeds without it",
                          "sparse_depth.py", rows, columns)
    return page + "\n" + summary(rows) + "\n"


def summary(rows: list[dict]) -> str:
    """Per scene, steps and arm: mean PSNR, mean change against the same seeds' runs without sparse depth (its
    standard error, over the seeds that have both), and the median depth error."""
    lines = ["| scene | steps | arm | runs | mean test PSNR | mean change against off (standard error) | "
             "median depth error |", "|---|---|---|---|---|---|---|"]
    for scene, steps, arm in [(scene, steps, arm) for scene in SCENES for steps in sorted({r["steps"] for r in rows})
                              for arm in ARMS]:
        mine = [r for r in rows if (r["scene"], r["steps"], r["arm"]) == (scene, steps, arm)]
        if mine:
            changes = [r["psnr_minus_off"] for r in mine if r["psnr_minus_off"] is not None]
            change = "-"
            if changes:
                spread = np.std(changes, ddof=1) / math.sqrt(len(changes)) if len(changes) > 1 else float("nan")
                change = f"{np.mean(changes):+.2f} dB ({spread:.2f}, {len(changes)} seeds)"
            lines.append(f"| {scene} | {steps:,} | {arm} | {len(mine)} | {np.mean([r['psnr'] for r in mine]):.2f} | "
                         f"{change} | {100 * np.median([r['depth_error'] for r in mine]):.1f}% |")
    return "\n".join(lines)


if __name__ == "__main__":
    import framework
    sys.exit(framework.script("sparse_depth"))
