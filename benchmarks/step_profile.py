"""Where a training step goes: what it launches, counted, and torch.profiler over steps of the trainer's own step
(gpu_vs_gsplat's mcsplat arm), on CUDA or the CPU.

    python benchmarks/step_profile.py --data PATH/lego [--cap 300000] [--warm 300] [--profiled 30]
    .venv/bin/python benchmarks/step_profile.py --device cpu --data PATH/lego --cap 100000 --warm 20 --profiled 5
    .venv/bin/python benchmarks/step_profile.py --device cpu --data PATH/lego --cap 1000 --downscale 6   # fixed cost
    python benchmarks/step_profile.py --data PATH/lego --cuda-graph     # the step replayed as a CUDA graph
    python benchmarks/step_profile.py --data PATH/lego --both           # the two, one after the other

First, with no profiler, --profiled steps are counted: the torch operators dispatched (aten operators, the autograd
backward's included: what the step asks of the framework), those among them that read a value back to the host
(VALUE_READS: on a GPU each makes the host wait for the queue), the Warp kernel launches (each launch of a CPU kernel
across the thread pool's workers counts once per worker, as each is a launch), and the host's wall time per step.

After --warm steps (Warp's kernels compiled, the model grown past the start) and the counted ones, --profiled steps
run under the profiler. Printed: the wall time per step (slowed by the profiler's own host work); the GPU's busy time
per step (the sum of the kernels' own device time, Warp's kernels included: CUPTI sees every launch of the process);
the host time per step spent in torch operators; the number of kernel launches per step; and the operators and kernels
that take the most device time and the most host time. Busy time well under the wall time means the step waits on the
host (launch overhead, Python, synchronisations), not on the GPU. JSON on the last line.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import collections
import contextlib
import json
import threading
import time
from dataclasses import dataclass
from typing import Annotated

import torch
import tyro
from torch.utils._python_dispatch import TorchDispatchMode

import _common as C
from gpu_vs_gsplat import McsplatArm, McsplatGraphArm, Setup, Training


@dataclass(frozen=True)
class Options:
    """Where a training step goes: its launches counted, then torch.profiler over steps."""

    training: Annotated[Training, tyro.conf.OmitArgPrefixes]
    warm: int = 300
    """Steps before the counted and the profiled ones (kernels compiled, the model grown)."""
    profiled: int = 30
    """Steps counted, then as many profiled."""
    top: int = 15
    """Rows of each table of operators and kernels."""
    downscale: int = 1
    """Load the images at 1/N of their size (a step's fixed cost: lego 400 at --downscale 6 is 66x66)."""
    cuda_graph: bool = False
    """The step replayed as a CUDA graph (`train --cuda-graph`): the operators and launches counted are then the
    host's own around each replay (on the CPU, where there are no graphs, the plain step's)."""
    both: bool = False
    """The step, then the step replayed as a CUDA graph, in one process (a JSON line each)."""


# Operators whose result the host must wait for on a GPU: a value read (item, int, float, bool), or an output whose
# size depends on the values. On the CPU they wait for nothing; counted all the same, they show what a GPU would wait
# on (on the CPU they include the camera numbers a view's first step reads from host memory).
VALUE_READS = {"_local_scalar_dense", "nonzero", "bincount", "masked_select", "_unique2", "unique_consecutive",
               "repeat_interleave"}


class OperatorCount(TorchDispatchMode):
    """Counts the aten operators dispatched while it is on (the autograd backward's among them), by name."""

    def __init__(self) -> None:
        super().__init__()
        self.names: collections.Counter = collections.Counter()

    @property
    def count(self) -> int:
        return sum(self.names.values())

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.names[func.overloadpacket.__name__] += 1
        return func(*args, **(kwargs or {}))


@contextlib.contextmanager
def warp_launches_counted():
    """Counts wp.launch and wp.launch_tiled calls, from any thread, while it is on."""
    import warp as wp
    counter, lock = [0], threading.Lock()
    originals = {name: getattr(wp, name) for name in ("launch", "launch_tiled")}

    def counting(original):
        def launch(*args, **kwargs):
            with lock:
                counter[0] += 1
            return original(*args, **kwargs)
        return launch

    for name, original in originals.items():
        setattr(wp, name, counting(original))
    try:
        yield counter
    finally:
        for name, original in originals.items():
            setattr(wp, name, original)


def count_step_work(step, first: int, steps: int, device: torch.device) -> dict:
    """Torch operators and Warp launches per step, and the wall time per step, over `steps` steps without a
    profiler (the operator count's hook slows the host a little: the wall time is an upper bound)."""
    operators = OperatorCount()
    with warp_launches_counted() as launches, operators:
        started = time.perf_counter()
        for k in range(first, first + steps):
            step(k)
        C.sync(device)
        wall = (time.perf_counter() - started) / steps
    reads = sum(n for name, n in operators.names.items() if name in VALUE_READS)
    return {"torch_ops_per_step": round(operators.count / steps, 1),
            "host_reads_per_step": round(reads / steps, 2),
            "torch_ops_most_per_step": {name: round(n / steps, 1) for name, n in operators.names.most_common(10)},
            "warp_launches_per_step": round(launches[0] / steps, 1),
            "counted_wall_ms_per_step": round(1000 * wall, 3)}


def views_size(setup) -> str:
    camera = setup.scene.train[0].camera
    return f"{camera.width}x{camera.height}"


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    steps = args.warm + 2 * args.profiled  # warm, counted, profiled
    setup = Setup(args.training, steps, downscale=args.downscale)
    for graphed in (False, True) if args.both else (args.cuda_graph,):  # one scene load for both
        print(json.dumps(profile_arm(args, setup, graphed)), flush=True)


def profile_arm(args: Options, setup: Setup, graphed: bool) -> dict:
    """The counts and the profile of one arm's steps (the step, or the step replayed as a CUDA graph)."""
    arm = (McsplatGraphArm if graphed else McsplatArm)(setup)
    views = setup.views()
    for step in range(args.warm):
        arm.step(step, next(views))
    C.sync(setup.device)
    counted = count_step_work(lambda step: arm.step(step, next(views)), args.warm, args.profiled, setup.device)
    first_profiled = args.warm + args.profiled
    activities = [torch.profiler.ProfilerActivity.CPU]
    if setup.device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    started = time.perf_counter()
    with torch.profiler.profile(activities=activities) as profile:
        for step in range(first_profiled, first_profiled + args.profiled):
            arm.step(step, next(views))
        C.sync(setup.device)
    wall = (time.perf_counter() - started) / args.profiled
    events = profile.key_averages()
    # The kernels alone: an operator's row repeats the device time of the kernels it launched.
    kernels = [e for e in events if getattr(e, "device_type", None) == torch.autograd.DeviceType.CUDA]
    device_time = sum(getattr(e, "self_device_time_total", 0) for e in kernels)  # microseconds
    host_time = sum(e.self_cpu_time_total for e in events if e not in kernels)
    launches = sum(e.count for e in kernels)
    for sort in ("self_device_time_total", "self_cpu_time_total"):
        if sort == "self_device_time_total" and setup.device.type != "cuda":
            continue
        print(f"--- by {sort}{' (as a CUDA graph)' if graphed else ''}")
        print(events.table(sort_by=sort, row_limit=args.top, max_name_column_width=70))
    return {"gaussians": arm.count(), "image": f"{views_size(setup)}", "wall_ms_per_step": round(1000 * wall, 3),
            "gpu_busy_ms_per_step": round(device_time / 1000 / args.profiled, 3),
            "host_op_ms_per_step": round(host_time / 1000 / args.profiled, 3),
            "kernel_launches_per_step": round(launches / args.profiled, 1), "profiled_steps": args.profiled,
            "cuda_graph": graphed, **counted, **C.machine(args.training.device)}


if __name__ == "__main__":
    main()
