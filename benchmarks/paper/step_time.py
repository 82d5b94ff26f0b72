"""The time of a training step of trained models, side by side: render + loss + backward of each run's final model
on the same training views, the runs taken in turn view by view so that a change in the machine's load falls on
all of them alike. It separates what a step costs at a given model from how a run's count grew. Beside the time, the
work that sets it: the (tile, Gaussian) pairs the rasterizer composites and the Gaussians drawn into a pixel (medians
over the views), and the models' opacities and sizes.

    .venv/bin/python -m benchmarks.paper.step_time cup-mcmc-sfm cup-mcmc-sfm-opacity-reg-0.001 cup-adc-sfm

Run names are folders under benchmarks/results/paper/<scale>/runs/ (or paths). Prints one JSON line per run and
writes them to results/paper/<scale>/step_time.jsonl.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import argparse
import sys
import time
from pathlib import Path

import torch

import _common as C


def shape(model) -> dict:
    """What the regularizers act on: the opacities (an opaque pixel stops compositing early) and the sizes."""
    with torch.no_grad():
        opacity, size = model.opacities, model.scales.max(dim=1).values
        return {"mean_opacity": round(float(opacity.mean()), 4),
                "opaque_share": round(float((opacity > 0.5).float().mean()), 4),
                "median_largest_axis": round(float(size.median()), 5)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", help="run names under results/paper/<scale>/runs/, or run folders")
    parser.add_argument("--scale", default="cpu")
    parser.add_argument("--views", type=int, default=30, help="training views timed per run")
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args()
    from mcsplat.run import trained as trained_run
    from mcsplat.losses import photometric_loss
    from mcsplat.render import render

    folder = C.RESULTS / "paper" / args.scale
    paths = [Path(name) if Path(name).is_dir() else folder / "runs" / name for name in args.runs]
    missing = [str(p) for p in paths if not (p / "checkpoint.pt").is_file()]
    if missing:
        sys.exit(f"step_time: no checkpoint.pt in {', '.join(missing)} (pass trained run folders)")
    C.set_threads(args.threads)
    cpu = torch.device("cpu")
    runs = [trained_run.load(path, cpu) for path in paths]
    views = runs[0].scene.train[:: max(1, len(runs[0].scene.train) // args.views)][: args.views]
    seconds: list[list[float]] = [[] for _ in runs]
    pairs: list[list[int]] = [[] for _ in runs]      # (tile, Gaussian) intersections: the compositing work
    composited: list[list[int]] = [[] for _ in runs]  # Gaussians drawn into at least one pixel
    for index, view in enumerate(views):
        for k, run in enumerate(runs):
            started = time.perf_counter()
            result = render(run.model, view.camera, run.background, run.sh_degree)
            photometric_loss(result.rgb, view.image_float(cpu), run.config.ssim_weight).backward()
            run.model.zero_grad(set_to_none=True)
            if index > 0:  # the first view warms the caches of each run
                seconds[k].append(time.perf_counter() - started)
            pairs[k].append(result.num_pairs)
            composited[k].append(int(result.contributed.sum()))
    records = [{"run": path.name, "num_gaussians": run.model.num_gaussians, "views": len(s),
                "ms_render_backward": round(1000 * C.median(s), 1), "tile_pairs": int(C.median(p)),
                "composited": int(C.median(c)), **shape(run.model)}
               for path, run, s, p, c in zip(paths, runs, seconds, pairs, composited)]
    for record in records:
        C.emit(record)
    C.append_jsonl(folder / "step_time.jsonl", [dict(r, date=C.timestamp(), machine=C.machine()) for r in records])


if __name__ == "__main__":
    main()
