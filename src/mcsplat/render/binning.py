"""Per-tile lists of Gaussians, sorted front to back: one sort on a (tile, depth rank) key."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class TileBins:
    gaussian_ids: torch.Tensor  # [P] int32: Gaussian index of each (tile, Gaussian) pair, grouped by tile, front to back
    tile_ranges: torch.Tensor   # [tiles_y * tiles_x, 2] int32: [start, end) into gaussian_ids for each tile
    tiles_x: int
    tiles_y: int

    @property
    def num_pairs(self) -> int:
        return int(self.gaussian_ids.shape[0])


def bin_gaussians(tile_min: torch.Tensor, tile_max: torch.Tensor, depths: torch.Tensor, radii: torch.Tensor,
                  tiles_x: int, tiles_y: int) -> TileBins:
    """List, for every tile, the visible Gaussians whose tile rectangle covers it, nearest first."""
    device = depths.device
    num_tiles = tiles_x * tiles_y
    visible = torch.nonzero(radii > 0).squeeze(1)
    if visible.numel() == 0:
        return TileBins(torch.zeros(0, dtype=torch.int32, device=device),
                        torch.zeros(num_tiles, 2, dtype=torch.int32, device=device), tiles_x, tiles_y)

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

    keys = tile_id * visible.numel() + depth_rank[owner]  # unique, so any sort gives the same order
    keys, perm = torch.sort(keys)
    gaussian_ids = visible[owner[perm]].to(torch.int32)
    sorted_tiles = keys // visible.numel()
    per_tile = torch.bincount(sorted_tiles, minlength=num_tiles)
    ends = torch.cumsum(per_tile, 0)
    tile_ranges = torch.stack([ends - per_tile, ends], dim=-1).to(torch.int32)
    return TileBins(gaussian_ids, tile_ranges, tiles_x, tiles_y)
