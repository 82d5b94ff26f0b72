"""Slicing a bilateral grid: the colour transform of every pixel read from a grid of affine transforms, and its
backward, as Warp kernels (CPU and CUDA) beside a torch version (`slice_reference`) that the tests hold them to.

A grid [12, L, H', W'] holds a 3x4 affine colour transform [A | b] (channel 4 k + j is row k, column j) at each of
W' x H' places across the image and L levels of brightness. A pixel at column x, row y with colour c = (r, g, b)
reads the transform at (x / (W - 1) (W' - 1), y / (H - 1) (H' - 1), gray(c) (L - 1)), trilinearly interpolated, with
gray(c) = 0.299 r + 0.587 g + 0.114 b clamped to [0, 1] (torch's grid_sample with align_corners and border padding),
and becomes A c + b. The gradient reaches the grid (each pixel's 8 corners) and the colour, both through A and
through the brightness that chose the level.

torch's grid_sample does the same (`slice_reference`); forward and backward of an 800x600 render take it 0.25 s on
2 cores, these kernels (one thread per pixel) 0.056 s (benchmarks/bilateral_slice.py), against 0.15 s for a whole
training step of the cup at that size without a grid. On the CPU the pixels run as contiguous ranges from the
rasterizer's thread pool; in the backward each range adds its grid gradient into a buffer of its own and the buffers
are summed in range order, so the result does not depend on timing (on CUDA: one launch, atomic adds).

(No `from __future__ import annotations` here: Warp reads the kernels' annotations as live objects.)
"""

import functools

import torch
import torch.nn.functional as F
import warp as wp

from ..compute.runtime import cpu_threads, ensure_warp, launch_on_cuda, thread_pool, warp_scalar

LUMA = (0.299, 0.587, 0.114)  # the brightness that picks a pixel's level (Rec. 601 luma)
LUMA_R, LUMA_G, LUMA_B = LUMA
_MIN_PIXELS_PER_THREAD = 8192


def slice_reference(grid: torch.Tensor, rgb: torch.Tensor) -> torch.Tensor:
    """rgb [H, W, 3] through grid [12, L, H', W'], with torch's grid_sample (the definition; slow on the CPU)."""
    height, width, _ = rgb.shape
    gray = (rgb @ torch.tensor(LUMA, dtype=rgb.dtype, device=rgb.device)).clamp(0, 1)
    ys, xs = torch.meshgrid(torch.linspace(-1, 1, height, dtype=rgb.dtype, device=rgb.device),
                            torch.linspace(-1, 1, width, dtype=rgb.dtype, device=rgb.device), indexing="ij")
    where = torch.stack([xs, ys, gray * 2 - 1], dim=-1)[None, None]  # [1, 1, H, W, 3]: x, y, level
    coefficients = F.grid_sample(grid[None], where, mode="bilinear", padding_mode="border", align_corners=True)
    affine = coefficients[0, :, 0].permute(1, 2, 0).reshape(height, width, 3, 4)
    return (affine[..., :3] @ rgb[..., None])[..., 0] + affine[..., 3]


