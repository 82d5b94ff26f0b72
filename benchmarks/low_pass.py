"""3DGS's 2D low-pass filter at 0.3 pixel^2 (render's `eps2d`) against a smaller one, same run otherwise.

    .venv/bin/python benchmarks/low_pass.py                              # cup, bird, fern, lego; 0.3 and 0.1
    .venv/bin/python benchmarks/low_pass.py --scenes cup --values 0.3 0.1 0.03

Every renderer call adds `eps2d` to each Gaussian's 2D covariance (project.py), widening every footprint: 3DGS's
cheap anti-aliasing, and what gsplat and the paper's code use. There is no option for it (a model is drawn with the
filter it was trained with, by the viewer and every export too), so each run happens in a child process whose
render() default is set before training, for its evaluation as well. Each scene trains 2,000 steps at half size with
cap 100k (the captures from their SfM points, lego from its random points); printed: test PSNR / SSIM / LPIPS per
value, and the difference to the first value. Results to results/low_pass/.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro

import _common as C

Scene = Literal["cup", "bird", "fern", "lego"]
SCENES: dict[Scene, str] = {"cup": "colmap_cup", "bird": "colmap_bird", "fern": "llff_fern/fern", "lego": C.LEGO}
STEPS = "2000"
# The table of results.md: one row per run.
COLUMNS = [("scene", "scene", ""), ("eps2d", "eps2d", ".2f"), ("test PSNR", "psnr", ".2f"), ("SSIM", "ssim", ".4f"),
           ("LPIPS-alex", "lpips", ".4f"), ("PSNR - first value", "psnr_minus_first", "+.2f")]

CHILD = """
import sys
import mcsplat.render as render
render.render.__kwdefaults__["eps2d"] = float(sys.argv[1])
from mcsplat.cli import main
sys.exit(main(sys.argv[2:]))
"""


@dataclass(frozen=True)
class Options:
    """3DGS's 2D low-pass filter at 0.3 pixel^2 against smaller ones."""

    scenes: tuple[Scene, ...] = tuple(SCENES)
    """Scenes of the shared data."""
    values: tuple[float, ...] = (0.3, 0.1)
    """Values of eps2d; the first is the baseline."""
    data_root: Path = C.DATA_ROOT
    """The shared data folder."""


def train(scene: Path, value: float, run: Path) -> dict:
    """One run with render's default eps2d set to `value`; its metrics.json."""
    if not (run / "metrics.json").exists():
        arguments = ["train", str(scene), "--out", str(run), "--overwrite", "--downscale", "2", "--steps", STEPS,
                     "--cap-max", "100000", "--quiet", "--save-every", "0", "--lpips-net", "alex",
                     "--no-save-renders"]
        done = subprocess.run([sys.executable, "-c", CHILD, repr(value), *arguments], capture_output=True, text=True,
                              env=dict(os.environ, PYTHONPATH=str(C.REPO / "src")))
        if done.returncode != 0:
            sys.exit(f"low_pass.py: training {scene} with eps2d {value} failed: {done.stderr.strip()[-500:]}")
    return json.loads((run / "metrics.json").read_text())


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    out = C.results_dir("low_pass")
    records = []
    for name in args.scenes:
        scene = Path(args.data_root) / SCENES[name]
        baseline = None
        for value in args.values:
            metrics = train(scene, value, out / "runs" / f"{name}-{value}")
            baseline = baseline if baseline is not None else metrics["psnr"]
            record = {"scene": name, "eps2d": value, "steps": int(STEPS), "psnr": metrics["psnr"],
                      "ssim": metrics["ssim"], "lpips": metrics.get("lpips"), "num_gaussians": metrics["num_gaussians"],
                      "psnr_minus_first": metrics["psnr"] - baseline, "commit": C.git_commit(),
                      "date": C.timestamp()}
            C.emit(record)
            records.append(record)
    C.write_results(out, records, C.markdown_table(records, COLUMNS) + "\n", show=True)


if __name__ == "__main__":
    main()
