"""Per-tile lists of Gaussians, sorted front to back: one stable radix sort on a (tile, depth) key.

Each (tile, Gaussian) pair also carries a 16-bit mask of the 4x4-pixel blocks of the tile where the Gaussian can pass
the alpha >= 1/255 test; pixels skip pairs whose bit is clear, and pairs with an empty mask are dropped. The image is
unchanged (those pixels would fail the test anyway) but small splats no longer cost every pixel of their tiles.

Two Warp kernels walk each visible Gaussian's tile rectangle: the first counts its non-empty pairs, the second (after
a prefix sum gives every Gaussian its slot) writes them in Gaussian order with the key (tile << 32) | depth key. A
stable radix sort of the keys (only the bits in use) then orders each tile front to back, equal depths by
Gaussian index.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import warp as wp

from ..compute.runtime import ensure_warp, run_ranges, warp_view
from .constants import ALL_BLOCKS, BLOCK_SIZE, TILE_SIZE


@dataclass
class TileBins:
    gaussian_ids: torch.Tensor  # [P] int32: Gaussian index of each (tile, Gaussian) pair, grouped by tile, front to back
    tile_ranges: torch.Tensor   # [tiles_y * tiles_x, 2] int32: [start, end) into gaussian_ids for each tile
    pair_masks: torch.Tensor    # [P] int32: bit (by * 4 + bx) set when the Gaussian may reach 4x4 block (bx, by)
    tiles_x: int
    tiles_y: int

    @property
    def num_pairs(self) -> int:
        return int(self.gaussian_ids.shape[0])


_PIXEL_LIMIT = 1.0e9  # pixel bounds are clamped here before the conversion to int (far-off splats)


@wp.func
def _pixel_span(mean: float, extent: float):
    """First and last pixel index whose centre (p + 0.5) lies within [mean - extent, mean + extent]."""
    first = wp.ceil(wp.clamp(mean - extent - 0.5, -_PIXEL_LIMIT, _PIXEL_LIMIT))
    last = wp.floor(wp.clamp(mean + extent - 0.5, -_PIXEL_LIMIT, _PIXEL_LIMIT))
    return int(first), int(last)


@wp.func
def _block_mask(first_x: int, last_x: int, first_y: int, last_y: int, tile_x: int, tile_y: int):
    """Mask of the tile's 4x4 blocks that hold a pixel of the span (0 when the span misses the tile)."""
    fx = first_x - tile_x * TILE_SIZE
    lx = last_x - tile_x * TILE_SIZE
    fy = first_y - tile_y * TILE_SIZE
    ly = last_y - tile_y * TILE_SIZE
    if lx < 0 or fx > TILE_SIZE - 1 or lx < fx or ly < 0 or fy > TILE_SIZE - 1 or ly < fy:
        return 0
    bfx = wp.clamp(fx, 0, TILE_SIZE - 1) / BLOCK_SIZE
    blx = wp.clamp(lx, 0, TILE_SIZE - 1) / BLOCK_SIZE
    bfy = wp.clamp(fy, 0, TILE_SIZE - 1) / BLOCK_SIZE
    bly = wp.clamp(ly, 0, TILE_SIZE - 1) / BLOCK_SIZE
    row = (1 << (blx + 1)) - (1 << bfx)
    mask = int(0)
    for by in range(bfy, bly + 1):
        mask = mask | (row << (BLOCK_SIZE * by))
    return mask


@wp.func
def _spans(means2d: wp.array2d(dtype=float), alpha_extent: wp.array2d(dtype=float), i: int, use_masks: int):
    if use_masks == 0:
        return 0, 0, 0, 0
    first_x, last_x = _pixel_span(means2d[i, 0], alpha_extent[i, 0])
    first_y, last_y = _pixel_span(means2d[i, 1], alpha_extent[i, 1])
    return first_x, last_x, first_y, last_y


@wp.kernel
def _count_pairs(offset: int, tile_min: wp.array2d(dtype=wp.int32), tile_max: wp.array2d(dtype=wp.int32),
                 means2d: wp.array2d(dtype=float), alpha_extent: wp.array2d(dtype=float), use_masks: int,
                 counts: wp.array(dtype=wp.int32)):
    i = offset + wp.tid()
    first_x, last_x, first_y, last_y = _spans(means2d, alpha_extent, i, use_masks)
    count = int(0)
    for ty in range(tile_min[i, 1], tile_max[i, 1]):
        for tx in range(tile_min[i, 0], tile_max[i, 0]):
            if use_masks == 0 or _block_mask(first_x, last_x, first_y, last_y, tx, ty) != 0:
                count += 1
    counts[i] = count


