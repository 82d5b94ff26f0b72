"""The binning in plain torch, as it was before warp_kernels.py was written: the tests' oracle and the benchmarks'
baseline, never used for rendering. Sorting by (tile, depth rank), ties broken by index, and the 4x4-block masks of
each (tile, Gaussian) pair, with the same results as warp_kernels.py."""

from __future__ import annotations

import torch

from .warp_kernels import TileBins
from ..constants import ALL_BLOCKS, BLOCK_SIZE, TILE_SIZE


def torch_bin_gaussians(tile_min: torch.Tensor, tile_max: torch.Tensor, depths: torch.Tensor, radii: torch.Tensor,
                        tiles_x: int, tiles_y: int, means2d: torch.Tensor | None = None,
                        alpha_extent: torch.Tensor | None = None) -> TileBins:
    """List, for every tile, the visible Gaussians whose tile rectangle covers it, nearest first.

    With `means2d` and `alpha_extent` (from the projection) each pair gets its block mask and empty pairs are
    dropped; without them every pair covers the whole tile.
    """
    device = depths.device
    num_tiles = tiles_x * tiles_y
    visible = torch.nonzero(radii > 0).squeeze(1)
    if visible.numel() == 0:
        return TileBins(torch.zeros(0, dtype=torch.int32, device=device),
                        torch.zeros(num_tiles, 2, dtype=torch.int32, device=device),
                        torch.zeros(0, dtype=torch.int32, device=device), tiles_x, tiles_y)

    # Depth rank among the visible Gaussians; ties broken by index so the order is deterministic.
    order = torch.argsort(depths[visible].detach(), stable=True)
    depth_rank = torch.empty_like(order)
    depth_rank[order] = torch.arange(order.numel(), device=device)

    lo, hi = tile_min[visible].long(), tile_max[visible].long()
    span_x = hi[:, 0] - lo[:, 0]
    counts = span_x * (hi[:, 1] - lo[:, 1])
    total = int(counts.sum())
    owner = torch.repeat_interleave(torch.arange(visible.numel(), device=device), counts, output_size=total)
    first = torch.cumsum(counts, 0) - counts
    offset = torch.arange(total, device=device) - first[owner]
    tile_x = lo[owner, 0] + offset % span_x[owner]
    tile_y = lo[owner, 1] + offset // span_x[owner]
    tile_id = tile_y * tiles_x + tile_x

    if means2d is not None and alpha_extent is not None:
        gaussian = visible[owner]
        masks = _block_masks(means2d.detach()[gaussian], alpha_extent[gaussian], tile_x, tile_y)
        useful = masks != 0
        owner, tile_id, masks = owner[useful], tile_id[useful], masks[useful]
    else:
        masks = torch.full_like(tile_id, ALL_BLOCKS)

    keys = tile_id * visible.numel() + depth_rank[owner]  # unique, so any sort gives the same order
    keys, perm = torch.sort(keys)
    gaussian_ids = visible[owner[perm]].to(torch.int32)
    pair_masks = masks[perm].to(torch.int32)
    sorted_tiles = keys // visible.numel()
    per_tile = torch.bincount(sorted_tiles, minlength=num_tiles)
    ends = torch.cumsum(per_tile, 0)
    tile_ranges = torch.stack([ends - per_tile, ends], dim=-1).to(torch.int32)
    return TileBins(gaussian_ids, tile_ranges, pair_masks, tiles_x, tiles_y)


def _block_masks(means2d: torch.Tensor, extent: torch.Tensor, tile_x: torch.Tensor, tile_y: torch.Tensor
                 ) -> torch.Tensor:
    """16-bit masks of the 4x4 blocks of each pair's tile whose pixel centres fall in the Gaussian's alpha box."""
    origin = torch.stack([tile_x, tile_y], dim=-1) * TILE_SIZE
    # Pixel p has its centre at p + 0.5: the covered pixel indices are ceil(m - h - 0.5) .. floor(m + h - 0.5).
    first = torch.ceil(means2d - extent - 0.5).clamp(-1e9, 1e9).long() - origin
    last = torch.floor(means2d + extent - 0.5).clamp(-1e9, 1e9).long() - origin
    empty = ((last < 0) | (first > TILE_SIZE - 1) | (last < first)).any(dim=-1)
    block_first = first.clamp(0, TILE_SIZE - 1) // BLOCK_SIZE
    block_last = last.clamp(0, TILE_SIZE - 1) // BLOCK_SIZE
    row = (1 << (block_last[:, 0] + 1)) - (1 << block_first[:, 0])  # bits block_first_x .. block_last_x
    masks = torch.zeros_like(row)
    for by in range(TILE_SIZE // BLOCK_SIZE):
        inside = (block_first[:, 1] <= by) & (by <= block_last[:, 1])
        masks |= torch.where(inside, row << (BLOCK_SIZE * by), torch.zeros_like(row))
    return torch.where(empty, torch.zeros_like(masks), masks)
