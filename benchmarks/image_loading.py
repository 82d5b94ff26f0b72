"""Training speed and memory with images in RAM (the default when they fit) or decoded on demand (a small cache).

    .venv/bin/python benchmarks/image_loading.py                        # cup (800x600, 77 views), 300 steps
    .venv/bin/python benchmarks/image_loading.py --scene bird --steps 500
    PYTHONPATH=/tmp/head/src .venv/bin/python benchmarks/image_loading.py --modes resident   # an older checkout

Each mode runs `mcsplat.train.train` in a fresh subprocess (so that its peak memory is its own) and prints one JSON
line: seconds per step (train_seconds / steps, load excluded), load seconds, peak RSS. Modes: `resident` (default
cache: all images decoded at load), `lazy` (MCSPLAT_IMAGE_CACHE_MB=--cache-mb: decoded on demand, 2 views
prefetched in the background).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from typing import Literal

import tyro

from _common import DATA_ROOT, SFM_SCENES

CHILD = """
import json, resource, sys, time
from pathlib import Path
from mcsplat.config import TrainConfig
from mcsplat.data import load_scene
from mcsplat.train import train
scene_dir, out, steps = sys.argv[1], Path(sys.argv[2]), int(sys.argv[3])
start = time.perf_counter()
load_scene(scene_dir)
load_seconds = time.perf_counter() - start
metrics = train(TrainConfig(data=Path(scene_dir), out=out, steps=steps, quiet=True, save_every=0, lpips_net="alex",
                            threads=2))
print(json.dumps({"seconds_per_step": metrics["train_seconds"] / steps, "load_seconds": load_seconds,
                  "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "psnr": metrics["psnr"]}))
"""


@dataclass(frozen=True)
class Options:
    """Training speed and memory with images in RAM or decoded on demand."""

    scene: Literal["bird", "cup"] = "cup"
    """A real capture of the shared data."""
    steps: int = 300
    """Training steps of each mode."""
    modes: tuple[Literal["resident", "lazy"], ...] = ("resident", "lazy")
    """resident: all images decoded at load; lazy: decoded on demand through a small cache."""
    cache_mb: float = 16.0
    """The lazy mode's image cache (MCSPLAT_IMAGE_CACHE_MB)."""


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    scene = DATA_ROOT / SFM_SCENES[args.scene]
    for mode in args.modes:
        env = dict(os.environ)
        env.pop("MCSPLAT_IMAGE_CACHE_MB", None)
        if mode == "lazy":
            env["MCSPLAT_IMAGE_CACHE_MB"] = str(args.cache_mb)
        with tempfile.TemporaryDirectory() as tmp:
            result = subprocess.run([sys.executable, "-c", CHILD, str(scene), str(os.path.join(tmp, "run")),
                                     str(args.steps)], env=env, capture_output=True, text=True, check=True)
        record = {"scene": args.scene, "mode": mode, "steps": args.steps, **json.loads(result.stdout.splitlines()[-1])}
        if mode == "lazy":
            record["cache_mib"] = args.cache_mb
        print(json.dumps(record), flush=True)


if __name__ == "__main__":
    main()