@wp.kernel
def _write_pairs(offset: int, tile_min: wp.array2d(dtype=wp.int32), tile_max: wp.array2d(dtype=wp.int32),
                 means2d: wp.array2d(dtype=float), alpha_extent: wp.array2d(dtype=float), use_masks: int,
                 depth_keys: wp.array(dtype=wp.int64), tiles_x: int, offsets: wp.array(dtype=wp.int32),
                 keys: wp.array(dtype=wp.int64), gaussian_ids: wp.array(dtype=wp.int32),
                 masks: wp.array(dtype=wp.int32)):
    i = offset + wp.tid()
    first_x, last_x, first_y, last_y = _spans(means2d, alpha_extent, i, use_masks)
    slot = offsets[i]
    for ty in range(tile_min[i, 1], tile_max[i, 1]):
        for tx in range(tile_min[i, 0], tile_max[i, 0]):
            mask = int(ALL_BLOCKS)
            if use_masks != 0:
                mask = _block_mask(first_x, last_x, first_y, last_y, tx, ty)
            if mask != 0:
                keys[slot] = (wp.int64(ty * tiles_x + tx) << wp.int64(32)) | depth_keys[i]
                gaussian_ids[slot] = i
                masks[slot] = mask
                slot += 1


def _depth_keys(depths: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """int64 [N] in [0, 2^31), ordered like the depths of the visible Gaussians (any value for the others)."""
    if depths.dtype == torch.float32:
        # Visible Gaussians lie in front of the near plane: positive floats order like their bit patterns.
        return torch.where(visible, depths.detach(), torch.zeros_like(depths)).view(torch.int32).to(torch.int64)
    order = torch.argsort(depths.detach(), stable=True)  # float64: ranks keep every distinction of the depths
    ranks = torch.empty_like(order)
    ranks[order] = torch.arange(order.numel(), device=depths.device)
    return ranks


def bin_gaussians(tile_min: torch.Tensor, tile_max: torch.Tensor, depths: torch.Tensor, radii: torch.Tensor,
                  tiles_x: int, tiles_y: int, means2d: torch.Tensor | None = None,
                  alpha_extent: torch.Tensor | None = None) -> TileBins:
    """List, for every tile, the visible Gaussians whose tile rectangle covers it, nearest first.

    With `means2d` and `alpha_extent` (from the projection) each pair gets its block mask and empty pairs are
    dropped; without them every pair covers the whole tile. Culled Gaussians (radius 0) have empty rectangles.
    """
    ensure_warp()
    device = depths.device
    n, num_tiles = depths.shape[0], tiles_x * tiles_y
    use_masks = means2d is not None and alpha_extent is not None
    if use_masks:
        spans = [means2d.detach().float().contiguous(), alpha_extent.detach().float().contiguous()]
    else:
        spans = [torch.zeros(1, 2, device=device)] * 2
    rectangles = [warp_view(t.contiguous()) for t in (tile_min, tile_max)]
    rectangles += [warp_view(t) for t in spans] + [int(use_masks)]
    counts = torch.zeros(n, dtype=torch.int32, device=device)
    run_ranges(_count_pairs, n, device, rectangles + [warp_view(counts)])
    ends = torch.cumsum(counts, 0, dtype=torch.int64)
    total = int(ends[-1]) if n else 0
    # The radix sort needs room for twice the pairs; the pair's slot rides along as the value.
    keys = torch.empty(2 * total, dtype=torch.int64, device=device)
    slots = torch.empty(2 * total, dtype=torch.int32, device=device)
    ids = torch.empty(total, dtype=torch.int32, device=device)
    masks = torch.empty(total, dtype=torch.int32, device=device)
    if total:
        offsets = (ends - counts).to(torch.int32)
        run_ranges(_write_pairs, n, device, rectangles + [
            warp_view(_depth_keys(depths, radii > 0)), tiles_x, warp_view(offsets), warp_view(keys),
            warp_view(ids), warp_view(masks)])
        torch.arange(total, dtype=torch.int32, device=device, out=slots[:total])
        wp.utils.radix_sort_pairs(wp.from_torch(keys), wp.from_torch(slots), total,
                                  end_bit=32 + max(1, (num_tiles - 1).bit_length()))
    keys, order = keys[:total], slots[:total].long()
    per_tile = torch.bincount(keys >> 32, minlength=num_tiles)
    tile_ends = torch.cumsum(per_tile, 0)
    tile_ranges = torch.stack([tile_ends - per_tile, tile_ends], dim=-1).to(torch.int32)
    return TileBins(ids[order], tile_ranges, masks[order], tiles_x, tiles_y)
