"""Scaling: full training step time against the number of Gaussians and against the image size, log-log slopes.

    .venv/bin/python benchmarks/scaling.py                        # N in 10k..300k at 400 px; 100..800 px at 100k
    .venv/bin/python benchmarks/scaling.py --sizes 10000 100000 --resolutions 200 400 --repeats 3
    .venv/bin/python benchmarks/scaling.py --device cuda          # skips cleanly without CUDA

The step is train_speed.py's `bench_step` (the trainer's own step: render, loss, backward, Adam, MCMC noise; refine steps
left out, see train_speed.py for their amortised cost) on train_speed.py's calibrated stand-in for a trained model.
Sweep 1: N Gaussians at 400x400. Sweep 2: fixed N, square images of 100..800 px: the lego views' K scaled with
Camera.scaled and the images resized (800 px is an upsampled 400 px image: only the timing matters). One JSON line
per point, then one per sweep with the least-squares slope of log(step time) against log(N) or log(pixels):
"linear" when the slope is within 0.15 of 1, "sub-linear" below, "super-linear" above. Note that more Gaussians
are also smaller (scale ~ N^-1/3, so the Gaussians composited per pixel grow ~ N^1/3); the tile pairs are recorded
so the two effects can be told apart.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import dataclasses
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

import _common as C
from train_speed import Bench, bench_step, realistic_model, step_numbers, training_views

LINEAR_TOLERANCE = 0.15


@dataclass(frozen=True)
class Options:
    """Training step time against the number of Gaussians and against the image size."""

    sizes: tuple[int, ...] = (10_000, 30_000, 100_000, 300_000)
    """Numbers of Gaussians for sweep 1 (none: skip it)."""
    size_resolution: int = 400
    """Image side for sweep 1."""
    resolutions: tuple[int, ...] = (100, 200, 400, 800)
    """Square image sides for sweep 2 (none: skip it)."""
    resolution_gaussians: int = 100_000
    """N for sweep 2."""
    threads: int | None = None
    """CPU threads (default: all cores)."""
    device: str = "cpu"
    """cpu or cuda."""
    scene: str = "lego"
    """lego (shared data) or a scene folder."""
    data_root: str = str(C.DATA_ROOT)
    """The shared data folder."""
    warmup: int = 2
    """Untimed steps first, at each point."""
    repeats: int = 5
    """Timed steps at each point (their median)."""
    seed: int = 0
    """Seed of the stand-in model."""
    out: str | None = None
    """Results folder (default benchmarks/results/scaling)."""


def time_steps(b: Bench, warmup: int, repeats: int) -> tuple[float, int]:
    """(median seconds per step, median tile pairs)."""
    steps = step_numbers()
    for i in range(warmup):
        bench_step(b, next(steps), i)
    times, pairs = [], []
    for i in range(repeats):
        t0 = C.now(b.device)
        pairs.append(bench_step(b, next(steps), warmup + i))
        times.append(C.now(b.device) - t0)
    return C.median(times), int(C.median(pairs))


def slope(xs: list[float], ys: list[float]) -> float:
    if len(xs) < 2:
        return float("nan")
    return float(np.polyfit(np.log(xs), np.log(ys), 1)[0])


def verdict(s: float) -> str:
    if math.isnan(s):
        return "n/a (fewer than 2 points)"
    if abs(s - 1.0) <= LINEAR_TOLERANCE:
        return "linear"
    return "sub-linear" if s < 1.0 else "super-linear"


def plot(points: list[dict], summaries: dict, path: Path, title: str) -> bool:
    plt = C.pyplot()
    if plt is None or not points:
        return False
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    panels = (("gaussians", "gaussians", "number of Gaussians"), ("image", "pixels", "pixels per image"))
    for ax, (sweep, key, xlabel) in zip(axes, panels):
        rows = [p for p in points if p["sweep"] == sweep]
        if not rows:
            ax.set_axis_off()
            continue
        xs = np.array([r[key] for r in rows], dtype=float)
        ys = np.array([r["step_ms"] for r in rows], dtype=float)
        ax.loglog(xs, ys, "o-", label="measured")
        s = summaries[sweep]["slope"]
        if not math.isnan(s):
            a, c = np.polyfit(np.log(xs), np.log(ys), 1)
            ax.loglog(xs, np.exp(c) * xs ** a, "--", label=f"fit: slope {s:.2f}")
        ax.loglog(xs, ys[-1] * (xs / xs[-1]), ":", color="grey", label="slope 1 (linear)")
        for x, y, r in zip(xs, ys, rows):
            ax.annotate(C.human(r["gaussians"]) if sweep == "gaussians" else r["image"], (x, y),
                        textcoords="offset points", xytext=(4, -10), fontsize=7)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("ms per training step")
        fixed = f"{rows[0]['image']}" if sweep == "gaussians" else f"{C.human(rows[0]['gaussians'])} Gaussians"
        ax.set_title(f"against {xlabel} ({fixed})", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def markdown(points: list[dict], summaries: dict, info: dict, args) -> str:
    cols = [("sweep", "sweep", ""), ("Gaussians", "gaussians", ""), ("image", "image", ""),
            ("step ms", "step_ms", ".1f"), ("tile pairs", "tile_pairs", ",")]
    lines = [f"# Scaling of the training step ({points[0]['device'] if points else args.device})", "",
             f"Machine: {C.machine_line(info)}; threads {args.threads}. Commit {C.git_commit()}, "
             f"{C.timestamp()}.", "",
             f"Median of {args.repeats} trainer steps after {args.warmup} warm-up steps (refine steps left out), "
             f"lego views, train_speed.py's realistic scene model.", "", C.markdown_table(points, cols), ""]
    for sweep, s in summaries.items():
        against = "log N" if sweep == "gaussians" else "log pixels"
        lines.append(f"- against {sweep}: slope of log(step time) vs {against} = **{s['slope']:.2f}** "
                     f"({s['verdict']}); x{s['time_ratio']:.1f} time for x{s['size_ratio']:.3g} size.")
    return "\n".join(lines) + "\n"


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    C.cuda_or_exit(args.device, "scaling")
    C.set_threads(args.threads)
    if args.threads is None and args.device == "cpu":
        args = dataclasses.replace(args, threads=torch.get_num_threads())
    out = C.results_dir("scaling", args.out)
    info = C.machine(args.device)
    load = C.warn_if_busy()
    scene = C.load(C.scene_path(args.scene, args.data_root))
    device_name = args.device if args.device != "cpu" else f"cpu ({C.cpu_name()})"

    grid = [("gaussians", n, args.size_resolution) for n in args.sizes]
    grid += [("image", args.resolution_gaussians, r) for r in args.resolutions]
    points, views = [], {}
    for sweep, n, side in grid:
        if side not in views:
            views[side] = training_views(scene, side)
        cameras, images = views[side]
        started = time.perf_counter()
        b = Bench.make(realistic_model(n, args.seed), scene, cameras, images, args.device)
        seconds, pairs = time_steps(b, args.warmup, args.repeats)
        record = {"benchmark": "scaling", "sweep": sweep, "device": device_name, "gaussians": n,
                  "image": f"{side}x{side}", "pixels": side * side, "step_ms": round(seconds * 1000.0, 1),
                  "tile_pairs": pairs, "threads": args.threads if args.device == "cpu" else None,
                  "repeats": args.repeats, "wall_seconds": round(time.perf_counter() - started, 1),
                  "load_average_before": load}
        C.emit(record)
        points.append(record)
        del b

    summaries = {}
    for sweep, key in (("gaussians", "gaussians"), ("image", "pixels")):
        rows = [p for p in points if p["sweep"] == sweep]
        if not rows:
            continue
        s = slope([r[key] for r in rows], [r["step_ms"] for r in rows])
        summaries[sweep] = {"slope": round(s, 3), "verdict": verdict(s), "size_ratio": rows[-1][key] / rows[0][key],
                            "time_ratio": round(rows[-1]["step_ms"] / rows[0]["step_ms"], 3)}
        C.emit({"benchmark": "scaling", "summary": sweep, "against": f"log {key}", **summaries[sweep],
                "device": device_name, "machine": info, "commit": C.git_commit(), "date": C.timestamp()})
    C.write_results(out, points, markdown(points, summaries, info, args))
    if plot(points, summaries, out / "scaling.png",
            f"Training step time, lego views, {device_name}, threads {args.threads}"):
        print(f"wrote {out / 'scaling.png'}", file=sys.stderr)


if __name__ == "__main__":
    main()
