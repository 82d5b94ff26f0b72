"""Per-tile lists of Gaussians, sorted front to back: a stable sort by depth, then a stable sort by tile.

Each (tile, Gaussian) pair also carries a 16-bit mask of the 4x4-pixel blocks of the tile where the Gaussian can pass
the alpha >= 1/255 test; pixels skip pairs whose bit is clear, and pairs with an empty mask are dropped. The image is
unchanged (those pixels would fail the test anyway) but small splats no longer cost every pixel of their tiles.

The Gaussians are sorted by depth first (a radix sort of N keys; equal depths by Gaussian index). The non-empty pairs
of a Gaussian are the tiles of its rectangle that its alpha span reaches, a rectangle of tiles too, so a first kernel
counts them without walking them; a prefix sum in depth order gives every Gaussian its slots, and a second kernel
writes its pairs there front to back, keyed by their tile. A stable radix sort of the tile keys (one pass of 16 bits
up to 65,536 tiles) then groups the pairs by tile, each tile front to back, and a last kernel finds each tile's run.
In a training step the lists sit at the front of a room sized ahead (pair_room.py), its empty slots keyed past the
last tile so that they sort last: the step's launches then have sizes known before it, and nothing is read. One sort
of the pairs by (tile, depth) gives the same lists but needs three 16-bit passes over pairs that outnumber the
Gaussians ten to one, and walking every tile of the rectangle twice cost as much again (both shapes timed on the
cup's trained model: docs/measurements-log.md, "The coarse phase's length chosen by --budget, and binning by depth
then tile, 2026-11-26 (later)").

CUDA runs these Warp kernels and Warp's CUB radix sort; this shape has been checked on the CPU only (the tests compare
the lists with the torch binning's) until a GPU run is recorded in benchmarks/README.md ("GPU"). The CPU runs the
same steps as C++ loops over ranges of Gaussians (cpu_loops.py), with sorts of its own that order the pairs as the
radix sorts do: a radix sort of the depths fused with the offsets, and a counting sort by tile that writes the
lists (benchmarks/results/train_speed/2026-11-27-kernels-side-by-side.md and 2026-11-29-glue-side-by-side.md);
set_cpu_kernels("scalar") puts the Warp kernels back.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import warp as wp

from ...compute.runtime import cpu_threads, ensure_warp, flat_view, radix_sort_pairs, run_ranges, warp_view
from ..constants import ALL_BLOCKS, BLOCK_SIZE, TILE_SIZE
from . import cpu_loops, pair_room
from ..kernel_choice import cpu_kernels


@dataclass
class TileBins:
    gaussian_ids: torch.Tensor  # [P] int32: the Gaussian of each (tile, Gaussian) pair, grouped by tile, front to back
    tile_ranges: torch.Tensor   # [tiles_y * tiles_x, 2] int32: [start, end) into gaussian_ids for each tile
    pair_masks: torch.Tensor    # [P] int32: bit (by * 4 + bx) set when the Gaussian may reach 4x4 block (bx, by)
    tiles_x: int
    tiles_y: int
    # int64 [1] on the device, when the lists sit at the front of a room of fixed size (pair_room.py): the pairs
    # counted; P is then the room, and the slots past the count belong to no tile.
    count: torch.Tensor | None = None

    @property
    def num_pairs(self) -> int:
        """The pairs listed (read from the device when the lists sit in a room)."""
        if self.count is None:
            return int(self.gaussian_ids.shape[0])
        return min(int(self.count.reshape(())), int(self.gaussian_ids.shape[0]))

    def listed(self) -> TileBins:
        """The same lists with no room past them (what the torch binning gives; reads the count)."""
        if self.count is None:
            return self
        used = self.num_pairs
        return TileBins(self.gaussian_ids[:used], self.tile_ranges, self.pair_masks[:used], self.tiles_x, self.tiles_y)


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
def _tiles_touched(first: int, last: int, tile_min: int, tile_max: int):
    """The tiles [a, b) of the rectangle [tile_min, tile_max) that hold a pixel of the span [first, last]: exactly
    those where _block_mask is not 0."""
    if last < first or last < 0:
        return tile_min, tile_min
    return wp.max(tile_min, wp.max(first, 0) / TILE_SIZE), wp.min(tile_max, last / TILE_SIZE + 1)


@wp.func
def _pair_tiles(tile_min: wp.array2d(dtype=wp.int32), tile_max: wp.array2d(dtype=wp.int32),
                means2d: wp.array2d(dtype=float), alpha_extent: wp.array2d(dtype=float), i: int, use_masks: int):
    """The tiles of Gaussian i's non-empty pairs, [x0, x1) x [y0, y1), and its pixel span."""
    if use_masks == 0:
        return tile_min[i, 0], tile_max[i, 0], tile_min[i, 1], tile_max[i, 1], 0, 0, 0, 0
    first_x, last_x = _pixel_span(means2d[i, 0], alpha_extent[i, 0])
    first_y, last_y = _pixel_span(means2d[i, 1], alpha_extent[i, 1])
    x0, x1 = _tiles_touched(first_x, last_x, tile_min[i, 0], tile_max[i, 0])
    y0, y1 = _tiles_touched(first_y, last_y, tile_min[i, 1], tile_max[i, 1])
    return x0, x1, y0, y1, first_x, last_x, first_y, last_y


