"""The Adam step of a model's six parameters on the CPU: torch.optim.Adam(fused=True), one per parameter (the step
before), against optim.step_optimizers (adam_cpu's one launch over all of them). Median of many steps each, on the
same random gradients; both give the same parameters to the bit (checked here on the first step too).

    .venv/bin/python benchmarks/adam_cpu.py [--gaussians 100000] [--repeats 200] [--threads 2]
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import json
import statistics
import time
from dataclasses import dataclass

import torch
import tyro

import _common as C
from mcsplat.compute.runtime import set_cpu_threads
from mcsplat.gaussians import PARAM_KEYS, GaussianModel
from mcsplat.optim import OptimConfig, make_optimizers, step_optimizers


@dataclass(frozen=True)
class Options:
    """The Adam step on the CPU: torch's fused Adam per parameter against one launch over all of them."""

    gaussians: int = 100_000
    """Gaussians of the model whose parameters step."""
    repeats: int = 200
    """Timed steps of each (the median is reported)."""
    threads: int = torch.get_num_threads()
    """CPU threads of torch and of the one-launch step."""


def model_with_gradients(n: int) -> GaussianModel:
    g = torch.Generator().manual_seed(0)
    model = GaussianModel.empty(n)
    with torch.no_grad():
        for key in PARAM_KEYS:
            model.params[key].copy_(torch.randn(model.params[key].shape, generator=g))
    return model


def timed(model: GaussianModel, take, repeats: int) -> list[float]:
    optimizers = make_optimizers(model, OptimConfig(), 2.0)
    grads = {key: torch.randn(model.params[key].shape) * 1e-3 for key in PARAM_KEYS}
    seconds = []
    for _ in range(repeats + 5):  # the first few: state made, kernels loaded, caches warm
        for key in PARAM_KEYS:
            model.params[key].grad = grads[key]
        started = time.perf_counter()
        take(optimizers)
        seconds.append(time.perf_counter() - started)
    return seconds[5:]


def torch_step(optimizers) -> None:
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    load = C.warn_if_busy()
    torch.set_num_threads(args.threads)
    set_cpu_threads(args.threads)
    first, second = model_with_gradients(args.gaussians), model_with_gradients(args.gaussians)
    for model, take in ((first, torch_step), (second, step_optimizers)):
        optimizers = make_optimizers(model, OptimConfig(), 2.0)
        for key in PARAM_KEYS:
            model.params[key].grad = torch.ones_like(model.params[key])
        take(optimizers)
    same = all(torch.equal(first.params[k], second.params[k]) for k in PARAM_KEYS)
    floats = sum(p.numel() for p in first.params.values())
    record = {"gaussians": args.gaussians, "floats": floats, "threads": args.threads, "repeats": args.repeats,
              "identical_to_torch": same, "load_average_before": load}
    for name, take in (("torch_fused_adam_ms", torch_step), ("one_launch_ms", step_optimizers)):
        record[name] = round(1000 * statistics.median(timed(model_with_gradients(args.gaussians), take,
                                                            args.repeats)), 3)
    record["speedup"] = round(record["torch_fused_adam_ms"] / record["one_launch_ms"], 2)
    record.update(C.machine("cpu"))
    print(json.dumps(record), flush=True)


if __name__ == "__main__":
    main()
