"""The room of a training step's pair lists (render/bin/pair_room.py): sized from the first count at an image size,
then from the most pairs per Gaussian of the counts that arrived since, times the Gaussians at hand; the front pairs
kept when a render does not fit; the same lists as the torch binning otherwise. On the Warp kernels CUDA runs (on the
CPU with set_cpu_kernels("scalar"))."""

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
def warp_binning(monkeypatch):
    """The Warp kernels, rooms made afresh, and no floor under a room (these scenes have hundreds of pairs)."""
    monkeypatch.setattr(pair_room, "MIN_ROOM", 1)
    pair_room.forget_rooms()
    set_cpu_kernels("scalar")
    yield
    set_cpu_kernels("simd")
    pair_room.forget_rooms()


def projected(n: int, seed: int, log_scale=(-4.0, -2.0), spread: float = 1.0):
    splats = random_splats(n, seed, log_scale=log_scale, spread=spread)
    p = project_gaussians(*(getattr(splats, name) for name in PARAMS[:4]), make_camera(96, 80, distance=2.5))
    return p.tile_min, p.tile_max, p.depths, p.radii, *TILES


def lists(bins) -> list[list[int]]:
    ranges, ids = bins.tile_ranges.tolist(), bins.gaussian_ids.tolist()
    return [ids[start:end] for start, end in ranges]


def same_lists(bins, exact) -> bool:
    return lists(bins) == lists(exact) and torch.equal(bins.listed().tile_ranges, exact.tile_ranges)


def test_a_step_lists_every_pair_in_its_room_which_grows_with_the_model():
    sparse = projected(60, 1, log_scale=(-5.0, -4.0), spread=1.5)
    exact = torch_bin_gaussians(*sparse)
    assert (exact.tile_ranges[:, 0] == exact.tile_ranges[:, 1]).any(), "some tiles must be empty"
    with pair_room.sized_ahead():
        first = bin_gaussians(*sparse)
        (room,) = pair_room._rooms.values()
        assert room.capacity == math.ceil(pair_room.HEADROOM * exact.num_pairs)
        assert first.gaussian_ids.shape[0] == room.capacity and first.num_pairs == exact.num_pairs
        assert same_lists(first, exact)  # empty tiles too: [k, k) where their run would start
    pair_room.forget_rooms()
    small, large = projected(300, 2), projected(600, 3)
    with pair_room.sized_ahead():
        bin_gaussians(*small)
        (room,) = pair_room._rooms.values()
        ratio = torch_bin_gaussians(*small).num_pairs / 300
        grown = bin_gaussians(*large)  # twice the Gaussians: a room for twice the pairs before it renders
        assert room.capacity >= pair_room.HEADROOM * ratio * 600
        assert same_lists(grown, torch_bin_gaussians(*large)) and room.overflows == 0


def test_a_render_that_does_not_fit_keeps_its_front_pairs_and_the_next_has_room():
    small, large = projected(300, 3), projected(300, 4, log_scale=(-2.0, -1.0))  # the same count, larger splats
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
        with pytest.warns(RuntimeWarning, match="farthest pairs were left out"):
            again = bin_gaussians(*large)
        assert room.overflows == 1 and same_lists(again, exact)
        assert room.capacity == math.ceil(pair_room.HEADROOM * exact.num_pairs)


def test_the_room_shrinks_only_when_none_of_the_last_counts_needed_it(monkeypatch):
    monkeypatch.setattr(pair_room, "WINDOW", 3)
    dense, sparse = projected(300, 5, log_scale=(-2.5, -1.5)), projected(300, 6, log_scale=(-5.0, -4.0))
    with pair_room.sized_ahead():
        bin_gaussians(*dense)
        (room,) = pair_room._rooms.values()
        full = room.capacity
        for _ in range(3):  # the dense count is still among the last three
            bin_gaussians(*sparse)
            assert room.capacity == full
        bin_gaussians(*sparse)
        assert room.capacity < full / 3
        bin_gaussians(*dense)  # does not fit the shrunk room: cut, and the next one has room again
        with pytest.warns(RuntimeWarning):
            assert same_lists(bin_gaussians(*dense), torch_bin_gaussians(*dense)) and room.overflows == 1


def test_an_empty_first_render_leaves_a_room_of_some_size(monkeypatch):
    monkeypatch.setattr(pair_room, "MIN_ROOM", 4096)
    zeros = torch.zeros(5, 2, dtype=torch.int32)
    with pair_room.sized_ahead():
        bins = bin_gaussians(zeros, zeros, torch.ones(5), torch.zeros(5, dtype=torch.int32), *TILES)
    assert bins.num_pairs == 0 and not bins.tile_ranges.any()
    assert next(iter(pair_room._rooms.values())).capacity == 4096


def test_other_renders_read_their_count_and_make_no_room():
    exact = torch_bin_gaussians(*projected(300, 7))
    bins = bin_gaussians(*projected(300, 7))
    assert not pair_room._rooms and bins.gaussian_ids.shape[0] == exact.num_pairs
    assert same_lists(bins, exact) and torch.equal(bins.pair_masks, exact.pair_masks)