@wp.kernel
def _count_pairs(offset: int, tile_min: wp.array2d(dtype=wp.int32), tile_max: wp.array2d(dtype=wp.int32),
                 means2d: wp.array2d(dtype=float), alpha_extent: wp.array2d(dtype=float), use_masks: int,
                 counts: wp.array(dtype=wp.int32)):
    i = offset + wp.tid()
    x0, x1, y0, y1, first_x, last_x, first_y, last_y = _pair_tiles(tile_min, tile_max, means2d, alpha_extent, i,
                                                                   use_masks)
    counts[i] = wp.max(x1 - x0, 0) * wp.max(y1 - y0, 0)


@wp.kernel
def _write_pairs(offset: int, tile_min: wp.array2d(dtype=wp.int32), tile_max: wp.array2d(dtype=wp.int32),
                 means2d: wp.array2d(dtype=float), alpha_extent: wp.array2d(dtype=float), use_masks: int,
                 tiles_x: int, capacity: wp.int64, offsets: wp.array(dtype=wp.int64), tiles: wp.array(dtype=wp.int32),
                 pairs: wp.array(dtype=wp.int64)):
    """Each pair as its tile (the sort key) and its Gaussian with its block mask in the high 32 bits (the value); the
    pairs past the room's `capacity` slots are dropped (the farthest Gaussians': slots go front to back)."""
    i = offset + wp.tid()
    x0, x1, y0, y1, first_x, last_x, first_y, last_y = _pair_tiles(tile_min, tile_max, means2d, alpha_extent, i,
                                                                   use_masks)
    slot = offsets[i]
    for ty in range(y0, y1):
        for tx in range(x0, x1):
            mask = int(ALL_BLOCKS)
            if use_masks != 0:
                mask = _block_mask(first_x, last_x, first_y, last_y, tx, ty)
            if slot < capacity:
                tiles[slot] = ty * tiles_x + tx
                pairs[slot] = (wp.int64(mask) << wp.int64(32)) | wp.int64(i)
            slot += wp.int64(1)


@wp.kernel
def _tile_ranges(offset: int, tiles: wp.array(dtype=wp.int32), num_tiles: int, ranges: wp.array2d(dtype=wp.int32)):
    """[start, end) of each tile's run in the sorted tile keys; a tile without pairs gets [k, k), k where its run
    would start, as the torch binning gives it. The room's empty slots are keyed num_tiles: they sort last."""
    k = offset + wp.tid()
    last = tiles.shape[0] - 1
    tile = tiles[k]
    before = int(-1)
    if k > 0:
        before = tiles[k - 1]
    if tile != before:  # a run starts here: the tiles between the previous run's and this one have none
        for empty in range(before + 1, wp.min(tile, num_tiles)):
            ranges[empty, 0] = k
            ranges[empty, 1] = k
        if tile < num_tiles:
            ranges[tile, 0] = k
    if tile < num_tiles and (k == last or tiles[k + 1] != tile):
        ranges[tile, 1] = k + 1
        if k == last:  # a full room: the tiles after the last run have none
            for empty in range(tile + 1, num_tiles):
                ranges[empty, 0] = k + 1
                ranges[empty, 1] = k + 1


