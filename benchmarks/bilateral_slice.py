"""The bilateral grid's slicing (`--appearance bilateral-grid`): forward + backward of the Warp kernels against
torch's grid_sample (`slice_reference`), one 16x16x8 grid, renders of 800x600 (the cup) and 544x960 (the bird).

    .venv/bin/python benchmarks/bilateral_slice.py
    .venv/bin/python benchmarks/bilateral_slice.py --threads 1 --repeats 21

Prints the median seconds of each over the repeats (the first, which compiles or warms up, left out).
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import statistics
import time
from dataclasses import dataclass

import torch
import tyro

import _common as C

SIZES = {"cup 800x600": (600, 800), "bird 544x960": (960, 544)}


@dataclass(frozen=True)
class Options:
    """The bilateral grid's slicing: the Warp kernels against torch's grid_sample."""

    threads: int | None = None
    """CPU threads of torch and the Warp launcher (default: torch's)."""
    repeats: int = 7
    """Timed calls of each (the median is printed)."""


def median_seconds(slicer, grid: torch.Tensor, rgb: torch.Tensor, repeats: int) -> float:
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        slicer(grid, rgb).sum().backward()
        times.append(time.perf_counter() - start)
    return statistics.median(times[1:])


def main() -> None:
    args = tyro.cli(Options, description=__doc__)

    from mcsplat.appearance import BilateralGridAppearance
    from mcsplat.appearance.slicing import slice_grid, slice_reference
    from mcsplat.compute.runtime import set_cpu_threads

    if args.threads:
        torch.set_num_threads(args.threads)
        set_cpu_threads(args.threads)
    generator = torch.Generator().manual_seed(0)
    identity = BilateralGridAppearance(1).grid(0).detach()
    grid = (identity + 0.05 * torch.randn(identity.shape, generator=generator)).requires_grad_()
    for label, (height, width) in SIZES.items():
        rgb = torch.rand(height, width, 3, generator=generator).requires_grad_()
        kernels = median_seconds(slice_grid, grid, rgb, args.repeats)
        reference = median_seconds(slice_reference, grid, rgb, args.repeats)
        C.emit({"image": label, "threads": torch.get_num_threads(), "warp_s": round(kernels, 4),
                "grid_sample_s": round(reference, 4), "speedup": round(reference / kernels, 2)})


if __name__ == "__main__":
    main()
