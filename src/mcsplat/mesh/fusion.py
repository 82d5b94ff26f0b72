"""Truncated signed distance fusion (Curless & Levoy 1996) of depth maps into a VoxelGrid, in torch on the volume's
device.

A grid point seen by a view at camera depth z, in front of the pixel's depth d or at most the truncation t behind it,
takes the observation min(1, (d - z) / t) into its running mean; farther behind it is hidden and left alone. An
observation of 1 (the point is a band or more in front: the view says only that it is empty) counts `free_weight`
(1 by default) beside one within the band. Given the view's clear depth (clear_space.py), it vouches for empty space
only a band or more in front of that, and leaves the grid points between there and its surface's band alone. The
running mean of the pixel's colour goes with it. Pixels without a surface (depth -inf) update nothing. The volume is
walked in slabs of the first axis, so that the temporaries stay small whatever the grid.
"""

from __future__ import annotations

import torch

from ..camera import Camera
from ..render.constants import NEAR_PLANE
from .grid import VoxelGrid

SLAB_VOXELS = 1 << 20  # grid points per slab
GAP_PASSES = 2         # fill_gaps: gaps up to about twice this many voxels wide close
GAP_NEIGHBOURS = 2     # fill_gaps: observed face neighbours an unobserved point needs
GAP_WEIGHT = 1e-3      # fill_gaps: the weight a filled point gets (observed, but by no view)


