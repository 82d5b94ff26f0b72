"""What a training process holds at its peak, against its cap and its image size: the figures behind the memory
estimate of a block plan (src/mcsplat/partition/memory.py).

    .venv/bin/python benchmarks/block_memory.py                 # the cup; caps 20k and 150k; downscale 1 and 4
    .venv/bin/python benchmarks/block_memory.py --caps 20000 300000 --downscales 2 8 --steps 400

Each configuration is one `mcsplat train` process (default options otherwise: the final evaluation with LPIPS
included), its cap reached by MCMC's growth well before the end. Its peak resident memory comes from the kernel
(wait4's maxrss). Then a least-squares fit of

    peak = fixed + per_gaussian * cap + per_pixel * pixels of a training image

over all configurations. Prints one JSON line per run and the fit; writes results/block_memory/results.{jsonl,md}.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro

import _common as C


@dataclass(frozen=True)
class Options:
    """Peak memory of training processes against their cap and image size."""

    scene: str = "cup"
    """cup, bird, lego (under the shared data folder) or a scene folder."""
    caps: tuple[int, ...] = (20_000, 150_000)
    """--cap-max of the runs."""
    downscales: tuple[int, ...] = (1, 4)
    """Image downscale factors of the runs (each with every cap)."""
    steps: int = 400
    """Training steps of each run."""


def peak_of_run(scene: Path, cap: int, downscale: int, steps: int, out: Path) -> int:
    """Peak resident bytes of one training process."""
    command = [sys.executable, "-m", "mcsplat.cli", "train", str(scene), "--out", str(out), "--cap-max", str(cap),
               "--downscale", str(downscale), "--steps", str(steps), "--save-every", "0", "--quiet",
               "--no-save-renders"]
    env = dict(os.environ, PYTHONPATH=str(C.REPO / "src"))
    process = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    if process.returncode != 0:
        sys.exit(f"training failed: {process.stderr.read().decode()[-2000:]}")
    return usage.ru_maxrss * 1024  # kilobytes on Linux


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    scene = C.scene_path(args.scene)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for downscale in args.downscales:
            loaded = C.load(scene, downscale)
            pixels = max(view.camera.width * view.camera.height for view in loaded.train)
            for cap in args.caps:
                out = Path(tmp) / f"run-{downscale}-{cap}"
                peak = peak_of_run(scene, cap, downscale, args.steps, out)
                gaussians = json.loads((out / "metrics.json").read_text())["num_gaussians"]
                row = {"scene": args.scene, "downscale": downscale, "pixels": pixels, "cap": cap,
                       "gaussians": gaussians, "peak_mib": round(peak / 2**20, 1)}
                C.emit(row)
                rows.append(row)
    design = torch.tensor([[1.0, row["gaussians"], row["pixels"]] for row in rows], dtype=torch.float64)
    peaks = torch.tensor([row["peak_mib"] * 2**20 for row in rows], dtype=torch.float64)
    fixed, per_gaussian, per_pixel = torch.linalg.lstsq(design, peaks[:, None]).solution[:, 0].tolist()
    fit = {"fixed_mib": round(fixed / 2**20), "bytes_per_gaussian": round(per_gaussian),
           "bytes_per_pixel": round(per_pixel)}
    C.emit({"fit": fit})
    folder = C.results_dir("block_memory")
    C.write_text(folder / "results.jsonl", "".join(json.dumps(row) + "\n" for row in [*rows, {"fit": fit}]))
    columns = [("scene", "scene", ""), ("downscale", "downscale", ""), ("pixels", "pixels", ","),
               ("cap", "cap", ","), ("Gaussians at the end", "gaussians", ","), ("peak MiB", "peak_mib", ".0f")]
    C.write_results_page(folder, "Peak memory of a training process", "block_memory.py", rows, columns)
    with open(folder / "results.md", "a") as page:
        page.write(f"\nFit: {fit['fixed_mib']} MiB + {fit['bytes_per_gaussian']:,} bytes a Gaussian + "
                   f"{fit['bytes_per_pixel']:,} bytes a pixel.\n")


if __name__ == "__main__":
    main()
