"""One training process of a multi-process test run (tests/distributed/test_distributed.py starts them with spawn).

Joins a gloo process group through a file store (no network port), trains, and writes what the test checks to
<results>/rank<N>.json: the final parameters' checksum and metrics, or the error it stopped with.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep)

import json
import os
import signal
from datetime import timedelta
from pathlib import Path
from typing import Callable

import torch.distributed as dist

from mcsplat.config import TrainConfig
from mcsplat.distributed import parameter_checksum
from mcsplat.errors import MCSplatError
from mcsplat.strategy.adc import ADCStrategy
from mcsplat.strategy.mcmc import MCMCStrategy
from mcsplat import train, trainer


def run(rank: int, world_size: int, init_file: str, results: str, configs: list[TrainConfig],
        crash: dict | None = None, timeout: float = 60.0) -> None:
    """`configs[rank]` is this process's configuration. `crash`: {"rank": r, "step": s, "how": "raise" | "exit" |
    "sigterm"} makes rank r (-1: every rank) fail at step s, by an exception, by dying on the spot, or by being sent
    SIGTERM (what torchrun passes on to its processes when it is stopped)."""
    _join_group(rank, world_size, init_file, timeout)
    if crash and crash["rank"] in (rank, -1):
        _fail_at(ADCStrategy if configs[rank].strategy == "adc" else MCMCStrategy, crash["step"], crash["how"])
    final = {}
    original_finish = trainer.TrainingRun._finish

    def finish(self, *args):
        final["checksum"] = parameter_checksum(self.model)
        return original_finish(self, *args)

    trainer.TrainingRun._finish = finish

    def training() -> dict:
        try:
            metrics = train.train(configs[rank])
        except RuntimeError as error:
            return {"crash": str(error)}
        return {"metrics": {k: v for k, v in metrics.items() if k != "per_view_psnr"}, **final}

    _write_outcome(rank, results, training)


def _join_group(rank: int, world_size: int, init_file: str, timeout: float) -> None:
    os.environ["GLOO_SOCKET_IFNAME"] = "lo"  # gloo's connections between the processes stay on this machine
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world_size,
                            timeout=timedelta(seconds=timeout))


def _write_outcome(rank: int, results: str, work: Callable[[], dict]) -> None:
    """Write what `work` returns, or the MCSplatError it stopped with, to <results>/rank<N>.json; the process group
    is left either way."""
    try:
        outcome = work()
    except MCSplatError as error:
        outcome = {"error": str(error)}
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()
    (Path(results) / f"rank{rank}.json").write_text(json.dumps(outcome))


def _fail_at(strategy, step_to_fail: int, how: str) -> None:
    original = strategy.step_post_optimizer

    def patched(self, step, *args, **kwargs):
        if step == step_to_fail:
            if how == "exit":
                os._exit(3)  # a process that dies without a word (killed, out of memory)
            if how == "sigterm":
                signal.raise_signal(signal.SIGTERM)
                return original(self, step, *args, **kwargs)
            raise RuntimeError("simulated crash")
        return original(self, step, *args, **kwargs)

    strategy.step_post_optimizer = patched


def reduce_once(rank: int, world_size: int, init_file: str, results: str) -> None:
    """One reduce_step on a tiny model whose gradients are rank + 1 times its position: what comes back."""
    import torch

    from mcsplat.distributed import join
    from mcsplat.gaussians import GaussianModel

    _join_group(rank, world_size, init_file, 60)
    try:
        team = join("cpu", 60)
        model = GaussianModel.empty(3, sh_degree=1)
        for key, p in model.params.items():
            if key != "quats":  # one parameter without a gradient: it counts as zeros
                p.grad = torch.arange(p.numel(), dtype=p.dtype).reshape(p.shape) * (rank + 1)
        values = team.reduce_step(model, torch.tensor([10.0 * (rank + 1), 1.0 if rank == 1 else 0.0])).tolist()
        grads = {key: p.grad.reshape(-1).tolist() for key, p in model.params.items()}
        (Path(results) / f"rank{rank}.json").write_text(json.dumps({"values": values, "grads": grads,
                                                                   "listening": listening_addresses()}))
    finally:
        dist.barrier()
        dist.destroy_process_group()


def listening_addresses() -> list[str]:
    """The local addresses of this process's listening TCP sockets (Linux: /proc), e.g. "7F000001:9C40"."""
    sockets = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            sockets.add(target[len("socket:["):-1])
    found = []
    for table in ("/proc/self/net/tcp", "/proc/self/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A" and fields[9] in sockets:  # LISTEN
                found.append(fields[1])
    return found


def train_blocks_run(rank: int, world_size: int, init_file: str, results: str, folder: str) -> None:
    """`mcsplat blocks train FOLDER` as one process of a torchrun group: trains its share of the blocks; rank 0
    merges. Writes which block folders this process made the runs of, and the merged metrics (rank 0)."""
    from mcsplat.blocks import train_blocks
    from mcsplat.partition import BlocksFolder

    _join_group(rank, world_size, init_file, 300)
    import mcsplat.blocks.train as block_training

    trained = []
    original = block_training.train

    def recording(config, *args, **kwargs):
        trained.append(int(config.block.rpartition("#")[2]))
        return original(config, *args, **kwargs)

    block_training.train = recording

    def training() -> dict:
        merged = train_blocks(BlocksFolder(folder), threads=1, quiet=True)
        return {"trained": trained, "merged": merged}

    _write_outcome(rank, results, training)