class TSDFVolume:
    def __init__(self, grid: VoxelGrid, device: torch.device, free_weight: float = 1.0):
        self.grid, self.device, self.free_weight = grid, device, free_weight
        self.tsdf = torch.ones(grid.shape, dtype=torch.float32, device=device)   # in units of the truncation
        self.weight = torch.zeros(grid.shape, dtype=torch.float32, device=device)  # observations so far
        self.color = torch.zeros((*grid.shape, 3), dtype=torch.float16, device=device)

    @torch.no_grad()
    def integrate(self, camera: Camera, depth: torch.Tensor, rgb: torch.Tensor,
                  clear_depth: torch.Tensor | None = None) -> None:
        """Fuse one view: `depth` [H, W] camera depth of the surface (-inf where there is none), `rgb` [H, W, 3];
        `clear_depth` [H, W] (at most `depth`): the view vouches for empty space only a band or more in front of it
        (None: of `depth`)."""
        grid, device = self.grid, self.device
        nx, ny, nz = grid.shape
        height, width = depth.shape
        # A border of pixels without a surface: grid points that project outside the image land on it.
        framed_depth = torch.full((height + 2, width + 2), -float("inf"), device=device)
        framed_depth[1:-1, 1:-1] = depth
        framed_rgb = torch.zeros((height + 2, width + 2, 3), device=device)
        framed_rgb[1:-1, 1:-1] = rgb
        framed_depth, framed_rgb = framed_depth.reshape(-1), framed_rgb.reshape(-1, 3)
        if clear_depth is not None:
            framed_clear = torch.full((height + 2, width + 2), -float("inf"), device=device)
            framed_clear[1:-1, 1:-1] = clear_depth
            framed_clear = framed_clear.reshape(-1)
        w2c = camera.world_to_camera.to(device, torch.float64)
        rotation = w2c[:3, :3]
        # Camera coordinates of grid point (i, j, k): base + i a + j b + k c, each axis's term computed once.
        base = rotation @ torch.tensor(grid.origin, dtype=torch.float64, device=device) + w2c[:3, 3]
        steps = rotation * grid.voxel_size  # columns: a, b, c
        j = torch.arange(ny, device=device, dtype=torch.float64)[:, None]
        k = torch.arange(nz, device=device, dtype=torch.float64)[None, :]
        plane = [(base[r] + steps[r, 1] * j + steps[r, 2] * k).float()[None] for r in range(3)]  # [1, ny, nz]
        step_i = [float(steps[r, 0]) for r in range(3)]
        truncation = grid.truncation
        slab = max(1, SLAB_VOXELS // (ny * nz))
        for x0 in range(0, nx, slab):
            x1 = min(nx, x0 + slab)
            if not self._slab_in_view(base, steps, x0, x1, camera):
                continue
            i = torch.arange(x0, x1, device=device, dtype=torch.float32)[:, None, None]
            z = torch.add(plane[2], i, alpha=step_i[2])
            inverse_z = z.clamp(min=NEAR_PLANE).reciprocal_()  # behind the camera: any finite value, left out below
            # Framed pixel coordinates, clamped onto the frame: floor by truncation, as they are not negative.
            column = torch.add(plane[0], i, alpha=step_i[0]).mul_(inverse_z).mul_(camera.fx).add_(camera.cx + 1)
            row = torch.add(plane[1], i, alpha=step_i[1]).mul_(inverse_z).mul_(camera.fy).add_(camera.cy + 1)
            pixel = row.clamp_(0, height + 1).long().mul_(width + 2).add_(column.clamp_(0, width + 1).long())
            sdf = framed_depth[pixel].sub_(z)
            counted = (sdf >= -truncation) & (z > NEAR_PLANE)
            if clear_depth is not None:  # in front of the surface but not clear of it: the view cannot tell
                counted &= (sdf < truncation) | (framed_clear[pixel] - z >= truncation)
            ids = counted.reshape(-1).nonzero().squeeze(1)
            if ids.numel() == 0:
                continue
            in_volume = ids + x0 * ny * nz
            weight = self.weight.view(-1)[in_volume]
            observed = (sdf.reshape(-1)[ids] / truncation).clamp_(max=1.0)
            this = torch.where(observed >= 1.0, self.free_weight, 1.0)
            new_weight = weight + this
            tsdf = self.tsdf.view(-1)
            tsdf[in_volume] = (tsdf[in_volume] * weight + observed * this) / new_weight
            self.weight.view(-1)[in_volume] = new_weight
            color = self.color.view(-1, 3)
            old = color[in_volume].float()
            color[in_volume] = (old + (framed_rgb[pixel.reshape(-1)[ids]] - old) * (this / new_weight)[:, None]).half()

    @torch.no_grad()
    def fill_gaps(self, passes: int = GAP_PASSES, least_neighbours: int = GAP_NEIGHBOURS) -> int:
        """Give each unobserved grid point with at least `least_neighbours` observed ones among its 6 the mean of
        their values and colours, `passes` times; the number of points filled. Closes the narrow gaps the views
        leave where none confirms a depth (the pixels along a sharp edge), without growing a surface's open rim (a
        point beside a flat rim has one observed neighbour)."""
        shape = self.grid.shape
        strides = (shape[1] * shape[2], shape[2], 1)
        tsdf, weight, color = self.tsdf.view(-1), self.weight.view(-1), self.color.view(-1, 3)
        filled = 0
        for _ in range(passes):
            seen = (self.weight > 0).to(torch.uint8)
            todo = ((seen == 0) & (_neighbour_count(seen) >= least_neighbours)).view(-1).nonzero().squeeze(1)
            if todo.numel() == 0:
                break
            position = [(todo // strides[axis]) % shape[axis] for axis in range(3)]
            total = torch.zeros_like(todo, dtype=torch.float32)
            colors = torch.zeros((todo.numel(), 3), dtype=torch.float32, device=todo.device)
            count = torch.zeros_like(total)
            for axis in range(3):
                for step in (-1, 1):
                    inside = (position[axis] + step >= 0) & (position[axis] + step < shape[axis])
                    neighbour = torch.where(inside, todo + step * strides[axis], todo)
                    observed = (inside & (weight[neighbour] > 0)).float()
                    total += tsdf[neighbour] * observed
                    colors += color[neighbour].float() * observed[:, None]
                    count += observed
            tsdf[todo] = total / count
            color[todo] = (colors / count[:, None]).half()
            weight[todo] = GAP_WEIGHT
            filled += todo.numel()
        return filled

    def _slab_in_view(self, base, steps, x0: int, x1: int, camera: Camera) -> bool:
        """False when the slab's box lies wholly behind the camera or wholly beside the image (a safe shortcut)."""
        ny, nz = self.grid.shape[1:]
        corners = torch.tensor([[a, b, c] for a in (x0, x1 - 1) for b in (0, ny - 1) for c in (0, nz - 1)],
                               dtype=torch.float64, device=base.device)
        points = base + corners @ steps.T
        z = points[:, 2]
        if (z <= NEAR_PLANE).all():
            return False
        if (z <= NEAR_PLANE).any():  # straddles the camera plane: its projection is unbounded
            return True
        u = points[:, 0] / z * camera.fx + camera.cx
        v = points[:, 1] / z * camera.fy + camera.cy
        return bool(u.max() >= 0 and u.min() < camera.width and v.max() >= 0 and v.min() < camera.height)


def _neighbour_count(seen: torch.Tensor) -> torch.Tensor:
    """[nx, ny, nz] uint8: how many of each grid point's 6 face neighbours are set in `seen` (uint8 0 or 1)."""
    total = torch.zeros_like(seen)
    for axis in range(3):
        size = seen.shape[axis]
        total.narrow(axis, 1, size - 1).add_(seen.narrow(axis, 0, size - 1))
        total.narrow(axis, 0, size - 1).add_(seen.narrow(axis, 1, size - 1))
    return total
