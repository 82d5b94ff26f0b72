"""SSIM forward + backward: torch's depthwise convolutions (losses.ssim_map), the fused Warp kernels of ssim/warp.py
(the CUDA path of losses.ssim) and, on the CPU, the fused C++ passes of ssim/cpu.py (the CPU path), at 400x400 and
800x800.

    .venv/bin/python benchmarks/ssim.py                          # CUDA when there is one, else the CPU
    .venv/bin/python benchmarks/ssim.py --device cpu --repeats 5

Prints one JSON line per size: the median milliseconds of each over the repeats (after one untimed call that
compiles or warms up), and the speed-up of the Warp kernels over torch.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

from dataclasses import dataclass

import torch
import tyro

import _common as C

SIZES = (400, 800)


@dataclass(frozen=True)
class Options:
    """SSIM forward + backward: torch's convolutions against the fused kernels."""

    device: str = "cuda" if torch.cuda.is_available() else "cpu"
    """cuda or cpu (default: cuda when there is one)."""
    repeats: int | None = None
    """Timed calls of each (default: 50 CUDA, 5 CPU)."""
    threads: int | None = None
    """CPU threads for torch and the Warp launcher."""


def median_ms(ssim, image: torch.Tensor, target: torch.Tensor, repeats: int) -> float:
    times = []
    for _ in range(repeats + 1):
        x = image.clone().requires_grad_()
        start = C.now(image.device)
        ssim(x, target).backward()
        times.append(C.now(image.device) - start)
    return 1000.0 * C.median(times[1:])


def main() -> None:
    args = tyro.cli(Options, description=__doc__)

    from mcsplat.losses import ssim_map
    from mcsplat.ssim.cpu import fused_ssim
    from mcsplat.ssim.warp import fused_ssim_warp

    C.cuda_or_exit(args.device, "ssim")
    C.set_threads(args.threads)
    device = torch.device(args.device)
    repeats = args.repeats or (50 if device.type == "cuda" else 5)
    load = C.warn_if_busy()
    methods = {"torch": lambda x, y: ssim_map(x, y).mean(), "warp": fused_ssim_warp}
    if device.type == "cpu":
        methods["ssim_cpu"] = fused_ssim
    generator = torch.Generator().manual_seed(0)
    for size in SIZES:
        target = torch.rand(size, size, 3, generator=generator)
        image = (target + 0.1 * torch.randn(size, size, 3, generator=generator)).clamp(0, 1)
        image, target = image.to(device), target.to(device)
        record = {"benchmark": "ssim", "device": str(device), "size": f"{size}x{size}", "repeats": repeats,
                  "threads": torch.get_num_threads()}
        for name, ssim in methods.items():
            record[f"{name}_ms"] = round(median_ms(ssim, image, target, repeats), 3)
        record["warp_speedup_over_torch"] = round(record["torch_ms"] / record["warp_ms"], 2)
        record["load_average_before"] = load
        if device.type == "cuda":
            record["gpu"] = torch.cuda.get_device_name(device)
        C.emit(record)


if __name__ == "__main__":
    main()
