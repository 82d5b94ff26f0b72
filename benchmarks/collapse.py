"""MCMC at a cap far above what the scene needs: does it collapse, and what do the health instruments show?

    .venv/bin/python benchmarks/collapse.py                                   # the bird at 1/4, 8,000 steps
    .venv/bin/python benchmarks/collapse.py --arms paper:1000000 alive:1000000 alive:62500 auto
    .venv/bin/python benchmarks/collapse.py --downscale 8 --arms paper:250000 alive:250000 --tag bird8
    .venv/bin/python benchmarks/collapse.py --report                          # rebuild results.md only

Each arm is one `mcsplat train` of the scene from its SfM points, with the same steps, seed and schedules:
`RELOCATION:CAP` trains with `--cap-max CAP --mcmc.relocation RELOCATION` (paper: Eq. 9 with up to 51 copies a host,
whatever their opacity, grown to the cap; alive: mcsplat's default, no copy born dead, no growth while dead are left
unplaced, growth stops where the scene stops asking);
`auto` trains without `--cap-max` (the count from the scene). The target (issue 56): at 1M, at most 25% dead at the
last refine step and a test PSNR within 0.5 dB of the fitting cap's (62,500). The record keeps the health levels of
every log record (log.jsonl: dead share, unseen dead share, copies per host, copies born dead, unplaced). Runs live in
results/collapse/runs/ (git-ignored); a finished run is reused. `--jobs 2 --threads 1` runs two at a time.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

import _common as C
from framework import Arm, Common

LEVELS = ("dead_share", "unseen_dead_share", "copies_max", "copies_mean", "born_dead_share", "unplaced")
MAX_DEAD_SHARE, PSNR_MARGIN = 0.25, 0.5
KEY = ("tag", "arm", "steps")


@dataclass(frozen=True)
class Options:
    """MCMC at a cap far above what the scene needs: the health levels and the test PSNR."""

    scene: str = "bird"
    """bird, cup, lego (the shared data) or a scene folder."""
    downscale: int = 4
    steps: int = 8000
    arms: tuple[str, ...] = ("paper:1000000", "alive:1000000", "alive:62500")
    """RELOCATION:CAP, or auto (no --cap-max)."""
    tag: str | None = None
    """The results' group and the start of its run folders' names (default: SCENE-1ofDOWNSCALE)."""
    seed: int = 0
    eval_every: int = 1000
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def arm_options(arm: str) -> list[str]:
    if arm == "auto":
        return []
    relocation, cap = arm.split(":")
    return ["--cap-max", cap, "--mcmc.relocation", relocation]


def arms(options: Options) -> list[Arm]:
    tag = options.tag or f"{Path(options.scene).name}-1of{options.downscale}"  # a folder's name, not its path
    return [Arm(f"{tag}-{arm.replace(':', '-')}-{options.steps}",
                {"tag": tag, "arm": arm, "steps": options.steps, "downscale": options.downscale})
            for arm in options.arms]


def run(arm: Arm, options: Options, folder: Path) -> dict:
    """`mcsplat train` of the arm (a finished run is reused), then its figures."""
    run_dir = folder / "runs" / arm.name
    if not (run_dir / "metrics.json").is_file():
        command = [sys.executable, "-m", "mcsplat", "train", str(C.scene_path(options.scene, options.common.data_root)),
                   "--out", str(run_dir), "--downscale", str(options.downscale), "--steps", str(options.steps),
                   "--seed", str(options.seed), "--eval-every", str(options.eval_every), "--save-every", "0",
                   "--quiet", "--lpips-net", "alex", "--no-save-renders", *arm_options(arm.labels["arm"])]
        if options.common.threads:
            command += ["--threads", str(options.common.threads)]
        command += ["--overwrite"] if run_dir.exists() else []
        print(" ".join(command), flush=True)
        run_dir.parent.mkdir(parents=True, exist_ok=True)
        with open(run_dir.parent / f"{run_dir.name}.txt", "w") as out:
            subprocess.run(command, check=True, stdout=out, stderr=subprocess.STDOUT)
    return figures(run_dir)


def figures(run: Path) -> dict:
    metrics = json.loads((run / "metrics.json").read_text())
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    refines = [r for r in log if "dead_share" in r]
    last = refines[-1] if refines else {}
    return {"psnr": metrics["psnr"], "ssim": metrics["ssim"], "num_gaussians": metrics["num_gaussians"],
            "train_seconds": metrics.get("train_seconds"),
            "last_refine": {key: last.get(key) for key in ("step", *LEVELS)},
            "trajectory": [{key: r.get(key) for key in ("step", "num_gaussians", "test_psnr", *LEVELS)} for r in log]}


def report(rows: list[dict], folder: Path) -> str:
    lines = ["# MCMC at a cap far above what the scene needs", "",
             "`benchmarks/collapse.py`: the health levels at the last refine step (log.jsonl) and the test PSNR of "
             "each arm. paper: the paper's relocation and growth (Eq. 9 with up to 51 copies a host); alive: no copy "
             "born dead, no growth while dead are left unplaced, growth stops where the scene stops asking (the "
             "default); auto: no --cap-max.", ""]
    for tag in sorted({r["tag"] for r in rows}):
        group = [r for r in rows if r["tag"] == tag]
        lines += [f"## {tag}", "", "| arm | steps | PSNR | Gaussians | dead share | unseen dead | copies max / mean | "
                  "born dead | unplaced |", "|---|---|---|---|---|---|---|---|---|"]
        for r in group:
            last = r["last_refine"]
            steps = f"{r['steps']:,}" + (f" (stopped at {r['stopped_at']:,})" if r.get("stopped_at") else "")
            last_psnr = r["psnr"] if r["psnr"] is not None else (r["trajectory"][-1].get("test_psnr"))
            lines.append(f"| {r['arm']} | {steps} | {C.fmt(last_psnr, '.2f')} | "
                         f"{C.fmt(r.get('num_gaussians') or r['trajectory'][-1]['num_gaussians'], ',')} | "
                         f"{C.fmt(last.get('dead_share'), '.1%')} | {C.fmt(last.get('unseen_dead_share'), '.1%')} | "
                         f"{C.fmt(last.get('copies_max'), '.0f')} / {C.fmt(last.get('copies_mean'), '.2f')} | "
                         f"{C.fmt(last.get('born_dead_share'), '.1%')} | {C.fmt(last.get('unplaced'), '.0f')} |")
        lines.append("")
        fitting = [r for r in group if r["arm"].startswith("alive:") and int(r["arm"].split(":")[1]) < 10**6]
        lines += [f"- {r['arm']}: {r['note']}" for r in group if r.get("note")]
        for r in group:
            if r["arm"].endswith(":1000000") and fitting and r["psnr"] is not None:
                dead = r["last_refine"].get("dead_share") or 0.0
                gap = r["psnr"] - fitting[0]["psnr"]
                met = dead <= MAX_DEAD_SHARE and gap >= -PSNR_MARGIN
                lines.append(f"- {r['arm']}: {dead:.1%} dead at the last refine, {gap:+.2f} dB against "
                             f"{fitting[0]['arm']}: {'met' if met else 'missed'}")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    import framework
    sys.exit(framework.script("collapse"))
