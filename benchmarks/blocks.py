"""A shared capture trained as one run and as 2 and 4 blocks merged (`mcsplat blocks`): test PSNR of the merged
model against the one run at the same total cap and the same steps per block, peak memory of each process, wall
clock with 2 processes on this machine, and a picture of a test view across the blocks' borders.

    .venv/bin/python benchmarks/blocks.py                                   # the cup at half size, 3,000 steps
    .venv/bin/python benchmarks/blocks.py --scene bird --downscale 4 --steps 5000 --cap 200000 --blocks 2 4

The one run trains with all the cores (`mcsplat train`). The blocks train as a job array would run them, two jobs
at a time, one thread each (`mcsplat blocks train OUT --block I`), then `mcsplat blocks merge`. Each process's peak
resident memory comes from the kernel (wait4's maxrss). Columns:

    psnr / ssim      the merged model (or the one run) on all the scene's test views
    gaussians        in the merged model (the blocks' own, inside their cells) or the one run
    caps             each block's cap (its region's share of the total: the margins overlap)
    peak_mib         the largest peak resident memory of the processes (for blocks: of any block's run)
    wall_s           from the first process started to the merged model written

Writes results/blocks/results.{jsonl,md} and results/blocks/<scene>-view.png (one test view: the photo, the one
run, each merged model, with the borders of the blocks' cells drawn where the ground crosses the view).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import tyro

import _common as C


@dataclass(frozen=True)
class Options:
    """A capture as one run and as blocks merged."""

    run: Annotated[C.BlockRuns, tyro.conf.OmitArgPrefixes] = C.BlockRuns(downscale=2, steps=3000, cap=100_000)
    blocks: tuple[int, ...] = (2, 4)
    """Numbers of blocks, each plan trained and merged."""
    keep: Path | None = None
    """Train into this folder and keep it (default: a temporary one)."""


def command(*args: str) -> list[str]:
    return [sys.executable, "-m", "mcsplat.cli", *args]


def run_all(commands: list[list[str]], at_once: int) -> list[int]:
    """Run the commands, `at_once` at a time; the peak resident bytes of each."""
    env = dict(os.environ, PYTHONPATH=str(C.REPO / "src"))
    peaks, waiting, running = [0] * len(commands), list(enumerate(commands)), {}
    while waiting or running:
        while waiting and len(running) < at_once:
            index, args = waiting.pop(0)
            running[subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE).pid] = \
                (index, args)
        pid, status, usage = os.wait4(-1, 0)
        index, args = running.pop(pid)
        if os.waitstatus_to_exitcode(status) != 0:
            sys.exit(f"failed: {' '.join(args)}")
        peaks[index] = usage.ru_maxrss * 1024
    return peaks


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    runs = args.run
    scene = C.scene_path(runs.scene)
    options = ["--downscale", str(runs.downscale), "--steps", str(runs.steps), "--cap-max", str(runs.cap),
               "--save-every", "0", "--quiet", "--lpips-net", "alex"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        start = time.perf_counter()
        [peak] = run_all([command("train", str(scene), "--out", str(root / "one"), *options)], 1)
        one = json.loads((root / "one" / "metrics.json").read_text())
        rows.append({"scene": runs.scene, "run": "one run", "psnr": one["psnr"], "ssim": one["ssim"],
                     "gaussians": one["num_gaussians"], "caps": f"{runs.cap:,}", "peak_mib": peak / 2**20,
                     "wall_s": time.perf_counter() - start})
        C.emit(rows[-1])
        for count in args.blocks:
            out = root / f"blocks{count}"
            start = time.perf_counter()
            run_all([command("blocks", "plan", str(scene), "--out", str(out), "--count", str(count), *options)], 1)
            plan = json.loads((out / "blocks.json").read_text())
            peaks = run_all([command("blocks", "train", str(out), "--block", str(i), "--threads", "1", "--quiet")
                             for i in range(count)], 2)
            run_all([command("blocks", "merge", str(out), "--quiet")], 1)
            merged = json.loads((out / "merged" / "metrics.json").read_text())
            rows.append({"scene": runs.scene, "run": f"{count} blocks", "psnr": merged["psnr"], "ssim": merged["ssim"],
                         "gaussians": merged["num_gaussians"],
                         "caps": " + ".join(f"{block['cap']:,}" for block in plan["blocks"]),
                         "peak_mib": max(peaks) / 2**20, "wall_s": time.perf_counter() - start})
            C.emit(rows[-1])
        folder = C.results_dir("blocks")
        picture(root, args, folder / f"{runs.scene}-view.png")
    for row in rows:
        row["psnr_vs_one"] = row["psnr"] - rows[0]["psnr"]
    C.write_text(folder / "results.jsonl", "".join(json.dumps(row) + "\n" for row in rows))
    columns = [("scene", "scene", ""), ("run", "run", ""), ("test PSNR", "psnr", ".2f"),
               ("vs one run", "psnr_vs_one", "+.2f"), ("SSIM", "ssim", ".4f"), ("Gaussians", "gaussians", ","),
               ("caps", "caps", ""), ("peak MiB a process", "peak_mib", ".0f"), ("wall s", "wall_s", ".0f")]
    C.write_results_page(folder, f"Blocks against one run ({runs.scene}, downscale {runs.downscale}, {runs.steps:,} "
                         f"steps a run, cap {runs.cap:,} in all)", "blocks.py", rows, columns)


def picture(root: Path, args, path: Path) -> None:
    """One test view: the photo, the one run and each merged model, the cells' borders drawn on the ground."""
    from mcsplat.data.images import uint8_pixels
    from mcsplat.run.evaluation import save_pixels
    from mcsplat.partition import read_plan
    from mcsplat.render import render
    from mcsplat.run.trained import load

    device = torch.device("cpu")
    one = load(root / "one", device)
    view = one.scene.test[len(one.scene.test) // 2]
    panels = [uint8_pixels(view.image_float())]
    for name in ["one", *(f"blocks{count}/merged" for count in args.blocks)]:
        run = load(root / name, device)
        result = render(run.model, view.camera, run.background, sh_degree=run.sh_degree)
        image = uint8_pixels(result.rgb)
        if name != "one":
            image = with_borders(image, read_plan(root / name.split("/")[0] / "blocks.json"), result, view)
        panels.append(image)
    save_pixels(path, np.concatenate(panels, axis=1))


def with_borders(image: np.ndarray, plan, result, view) -> np.ndarray:
    """The image with each pixel whose ray meets the scene (the render `result`'s depth) on a cell border in red."""
    depth, alpha = result.depth, result.alpha
    camera = view.camera
    height, width = depth.shape
    v, u = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    rays = torch.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, torch.ones_like(u)], dim=-1)
    local = rays * (depth / alpha.clamp(min=1e-6))[..., None]
    w2c = camera.world_to_camera
    world = (local.reshape(-1, 3) - w2c[:3, 3]) @ w2c[:3, :3]
    owner = torch.zeros(world.shape[0], dtype=torch.long)
    where = plan.ground.coordinates(world)
    for block in plan.blocks:
        owner[block.core.contains(where)] = block.index
    owner = owner.reshape(height, width)
    edge = torch.zeros_like(owner, dtype=torch.bool)
    edge[:, 1:] |= owner[:, 1:] != owner[:, :-1]
    edge[1:, :] |= owner[1:, :] != owner[:-1, :]
    edge &= alpha > 0.5
    marked = image.copy()
    marked[edge.numpy()] = (255, 0, 0)
    return marked


if __name__ == "__main__":
    main()
