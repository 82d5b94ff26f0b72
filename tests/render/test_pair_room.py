"""The room of a training step's pair lists (render/bin/pair_room.py): sized from the first count at an image size,
grown before it fills from counts copied a render late, the front pairs kept when a render does not fit, and the
same lists as the torch binning otherwise. On the Warp kernels CUDA runs (on the CPU with set_cpu_kernels("scalar"))."""

from __future__ import annotations

import math

import pytest
import torch

from mcsplat.render.bin import pair_room
from mcsplat.render.bin.torch_oracle import torch_bin_gaussians
from mcsplat.render.bin.warp_kernels import bin_gaussians
from mcsplat.render.composite.function import set_cpu_kernels
from mcsplat.render.project.torch_autograd import project_gaussians

from tests.render.test_render import PARAMS, make_camera, random_splats

TILES = (6, 5)  # a 96x80 image


@pytest.fixture(autouse=True)
def warp_binning():
    pair_room.forget_rooms()
    set_cpu_kernels("scalar")
    yield
    set_cpu_kernels("simd")
    pair_room.forget_rooms()


def projected(n: int, seed: int):
    splats = random_splats(n, seed, log_scale=(-4.0, -2.0))
    p = project_gaussians(*(getattr(splats, name) for name in PARAMS[:4]), make_camera(96, 80, distance=2.5))
    return p.tile_min, p.tile_max, p.depths, p.radii, *TILES


def lists(bins) -> list[list[int]]:
    ranges, ids = bins.tile_ranges.tolist(), bins.gaussian_ids.tolist()
    return [ids[start:end] for start, end in ranges]


def test_a_step_lists_every_pair_in_its_room_and_grows_it_before_it_fills():
    small, large = projected(300, 1), projected(360, 2)
    exact_small, exact_large = torch_bin_gaussians(*small), torch_bin_gaussians(*large)
    assert exact_small.num_pairs < exact_large.num_pairs < pair_room.HEADROOM * exact_small.num_pairs
    with pair_room.sized_ahead():
        first = bin_gaussians(*small)
        (room,) = pair_room._rooms.values()
        assert room.capacity == math.ceil(pair_room.HEADROOM * exact_small.num_pairs)
        assert first.gaussian_ids.shape[0] == room.capacity and first.num_pairs == exact_small.num_pairs
        assert lists(first) == lists(exact_small)
        assert exact_large.num_pairs > pair_room.GROW_AT * room.capacity
        second = bin_gaussians(*large)  # fits, but above GROW_AT of the room: the next render has more
        assert lists(second) == lists(exact_large)
        bin_gaussians(*small)
        assert room.capacity == math.ceil(pair_room.HEADROOM * exact_large.num_pairs) and room.overflows == 0


def test_a_render_that_does_not_fit_keeps_its_front_pairs_and_the_next_has_room():
    small, large = projected(200, 3), projected(900, 4)
    exact = torch_bin_gaussians(*large)
    with pair_room.sized_ahead():
        bin_gaussians(*small)
        (room,) = pair_room._rooms.values()
        capacity = room.capacity
        assert exact.num_pairs > 2 * capacity
        cut = bin_gaussians(*large)
        kept, full = lists(cut), lists(exact)
        assert sum(map(len, kept)) == capacity and cut.num_pairs == capacity
        assert all(k == f[:len(k)] for k, f in zip(kept, full))  # each tile's nearest Gaussians
        assert any(len(k) < len(f) for k, f in zip(kept, full))
        again = bin_gaussians(*large)
        assert room.overflows == 1 and lists(again) == full
        assert room.capacity == math.ceil(pair_room.HEADROOM * exact.num_pairs)
        bin_gaussians(*small)
        bin_gaussians(*small)  # the count fell under a third of the room: it shrinks
        assert room.capacity == math.ceil(pair_room.HEADROOM * torch_bin_gaussians(*small).num_pairs)


def test_other_renders_read_their_count_and_make_no_room():
    exact = torch_bin_gaussians(*projected(300, 5))
    bins = bin_gaussians(*projected(300, 5))
    assert not pair_room._rooms and bins.gaussian_ids.shape[0] == exact.num_pairs
    assert lists(bins) == lists(exact) and torch.equal(bins.pair_masks, exact.pair_masks)