@functools.lru_cache(maxsize=None)
def _kernels(dtype):
    """(forward, backward) slicing kernels for scalar type wp.float32 or wp.float64."""
    vec3 = wp.types.vector(3, dtype)
    vec4 = wp.types.vector(4, dtype)

    @wp.func
    def lower_corner(at: dtype, size: int):
        """The cell of a coordinate in [0, size - 1]: its lower corner and the fraction beyond it."""
        corner = wp.min(wp.max(int(wp.floor(at)), 0), size - 2)
        return corner, at - dtype(corner)

    @wp.func
    def bilinear(grid: wp.array(dtype=dtype), start: int, columns: int, fx: dtype, fy: dtype):
        one = dtype(1.0)
        return ((one - fy) * ((one - fx) * grid[start] + fx * grid[start + 1])
                + fy * ((one - fx) * grid[start + columns] + fx * grid[start + columns + 1]))

    @wp.func
    def gray_of(color: vec3):
        return dtype(LUMA_R) * color[0] + dtype(LUMA_G) * color[1] + dtype(LUMA_B) * color[2]

    @wp.func
    def place(pixel: int, gray: dtype, width: int, height: int, levels: int, rows: int, columns: int):
        """Index of the pixel's lower grid corner in channel 0 and its fractions along x, y and the levels."""
        gx = dtype(pixel % width) * dtype(columns - 1) / dtype(wp.max(width - 1, 1))
        gy = dtype(pixel // width) * dtype(rows - 1) / dtype(wp.max(height - 1, 1))
        gz = wp.clamp(gray, dtype(0.0), dtype(1.0)) * dtype(levels - 1)
        x0, fx = lower_corner(gx, columns)
        y0, fy = lower_corner(gy, rows)
        z0, fz = lower_corner(gz, levels)
        return (z0 * rows + y0) * columns + x0, fx, fy, fz

    @wp.kernel(module="unique")
    def forward(offset: int, grid: wp.array(dtype=dtype), rgb: wp.array(dtype=vec3), width: int, height: int,
                levels: int, rows: int, columns: int, out: wp.array(dtype=vec3)):
        pixel = offset + wp.tid()
        color = rgb[pixel]
        corner, fx, fy, fz = place(pixel, gray_of(color), width, height, levels, rows, columns)
        plane = rows * columns
        channel = levels * plane
        one = dtype(1.0)
        homogeneous = vec4(color[0], color[1], color[2], one)
        result = vec3()
        for c in range(12):
            start = c * channel + corner
            value = ((one - fz) * bilinear(grid, start, columns, fx, fy)
                     + fz * bilinear(grid, start + plane, columns, fx, fy))
            result[c // 4] += value * homogeneous[c % 4]
        out[pixel] = result

    @wp.kernel(module="unique")
    def backward(offset: int, grid: wp.array(dtype=dtype), rgb: wp.array(dtype=vec3), grad_out: wp.array(dtype=vec3),
                 width: int, height: int, levels: int, rows: int, columns: int,
                 grad_grid: wp.array(dtype=dtype), grad_rgb: wp.array(dtype=vec3)):
        pixel = offset + wp.tid()
        color = rgb[pixel]
        gray = gray_of(color)
        corner, fx, fy, fz = place(pixel, gray, width, height, levels, rows, columns)
        plane = rows * columns
        channel = levels * plane
        one = dtype(1.0)
        homogeneous = vec4(color[0], color[1], color[2], one)
        upstream = grad_out[pixel]
        grad_color = vec3()
        grad_level = dtype(0.0)  # d loss / d (the level coordinate gray * (L - 1))
        for c in range(12):
            start = c * channel + corner
            below = bilinear(grid, start, columns, fx, fy)
            above = bilinear(grid, start + plane, columns, fx, fy)
            row = c // 4
            column = c % 4
            grad_value = upstream[row] * homogeneous[column]
            if column < 3:
                grad_color[column] += upstream[row] * ((one - fz) * below + fz * above)
            grad_level += grad_value * (above - below)
            for level in range(2):
                weight_z = grad_value * wp.where(level == 0, one - fz, fz)
                at = start + level * plane
                wp.atomic_add(grad_grid, at, weight_z * (one - fy) * (one - fx))
                wp.atomic_add(grad_grid, at + 1, weight_z * (one - fy) * fx)
                wp.atomic_add(grad_grid, at + columns, weight_z * fy * (one - fx))
                wp.atomic_add(grad_grid, at + columns + 1, weight_z * fy * fx)
        if gray > dtype(0.0) and gray < dtype(1.0):  # clamped brightness: the level does not move
            grad_gray = grad_level * dtype(levels - 1)
            grad_color += grad_gray * vec3(dtype(LUMA_R), dtype(LUMA_G), dtype(LUMA_B))
        grad_rgb[pixel] = grad_color

    return forward, backward


def _vec3_view(tensor: torch.Tensor) -> wp.array:
    return wp.from_torch(tensor.detach(), dtype=wp.types.vector(3, warp_scalar(tensor.dtype)), requires_grad=False)


def _flat_view(tensor: torch.Tensor) -> wp.array:
    return wp.from_torch(tensor.detach().reshape(-1), requires_grad=False)


def _pixel_ranges(pixels: int, device: torch.device) -> list[tuple[int, int]]:
    parts = 1 if device.type == "cuda" else max(1, min(cpu_threads(), pixels // _MIN_PIXELS_PER_THREAD))
    edges = [pixels * k // parts for k in range(parts + 1)]
    return list(zip(edges[:-1], edges[1:]))


def _launch_ranges(kernel, ranges: list[tuple[int, int]], arguments_for, device: torch.device) -> None:
    """Launch `kernel` once per pixel range (its first argument the range's first pixel), the ranges in parallel on
    the CPU; `arguments_for(part)` gives range `part`'s other arguments."""
    if device.type == "cuda":
        first, last = ranges[0]
        launch_on_cuda(kernel, last - first, [first] + arguments_for(0), device)
        return

    def run(part: int) -> None:
        first, last = ranges[part]
        wp.launch(kernel, dim=last - first, inputs=[first] + arguments_for(part), device="cpu")

    if len(ranges) == 1:
        run(0)
    else:
        for future in [thread_pool(len(ranges)).submit(run, part) for part in range(len(ranges))]:
            future.result()


class _SliceFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, grid, rgb):
        grid, rgb = grid.contiguous(), rgb.contiguous()
        height, width, _ = rgb.shape
        _, levels, rows, columns = grid.shape
        forward_kernel, _ = _kernels(warp_scalar(rgb.dtype))
        out = torch.empty_like(rgb)
        sizes = [width, height, levels, rows, columns]
        ranges = _pixel_ranges(height * width, rgb.device)
        arguments = [_flat_view(grid), _vec3_view(rgb.view(-1, 3))] + sizes + [_vec3_view(out.view(-1, 3))]
        _launch_ranges(forward_kernel, ranges, lambda part: arguments, rgb.device)
        ctx.save_for_backward(grid, rgb)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        grid, rgb = ctx.saved_tensors
        height, width, _ = rgb.shape
        _, levels, rows, columns = grid.shape
        _, backward_kernel = _kernels(warp_scalar(rgb.dtype))
        ranges = _pixel_ranges(height * width, rgb.device)
        grad_parts = torch.zeros((len(ranges), grid.numel()), dtype=grid.dtype, device=grid.device)
        grad_rgb = torch.empty_like(rgb)
        shared = [_flat_view(grid), _vec3_view(rgb.view(-1, 3)), _vec3_view(grad_out.contiguous().view(-1, 3)),
                  width, height, levels, rows, columns]
        views = [_flat_view(grad_parts[part]) for part in range(len(ranges))]
        rgb_view = _vec3_view(grad_rgb.view(-1, 3))
        _launch_ranges(backward_kernel, ranges, lambda part: shared + [views[part], rgb_view], rgb.device)
        grad_grid = grad_parts[0] if len(ranges) == 1 else grad_parts.sum(dim=0)
        return grad_grid.view_as(grid), grad_rgb


def slice_grid(grid: torch.Tensor, rgb: torch.Tensor) -> torch.Tensor:
    """rgb [H, W, 3] through grid [12, L, H', W'] (float32 or float64, on the CPU or CUDA), differentiable in both."""
    if grid.dim() != 4 or grid.shape[0] != 12 or min(grid.shape[1:]) < 2:
        raise ValueError(f"a bilateral grid is [12, levels, rows, columns] with at least 2 of each, got {grid.shape}")
    ensure_warp()
    return _SliceFunction.apply(grid, rgb.to(grid.dtype))


def slicing_kernels(dtype: torch.dtype = torch.float32) -> list:
    """The Warp kernels a training step with a bilateral grid launches (compiled before the first step)."""
    return list(_kernels(warp_scalar(dtype)))