def _depth_order(depths: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """int32 [N]: the Gaussians front to back (the visible ones; the others anywhere), equal depths by index."""
    n, device = depths.shape[0], depths.device
    if depths.dtype == torch.float32:
        # Visible Gaussians lie in front of the near plane: positive floats order like their bit patterns.
        keys = torch.where(visible, depths.detach(), torch.zeros_like(depths)).view(torch.int32)
    else:  # float64: ranks keep every distinction of the depths
        order = torch.argsort(depths.detach(), stable=True)
        keys = torch.empty(n, dtype=torch.int32, device=device)
        keys[order] = torch.arange(n, dtype=torch.int32, device=device)
    sort_keys = torch.empty(2 * n, dtype=torch.int32, device=device)  # the radix sort's room for twice the items
    order = torch.empty(2 * n, dtype=torch.int32, device=device)
    sort_keys[:n] = keys
    torch.arange(n, dtype=torch.int32, device=device, out=order[:n])
    radix_sort_pairs(sort_keys, order, n, end_bit=31)
    return order[:n]


def bin_gaussians(tile_min: torch.Tensor, tile_max: torch.Tensor, depths: torch.Tensor, radii: torch.Tensor,
                  tiles_x: int, tiles_y: int, means2d: torch.Tensor | None = None,
                  alpha_extent: torch.Tensor | None = None) -> TileBins:
    """List, for every tile, the visible Gaussians whose tile rectangle covers it, nearest first.

    With `means2d` and `alpha_extent` (from the projection) each pair gets its block mask and empty pairs are
    dropped; without them every pair covers the whole tile. Culled Gaussians (radius 0) have empty rectangles.
    """
    ensure_warp()
    device = depths.device
    use_masks = means2d is not None and alpha_extent is not None
    if use_masks:
        spans = [means2d.float().contiguous(), alpha_extent.float().contiguous()]  # read by the kernels only
    else:
        spans = [torch.zeros(1, 2, device=device)] * 2
    rectangles = [t.contiguous() for t in (tile_min, tile_max)] + spans
    if device.type == "cpu" and cpu_kernels() == "simd":
        return _bin_on_cpu(rectangles, int(use_masks), depths, radii, tiles_x, tiles_y)
    return _bin_in_room([warp_view(t) for t in rectangles] + [int(use_masks)], depths, radii, tiles_x, tiles_y)


def _bin_in_room(rectangles: list, depths: torch.Tensor, radii: torch.Tensor, tiles_x: int,
                 tiles_y: int) -> TileBins:
    """bin_gaussians with the Warp kernels. In a training step (pair_room.sized_ahead) the lists go into the room of
    this image size: nothing is read back but the first count at a size, and every launch has a size known before
    the render; elsewhere the count is read and the lists are exactly as long."""
    device, n, num_tiles = depths.device, depths.shape[0], tiles_x * tiles_y
    counts = torch.zeros(n, dtype=torch.int32, device=device)
    run_ranges(_count_pairs, n, device, rectangles + [warp_view(counts)])
    order = _depth_order(depths, radii > 0).long() if n else torch.zeros(0, dtype=torch.int64, device=device)
    counts_front_to_back = counts[order]
    ends = torch.cumsum(counts_front_to_back, 0, dtype=torch.int64)  # each Gaussian's slots, front to back
    total = ends[-1:] if n else torch.zeros(1, dtype=torch.int64, device=device)
    room = pair_room.room(device, tiles_x, tiles_y, total, n) if pair_room.is_sized_ahead() else None
    capacity = room.size(n) if room is not None else int(total)  # outside a training step: read, every pair listed
    tiles, pairs = _pair_room(capacity, device)
    tiles[:capacity].fill_(num_tiles)  # a slot no pair reaches sorts after every tile
    if n:
        offsets = torch.empty(n, dtype=torch.int64, device=device)
        offsets[order] = ends - counts_front_to_back
        run_ranges(_write_pairs, n, device, rectangles + [tiles_x, capacity, warp_view(offsets), warp_view(tiles),
                                                          warp_view(pairs)])
    if room is not None:
        room.counted(total, n)
    if capacity:
        _sort_by_tile(tiles, pairs, capacity, num_tiles + 1)
    tiles, pairs = tiles[:capacity], pairs[:capacity]
    tile_ranges = torch.zeros(num_tiles, 2, dtype=torch.int32, device=device)
    run_ranges(_tile_ranges, capacity, device, [warp_view(tiles), num_tiles, warp_view(tile_ranges)])
    return TileBins((pairs & 0xFFFFFFFF).to(torch.int32), tile_ranges, (pairs >> 32).to(torch.int32), tiles_x, tiles_y,
                    count=total)


def _pair_room(total: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Tile keys and pair values for `total` pairs, with the room for twice as many that the radix sort needs."""
    return (torch.empty(2 * total, dtype=torch.int32, device=device),
            torch.empty(2 * total, dtype=torch.int64, device=device))


def _sort_by_tile(tiles: torch.Tensor, pairs: torch.Tensor, total: int, num_tiles: int) -> None:
    """A stable radix sort of the first `total` pairs by tile key, on as many bits as keys below `num_tiles` need."""
    radix_sort_pairs(tiles, pairs, total, end_bit=max(1, (num_tiles - 1).bit_length()))


def _bin_on_cpu(rectangles: list[torch.Tensor], use_masks: int, depths: torch.Tensor, radii: torch.Tensor,
                tiles_x: int, tiles_y: int) -> TileBins:
    """bin_gaussians with the CPU's C++ loops (cpu_loops.py), whose two sorts order the lists as the Warp path's radix
    sorts do: the same lists."""
    n, num_tiles = depths.shape[0], tiles_x * tiles_y
    views = [flat_view(t) for t in rectangles] + [use_masks]
    parts = max(1, min(cpu_threads(), n // 4096))  # each thread a range of Gaussians; ranges write their own
    counts = torch.empty(n, dtype=torch.int32)
    offsets = torch.empty(n, dtype=torch.int32)
    total = torch.zeros(1, dtype=torch.int64)
    if n:
        run_ranges(cpu_loops.count_pairs_cpu, parts, depths.device, [n, parts, *views, warp_view(counts)], 1)
        if depths.dtype == torch.float32:
            keys, order = torch.empty(2 * n, dtype=torch.int32), torch.empty(2 * n, dtype=torch.int32)  # sort's room
            wp.launch(cpu_loops.depth_slots_cpu, dim=1, device="cpu", inputs=[
                n, *map(flat_view, (depths.detach().contiguous(), radii.contiguous(), counts, keys, order, offsets,
                                    total))])
        else:  # float64 (the tests' renders): the ranks' order, the slots summed by torch
            order = _depth_order(depths, radii > 0).long()
            ends = torch.cumsum(counts[order], 0, dtype=torch.int64)
            offsets[order] = (ends - counts[order]).to(torch.int32)
            total[0] = ends[-1]
    count = total.item()  # read on the host: it sizes the pair lists (on the CPU, no wait)
    tiles, pairs = torch.empty(count, dtype=torch.int32), torch.empty(count, dtype=torch.int64)
    if count:
        run_ranges(cpu_loops.write_pairs_cpu, parts, depths.device,
                   [n, parts, *views, tiles_x, *map(warp_view, (offsets, tiles, pairs))], 1)
    gaussian_ids, pair_masks = torch.empty(count, dtype=torch.int32), torch.empty(count, dtype=torch.int32)
    tile_ranges = torch.empty(num_tiles, 2, dtype=torch.int32)
    wp.launch(cpu_loops.sort_split_cpu, dim=1, device="cpu", inputs=[
        count, num_tiles, *map(flat_view, (tiles, pairs, gaussian_ids, pair_masks, tile_ranges))])
    return TileBins(gaussian_ids, tile_ranges, pair_masks, tiles_x, tiles_y)
