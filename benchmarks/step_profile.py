"""Where a GPU training step goes: torch.profiler over steps of the trainer's own step (gpu_vs_gsplat's mcsplat arm).

    python benchmarks/step_profile.py --data PATH/lego [--cap 300000] [--warm 300] [--profiled 30]

After --warm steps (Warp's kernels compiled, the model grown past the start), --profiled steps run under the
profiler. Printed: the wall time per step (slowed by the profiler's own host work); the GPU's busy time per step (the sum of
the kernels' own device time, Warp's kernels included: CUPTI sees every launch of the process); the host time per step spent in torch operators;
the number of kernel launches per step; and the operators and kernels that take the most device time and the most
host time. Busy time well under the wall time means the step waits on the host (launch overhead, Python,
synchronisations), not on the GPU. JSON on the last line.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import argparse
import json
import time

import torch

import _common as C
from gpu_vs_gsplat import McsplatArm, Setup


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--cap", type=int, default=300_000)
    parser.add_argument("--init", type=int, default=None, help="random initial points (default: cap / 2)")
    parser.add_argument("--init-method", default="auto", choices=["auto", "random"])
    parser.add_argument("--warm", type=int, default=300)
    parser.add_argument("--profiled", type=int, default=30)
    parser.add_argument("--device", default="cuda", choices=["cuda", "cpu"])
    parser.add_argument("--top", type=int, default=15)
    args = parser.parse_args()
    args.init = args.init or args.cap // 2
    args.steps, args.seed = args.warm + args.profiled, 0
    setup = Setup(args)
    arm = McsplatArm(setup)
    views = setup.views()
    for step in range(args.warm):
        arm.step(step, next(views))
    C.sync(setup.device)
    activities = [torch.profiler.ProfilerActivity.CPU]
    if setup.device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    started = time.perf_counter()
    with torch.profiler.profile(activities=activities) as profile:
        for step in range(args.warm, args.warm + args.profiled):
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
        print(f"--- by {sort}")
        print(events.table(sort_by=sort, row_limit=args.top, max_name_column_width=70))
    record = {"gaussians": arm.count(), "wall_ms_per_step": round(1000 * wall, 3),
              "gpu_busy_ms_per_step": round(device_time / 1000 / args.profiled, 3),
              "host_op_ms_per_step": round(host_time / 1000 / args.profiled, 3),
              "kernel_launches_per_step": round(launches / args.profiled, 1), "profiled_steps": args.profiled,
              **C.machine(args.device)}
    print(json.dumps(record), flush=True)


if __name__ == "__main__":
    main()
