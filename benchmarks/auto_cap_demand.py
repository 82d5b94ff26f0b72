"""The automatic cap's demand share D/N of trained runs, over windows of 10, 30 and 100 training views.

    .venv/bin/python benchmarks/auto_cap_demand.py benchmarks/results/auto_cap/runs/lego-100k-3000steps ...

The model is frozen (no optimizer step): each view is rendered, its loss back-propagated, and the screen-gradient
statistic of `--cap-max auto` (strategy/screen_gradients.py) accumulated; every `window` views D/N is read and the
statistic reset. It asks whether the demand depends on how many views the statistic averages over (10 at the
squeezed schedules of auto_cap.py, 100 at the paper's) or is a level set by the scene. Results go to
results/auto_cap/demand.{jsonl,md}.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import torch
import tyro

import _common as C

WINDOWS = (10, 30, 100)


@dataclass(frozen=True)
class Options:
    """The automatic cap's demand share of trained runs."""

    runs: Annotated[tuple[Path, ...], tyro.conf.Positional, tyro.conf.arg(metavar="RUN")]
    """Run directories (with checkpoint.pt)."""
    views: int = 100
    """Views rendered per run (a multiple of 100)."""
    seed: int = 1
    """Seed of the random order of the training views."""
    threads: int = 1
    """CPU threads."""


def demand_shares(run_dir: Path, views: int, seed: int) -> dict:
    from mcsplat.run import trained as trained_run
    from mcsplat.losses import photometric_loss
    from mcsplat.render import render
    from mcsplat.strategy.auto_cap import growth_demand
    from mcsplat.strategy.screen_gradients import ScreenGradients

    cpu = torch.device("cpu")
    run = trained_run.load(run_dir, cpu)
    config, model, step, scene = run.config, run.model, run.step, run.scene
    background, sh_degree, n = run.background, run.sh_degree, model.num_gaussians
    stats = {w: ScreenGradients() for w in WINDOWS}
    shares: dict[int, list[float]] = {w: [] for w in WINDOWS}
    order = torch.randint(len(scene.train), (views,), generator=torch.Generator().manual_seed(seed)).tolist()
    for done, index in enumerate(order, 1):
        view = scene.train[index]
        result = render(model, view.camera, background, sh_degree)
        photometric_loss(result.rgb, view.image_float(cpu), config.ssim_weight).backward()
        for window, stat in stats.items():
            stat.add(result, n, view.camera.width, view.camera.height)
            if done % window == 0:
                demand = growth_demand(stat, model.opacities.detach(), config.mcmc.demand_threshold,
                                       config.mcmc.min_opacity)
                shares[window].append(demand / n)
                stat.reset(n, cpu)
        model.zero_grad(set_to_none=True)
    return {"run": run_dir.name, "num_gaussians": n, "step": step, "views": views,
            **{f"share_{w}": round(C.median(s), 4) for w, s in shares.items() if s}}


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    if not args.runs:
        sys.exit("auto_cap_demand: give one or more trained run folders")
    missing = [str(run) for run in args.runs if not (run / "checkpoint.pt").is_file()]
    if missing:
        sys.exit(f"auto_cap_demand: no checkpoint.pt in {', '.join(missing)} (pass trained run folders)")
    C.set_threads(args.threads)
    out = C.results_dir("auto_cap")
    records = []
    for run_dir in args.runs:
        record = demand_shares(run_dir, args.views, args.seed)
        C.emit(record)
        records.append(record)
    C.append_jsonl(out / "demand.jsonl", records)
    table = C.markdown_table(C.read_jsonl(out / "demand.jsonl"), [
        ("run", "run", ""), ("#G", "num_gaussians", ","), ("views", "views", "")] +
        [(f"D/N, {w} views", f"share_{w}", ".4f") for w in WINDOWS])
    C.write_text(out / "demand.md", "# Demand share of trained runs by window (median over windows)\n\n" + table + "\n")


if __name__ == "__main__":
    main()
