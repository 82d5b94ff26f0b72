"""Rasterizer speed and memory: one JSON line per configuration (medians over repeats).

    .venv/bin/python benchmarks/rasterizer.py                      # the default grid on CPU
    .venv/bin/python benchmarks/rasterizer.py --sizes 100000 --resolutions 400 --threads 1 2
    python benchmarks/rasterizer.py --device cuda --cuda-kernels tile tile-all scalar   # the CUDA kernels side by side

Scene: N Gaussians in a ball in front of the camera, scaled so that about 32 Gaussians are composited per pixel at
100k and 400x400 (the reference configuration of the targets). Timed separately: the compositing kernels alone
(forward, backward) and the whole render + backward (projection, SH, binning, compositing, autograd). On the CPU the
same scene is also timed, in the same process, through the kernels as they were before the SIMD work (the scalar
compositing kernels; torch projection, SH and binning), and the speed-ups are reported as ratios. On CUDA,
`--cuda-kernels` times each named set of compositing kernels (render/kernel_choice.py's set_cuda_kernels) on the same
bins, as `<name>_composite_forward_ms` / `<name>_composite_backward_ms`; the first named also runs the whole render.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import json
import math
import platform
import resource
import statistics
import time
from dataclasses import dataclass
from typing import Annotated, Literal

import torch
import tyro

from mcsplat.camera import Camera, intrinsics
from mcsplat.render import Splats, render, set_cpu_threads
from mcsplat.render.bin.warp_kernels import bin_gaussians
from mcsplat.render.composite.function import CompositeFunction, cuda_kernels, set_cpu_kernels, set_cuda_kernels
from mcsplat.render.paths import TORCH_BASELINE_PATH, use_render_path
from mcsplat.render.constants import ALPHA_MAX, ALPHA_MIN, BLOCK_SIZE, TILE_SIZE, TRANSMITTANCE_MIN
from mcsplat.render.project.torch_autograd import project_gaussians, view_dependent_colors


@dataclass(frozen=True)
class Options:
    """Rasterizer speed and memory: one JSON line per configuration."""

    sizes: tuple[int, ...] = (20_000, 100_000, 300_000)
    """Numbers of Gaussians."""
    resolutions: tuple[int, ...] = (400, 800)
    """Square image sides."""
    threads: tuple[int, ...] = (1, torch.get_num_threads())
    """CPU threads (on CUDA: 1)."""
    device: str = "cpu"
    """cpu or cuda."""
    repeats: int = 5
    """Timed calls of each (medians)."""
    cuda_kernels: tuple[Literal["tile", "tile-all", "scalar"], ...] = ("tile",)
    """On CUDA: the compositing kernels to time side by side (the first is the main record)."""
    no_baseline: Annotated[bool, tyro.conf.FlagCreatePairsOff] = False
    """Skip the in-process baseline (the scalar kernels and the torch projection/binning)."""


def make_scene(n: int, size: int, device: str, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    means = direction * torch.rand(n, 1, generator=g) ** (1 / 3)
    # Scale shrinks as N grows so the per-pixel depth complexity stays comparable across sizes.
    base = 0.007 * (100_000 / n) ** (1 / 3)
    scales = base * torch.exp(torch.randn(n, 3, generator=g) * 0.3)
    splats = Splats(means=means, quats=torch.randn(n, 4, generator=g), scales=scales,
                    opacities=torch.rand(n, generator=g) * 0.6 + 0.05, sh=torch.randn(n, 16, 3, generator=g) * 0.3)
    splats = Splats(*(t.to(device).requires_grad_() for t in (splats.means, splats.quats, splats.scales,
                                                             splats.opacities, splats.sh)))
    focal = size * 1.2
    w2c = torch.eye(4)
    w2c[2, 3] = 2.8
    camera = Camera(K=intrinsics(focal, focal, size / 2, size / 2), world_to_camera=w2c, width=size, height=size)
    return splats, camera.to(device)


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def timed(fn, device: str, repeats: int) -> list[float]:
    times = []
    for _ in range(repeats):
        sync(device)
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append((time.perf_counter() - t0) * 1000.0)
    return times


def bench(n: int, size: int, threads: int, device: str, repeats: int, baseline: bool = True,
          cuda_variants: tuple[str, ...] = ("tile",)) -> dict:
    set_cpu_threads(threads)
    torch.set_num_threads(threads)
    splats, camera = make_scene(n, size, device)
    background = torch.zeros(3, device=device)

    # Compositing alone, on fixed projected inputs.
    with torch.no_grad():
        proj = project_gaussians(splats.means, splats.quats, splats.scales, splats.opacities, camera)
        colors = view_dependent_colors(splats.means, splats.sh, camera, 3)
        tiles = (math.ceil(size / TILE_SIZE), math.ceil(size / TILE_SIZE))
        bins = bin_gaussians(proj.tile_min, proj.tile_max, proj.depths, proj.radii, *tiles, means2d=proj.means2d,
                             alpha_extent=proj.alpha_extent)
    inputs = [t.detach().clone().requires_grad_() for t in (proj.means2d, proj.conics, splats.opacities, colors,
                                                            proj.depths)]
    grad_rgb = torch.rand(size, size, 3, device=device)

    def composite_times(kernels: str) -> tuple[list[float], list[float]]:
        if device == "cpu":
            set_cpu_kernels(kernels)
        else:
            set_cuda_kernels(kernels)
        state = {}

        def forward_only():
            state["out"] = CompositeFunction.apply(*inputs, background, bins, size, size)

        def backward_only():
            torch.autograd.backward(state["out"][0], grad_rgb, inputs=inputs)

        forward_only()  # compile / warm up
        backward_only()
        fwd, bwd = [], []
        for _ in range(repeats):
            fwd += timed(forward_only, device, 1)
            bwd += timed(backward_only, device, 1)
        set_cpu_kernels("simd")
        set_cuda_kernels(cuda_variants[0])
        return fwd, bwd

    def full_step():
        out = render(splats, camera, background, 3)
        (out.rgb * grad_rgb).sum().backward()

    variant_times = {name: composite_times(name) for name in cuda_variants[1:]} if device != "cpu" else {}
    fwd, bwd = composite_times("simd" if device == "cpu" else cuda_variants[0])
    full_step()
    full = timed(full_step, device, repeats)
    peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # before the baseline runs
    record_baseline = baseline and device == "cpu"
    if record_baseline:  # the same scene through the kernels as they were, in this process
        base_fwd, base_bwd = composite_times("scalar")
        with use_render_path(TORCH_BASELINE_PATH):
            full_step()
            base_full = timed(full_step, device, repeats)

    walked, composited = _per_pixel_counts(bins, inputs, size)
    record = {
        "device": device if device != "cpu" else f"cpu ({platform.processor() or platform.machine()})",
        "gaussians": n, "image": f"{size}x{size}", "threads": threads if device == "cpu" else None,
        "visible": int((proj.radii > 0).sum()), "tile_pairs": bins.num_pairs,
        "evaluated_per_pixel": round(walked, 1), "composited_per_pixel": round(composited, 1),
        "composite_forward_ms": round(statistics.median(fwd), 3),
        "composite_backward_ms": round(statistics.median(bwd), 3),
        "composite_total_ms": round(statistics.median(fwd) + statistics.median(bwd), 3),
        "render_forward_backward_ms": round(statistics.median(full), 3),
        "repeats": repeats,
    }
    if device != "cpu":
        record["cuda_kernels"] = cuda_kernels()
        for name, (variant_fwd, variant_bwd) in variant_times.items():
            record[f"{name}_composite_forward_ms"] = round(statistics.median(variant_fwd), 3)
            record[f"{name}_composite_backward_ms"] = round(statistics.median(variant_bwd), 3)
    if record_baseline:
        base_total = statistics.median(base_fwd) + statistics.median(base_bwd)
        record.update({
            "baseline_composite_total_ms": round(base_total, 1),
            "composite_speedup": round(base_total / (statistics.median(fwd) + statistics.median(bwd)), 2),
            "baseline_render_forward_backward_ms": round(statistics.median(base_full), 1),
            "render_speedup": round(statistics.median(base_full) / statistics.median(full), 2)})
    if device == "cpu":
        record["peak_rss_mb"] = round(peak_rss_mb, 1)
    else:
        record["peak_cuda_mb"] = round(torch.cuda.max_memory_allocated() / 2 ** 20, 1)
    return record


def _per_pixel_counts(bins, inputs, size, samples: int = 400) -> tuple[float, float]:
    """(evaluated, composited) Gaussians per pixel, averaged over sampled pixels, by the kernel's own rules.

    Evaluated: list entries whose block bit is set for the pixel, up to where the walk stops (the exp-or-skip work)."""
    means2d, conics, opacities = (t.detach().cpu() for t in inputs[:3])
    ranges, ids, masks = bins.tile_ranges.cpu(), bins.gaussian_ids.cpu().long(), bins.pair_masks.cpu()
    g = torch.Generator().manual_seed(1)
    walked = composited = 0
    for px, py in torch.randint(0, size, (samples, 2), generator=g).tolist():
        start, end = ranges[(py // TILE_SIZE) * bins.tiles_x + px // TILE_SIZE].tolist()
        bit = 1 << (((py % TILE_SIZE) // BLOCK_SIZE) * BLOCK_SIZE + (px % TILE_SIZE) // BLOCK_SIZE)
        k = ids[start:end][(masks[start:end] & bit) != 0]
        d = means2d[k] - torch.tensor([px + 0.5, py + 0.5])
        q = conics[k]
        power = -0.5 * (q[:, 0] * d[:, 0] ** 2 + q[:, 2] * d[:, 1] ** 2) - q[:, 1] * d[:, 0] * d[:, 1]
        alpha = torch.clamp(opacities[k] * torch.exp(power), max=ALPHA_MAX)
        used = (power <= 0) & (alpha >= ALPHA_MIN)
        t_after = torch.cumprod(torch.where(used, 1 - alpha, torch.ones_like(alpha)), 0)
        included = used & (t_after >= TRANSMITTANCE_MIN)
        stop = torch.nonzero(used & (t_after < TRANSMITTANCE_MIN))
        walked += int(stop[0]) + 1 if stop.numel() else k.numel()
        composited += int(included.sum())
    return walked / samples, composited / samples


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    threads = sorted(set(args.threads)) if args.device == "cpu" else [1]
    for size in args.resolutions:
        for n in args.sizes:
            for t in threads:
                print(json.dumps(bench(n, size, t, args.device, args.repeats, not args.no_baseline,
                                       args.cuda_kernels)), flush=True)


if __name__ == "__main__":
    main()
