"""`make demo` per CPU build, each from an empty kernel cache: what a fresh clone costs on a CPU with or without
AVX-512, measured on one machine.

    .venv/bin/python benchmarks/demo_builds.py                       # native (this host) and znver3 (AVX2)
    .venv/bin/python benchmarks/demo_builds.py --builds native znver3 haswell --rounds 2

A build is "native" (the kernels compiled for this host: AVX-512 where it has it) or an LLVM CPU name, compiled for
that CPU through MCSPLAT_CPU_TARGET (mcsplat/compute/cpu_target.py): `znver3` is an AMD EPYC with AVX2 and no
AVX-512. Each run trains the bundled lego with the Makefile's demo options in a fresh process whose Warp kernel cache
(WARP_CACHE_PATH) starts empty, so its wall time includes compiling every kernel, as a fresh clone's first run
does; the package install is not included. One JSON line per run, then a table; results.jsonl and results.md go to
benchmarks/results/demo_builds/.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import tyro

import _common as C

ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Options:
    """`make demo` per CPU build, each from an empty kernel cache."""

    builds: tuple[str, ...] = ("native", "znver3")
    """native (this host's kernels), or LLVM CPU names to compile the kernels for."""
    rounds: int = 1
    """Runs of each build, the builds taking turns."""
    out: str | None = None
    """Results folder (default benchmarks/results/demo_builds)."""


def demo_options() -> list[str]:
    """The Makefile's DEMO_OPTIONS, read from it so that the two never differ."""
    match = re.search(r"^DEMO_OPTIONS := (.+)$", (ROOT / "Makefile").read_text(), re.MULTILINE)
    if match is None:
        sys.exit("demo_builds: the Makefile has no DEMO_OPTIONS line")
    return match.group(1).split()


def run_demo(build: str, out: Path) -> dict:
    """One demo run on `build`, from an empty kernel cache: wall seconds, training seconds and test scores."""
    with tempfile.TemporaryDirectory(prefix="mcsplat-kernels-") as cache:
        env = {**os.environ, "MCSPLAT_CPU_TARGET": build, "WARP_CACHE_PATH": cache}
        command = [str(Path(sys.executable).parent / "mcsplat"), "train", str(ROOT / "data" / "lego_demo"),
                   "--out", str(out), "--overwrite", "--quiet", *demo_options()]
        started = time.perf_counter()
        subprocess.run(command, env=env, check=True)
        wall = time.perf_counter() - started
    metrics = json.loads((out / "metrics.json").read_text())
    return {"benchmark": "demo_builds", "build": build, "wall_seconds": round(wall, 1),
            "train_seconds": metrics["train_seconds"], "set_up_and_compile_seconds": round(
                wall - metrics["train_seconds"], 1), "psnr": round(metrics["psnr"], 2),
            "ssim": round(metrics["ssim"], 4), "gaussians": metrics["num_gaussians"]}


def markdown(records: list[dict], info: dict) -> str:
    lines = [f"# `make demo` per CPU build ({info['cpu']})", "",
             f"Commit {C.git_commit()}, {C.timestamp()}. Each run from an empty kernel cache (its wall time includes "
             f"compiling every kernel); the package install is not included.", "",
             "| build | wall s | training s | set-up and compile s | PSNR | SSIM |", "|---|---|---|---|---|---|"]
    lines += [f"| {r['build']} | {r['wall_seconds']} | {r['train_seconds']} | {r['set_up_and_compile_seconds']} | "
              f"{r['psnr']} | {r['ssim']} |" for r in records]
    return "\n".join(lines) + "\n"


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    out = C.results_dir("demo_builds", args.out)
    info = C.machine("cpu")
    C.warn_if_busy()
    records = []
    with tempfile.TemporaryDirectory(prefix="mcsplat-demo-") as runs:
        for _ in range(args.rounds):
            for build in args.builds:
                record = {**run_demo(build, Path(runs) / build), "machine": info, "commit": C.git_commit(),
                          "date": C.timestamp()}
                C.emit(record)
                records.append(record)
    C.write_results(out, records, markdown(records, info))


if __name__ == "__main__":
    main()
