"""The splats' own depth at the SfM points: before any mesh, how far each run's median depth lies from the points
COLMAP triangulated, in the training views that see them. It tells a mesh that is far from the points because its
depth maps are (the model's doing) from one the fusion moved (the mesh export's doing).

    .venv/bin/python benchmarks/sfm_depth.py                              # mesh_quality.py's cup and bird runs
    .venv/bin/python benchmarks/sfm_depth.py --runs RUN [RUN ...]         # other runs of a COLMAP scene
    .venv/bin/python benchmarks/sfm_depth.py --report                     # rebuild results from the records

For every 4th training view, each SfM point in front of the camera and inside the image is projected to its pixel;
where the splats cover the pixel (alpha >= 0.5) the signed difference between the rendered median depth and the
point's depth is kept, positive where the splats' surface lies behind the point. Differences beyond 5% of R are left
out: a point hidden behind the surface in that view (the other side of the cup, the table under it) is not an error
of the depth. Recorded in % of the scene radius R: the median absolute difference, its 90th percentile, the median
signed difference, and the share within 1% of R. Records: results/mesh_quality/sfm_depth.jsonl, table:
results/mesh_quality/sfm_depth.md. A run already recorded is not measured again (--rerun measures it again); a default
run that mesh_quality.py has not trained is left out.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import tyro

import _common as C
from framework import Arm, Common, NotReady

RUNS = C.RESULTS / "mesh_quality" / "runs"
DEFAULT_RUNS = [f"{scene}-{arm}" for scene in ("cup", "bird") for arm in ("mcmc", "mcmc-surface", "adc", "adc-surface")]
VIEW_STRIDE = 4          # every 4th training view
ALPHA_MIN = 0.5          # the pixel must be covered, as the mesh export asks
HIDDEN = 0.05            # differences beyond this share of R: the point is hidden in that view
RESULTS = "mesh_quality/sfm_depth"  # beside the runs it measures
KEY = ("run",)


@dataclass(frozen=True)
class Options:
    """The splats' median depth at the SfM points, run by run."""

    runs: tuple[Path, ...] = ()
    """Runs of a COLMAP scene (default: mesh_quality.py's cup and bird runs)."""
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def arms(options: Options) -> list[Arm]:
    runs = options.runs or [RUNS / name for name in DEFAULT_RUNS]
    return [Arm(run.name, {"run": run.name, "run_folder": str(run)}) for run in runs]


def run(arm: Arm, options: Options, folder: Path) -> dict:
    run_dir = Path(arm.labels["run_folder"])
    if not (run_dir / "metrics.json").is_file():
        raise NotReady(f"{run_dir} is not a finished run")
    return measure(run_dir)


@torch.no_grad()
def signed_differences(run: Path) -> tuple[np.ndarray, float]:
    """(median depth - point depth at the point's pixel over the kept pairs, scene radius)."""
    from mcsplat.run import trained as trained_run
    from mcsplat.render import render

    trained = trained_run.load(run, torch.device("cpu"))
    scene, radius = trained.scene, trained.scene.radius
    if scene.points is None:
        raise SystemExit(f"{run}: its scene has no SfM points")
    points = scene.points.float()
    kept = []
    for view in scene.train[::VIEW_STRIDE]:
        camera = view.camera
        out = render(trained.model, camera, outputs={"median_depth"})
        local = camera.to_camera_space(points)
        z = local[:, 2]
        u, v, inside = camera.pixels_of(local)
        col, row = u[inside].long(), v[inside].long()
        covered = out.alpha.reshape(camera.height, camera.width)[row, col] >= ALPHA_MIN
        difference = out.median_depth.reshape(camera.height, camera.width)[row, col] - z[inside]
        difference = difference[covered]
        kept.append(difference[difference.abs() < HIDDEN * radius].numpy())
    return np.concatenate(kept), radius


def measure(run: Path) -> dict:
    differences, radius = signed_differences(run)
    relative = differences / radius
    magnitude = np.abs(relative)
    return {"pairs": int(len(relative)), "median_abs_r": float(np.median(magnitude)),
            "p90_abs_r": float(np.quantile(magnitude, 0.9)), "median_signed_r": float(np.median(relative)),
            "within_1pct_r": float((magnitude <= 0.01).mean())}


def report(records: list[dict], folder: Path) -> str:
    columns = [("run", "run", ""), ("point-view pairs", "pairs", ","),
               ("median abs. difference %R", "", lambda r: f"{100 * r['median_abs_r']:.2f}"),
               ("p90 %R", "", lambda r: f"{100 * r['p90_abs_r']:.2f}"),
               ("median signed %R (+: behind)", "", lambda r: f"{100 * r['median_signed_r']:+.2f}"),
               ("within 1% R", "", lambda r: f"{100 * r['within_1pct_r']:.1f}%")]
    return ("# The splats' median depth at the SfM points (sfm_depth.py)\n\n"
            + C.markdown_table(records, columns) + "\n")


if __name__ == "__main__":
    import framework
    sys.exit(framework.script("sfm_depth"))
