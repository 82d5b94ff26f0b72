"""Training with several processes: views per second with 1 and 2 processes, and the all-reduce's share of a step.

    .venv/bin/python benchmarks/distributed.py                          # 10k, 100k, 1M Gaussians; 1 and 2 processes
    .venv/bin/python benchmarks/distributed.py --sizes 10000 --steps 20 --processes 2

Each configuration starts its processes afresh (spawn; gloo over a file store, connections on the loopback
interface), 1 CPU thread each, as `torchrun --nproc-per-node N` would run `mcsplat train`: the trainer's step
(`mcsplat.step.Step`) with the team's reduce (distributed/team.py: one flat all-reduce of every gradient per step), the
schedules and learning rates scaled for N views per step, on lego 400x400 views and train_speed.py's calibrated
stand-in for a trained model (no refinement, so the size stays put). Rank 0 reports:

    step_ms        median wall time of a step (all processes step together)
    views_per_s    processes / step time
    reduce_ms      median time inside the step's reduce: packing, the all-reduce, unpacking, and waiting for the
                   slower process
    allreduce_ms   median of a bare all-reduce of a buffer of the same size, after a barrier: the communication
    share          allreduce_ms / step_ms
    buffer_mb      the all-reduce's buffer (59 floats per Gaussian at SH degree 3, plus the step's loss values)

Prints one JSON line per configuration and writes results/distributed/results.{jsonl,md}.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import json
import multiprocessing
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

import torch
import torch.distributed as dist
import tyro

import _common as C
from train_speed import realistic_model

WARMUP = 3


@dataclass(frozen=True)
class Options:
    """Training with several processes: views per second and the all-reduce's share of a step."""

    sizes: tuple[int, ...] = (10_000, 100_000, 1_000_000)
    """Numbers of Gaussians."""
    processes: tuple[int, ...] = (1, 2)
    """Numbers of processes (1 first: the others' speed-up is against it)."""
    steps: int = 12
    """Timed steps per configuration (after 3 warm-up)."""
    out: str | None = None
    """Results folder (default benchmarks/results/distributed)."""


def worker(rank: int, world_size: int, store: str, size: int, steps: int, out: str) -> None:
    from mcsplat.config import TrainConfig
    from mcsplat.distributed import join
    from mcsplat.gaussians import PARAM_KEYS
    from mcsplat.optim import make_optimizers
    from mcsplat.planning import Plan, for_processes
    from mcsplat.compute.compile import compile_kernels
    from mcsplat.render import set_cpu_threads
    from mcsplat.run.scene import background_of
    from mcsplat.run.state import ViewSampler
    from mcsplat.strategy.mcmc import MCMCConfig, MCMCStrategy
    from mcsplat.step import Step, step_kernels

    os.environ["GLOO_SOCKET_IFNAME"] = "lo"
    if world_size > 1:
        dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=world_size,
                                timeout=timedelta(seconds=900))
    team = join("cpu", 900)
    torch.set_num_threads(1)
    set_cpu_threads(1)
    device = torch.device("cpu")
    compile_kernels(step_kernels(device), device)
    scene = C.load(C.scene_path("lego"))
    config = TrainConfig(data=scene.root, steps=30_000)
    plan = for_processes(Plan.literal(config), world_size)
    model = realistic_model(size)
    team.share_parameters(model)
    optimizers = make_optimizers(model, plan.optim, scene.radius)
    strategy = MCMCStrategy(MCMCConfig(cap_max=size, refine_start=10**9), scene.radius,
                            torch.Generator().manual_seed(0))
    strategy.collective = team.collective
    sampler = ViewSampler(len(scene.train), 0)
    background = background_of(config, scene)
    reduce_seconds: list[float] = []

    def timed_reduce(m, values):
        tick = time.perf_counter()
        result = team.reduce_step(m, values)
        reduce_seconds.append(time.perf_counter() - tick)
        return result

    step_seconds = []
    first = 5000 // world_size  # past the SH warm-up: degree 3, as most of a run
    one_step = Step(model, optimizers, strategy, config, scene.radius, background, device, reduce=timed_reduce)
    for i in range(WARMUP + steps):
        view = scene.train[team.pick(sampler.take(world_size))]
        tick = time.perf_counter()
        one_step(first + i, view, plan)
        step_seconds.append(time.perf_counter() - tick)
    numel = sum(model.params[key].numel() for key in PARAM_KEYS) + 2
    bare = []
    if world_size > 1:
        buffer = torch.zeros(numel)
        for _ in range(7):
            dist.barrier()
            tick = time.perf_counter()
            dist.all_reduce(buffer)
            bare.append(time.perf_counter() - tick)
    if team.is_main:
        record = {"gaussians": size, "processes": world_size, "threads_per_process": 1,
                  "step_ms": round(1000 * C.median(step_seconds[WARMUP:]), 1),
                  "views_per_s": round(world_size / C.median(step_seconds[WARMUP:]), 2),
                  "reduce_ms": round(1000 * C.median(reduce_seconds[WARMUP:]), 2) if world_size > 1 else 0.0,
                  "allreduce_ms": round(1000 * C.median(bare), 2) if bare else 0.0,
                  "buffer_mb": round(numel * 4 / 2**20, 1), "steps": steps}
        record["share"] = round(record["allreduce_ms"] / record["step_ms"], 4)
        Path(out).write_text(json.dumps(record))
    if dist.is_initialized():
        dist.barrier()  # no process leaves while another still talks to it
        dist.destroy_process_group()


def run_configuration(size: int, processes: int, steps: int) -> dict:
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "record.json"
        context = multiprocessing.get_context("spawn")
        workers = [context.Process(target=worker, args=(rank, processes, str(Path(folder) / "store"), size, steps,
                                                        str(out))) for rank in range(processes)]
        for w in workers:
            w.start()
        for w in workers:
            w.join()
        if any(w.exitcode != 0 for w in workers) or not out.is_file():
            sys.exit(f"{processes} process(es) at {C.human(size)} Gaussians failed (exit codes "
                     f"{[w.exitcode for w in workers]})")
        return json.loads(out.read_text())


def markdown(rows: list[dict], info: dict) -> str:
    cols = [("Gaussians", "gaussians", lambda r: C.human(r["gaussians"])), ("processes", "processes", ""),
            ("step ms", "step_ms", ".1f"), ("views/s", "views_per_s", ".2f"), ("speed-up", "speedup", ".2f"),
            ("reduce ms", "reduce_ms", ".2f"), ("all-reduce ms", "allreduce_ms", ".2f"),
            ("all-reduce share", "share", ".1%"), ("buffer MB", "buffer_mb", ".1f")]
    return "\n".join(["# Training with several processes (gloo, CPU, 1 thread per process)", "",
                      "Machine: " + C.machine_line(info), "", C.markdown_table(rows, cols), ""])


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    C.warn_if_busy()
    out = C.results_dir("distributed", args.out)
    info = C.machine("cpu")
    rows = []
    for size in args.sizes:
        alone = None
        for processes in args.processes:
            record = run_configuration(size, processes, args.steps)
            alone = record if processes == 1 else alone
            record["speedup"] = round(record["views_per_s"] / alone["views_per_s"], 3) if alone else None
            record.update(machine=info, commit=C.git_commit(), date=C.timestamp())
            C.emit({k: v for k, v in record.items() if k != "machine"})
            rows.append(record)
    C.write_results(out, rows, markdown(rows, info))


if __name__ == "__main__":
    main()
