"""The parcels of benchmarks/gpu_carry.py: what is split comes back whole, and the lego it packs is a scene the
loader reads. (The wheels it downloads and the calls themselves are checked on a GPU machine.)"""

from __future__ import annotations

import os

from mcsplat.data import load_scene

import gpu_carry


def test_a_split_file_joins_back_whole(tmp_path):
    source = tmp_path / "library.xz"
    source.write_bytes(os.urandom(10_000))
    gpu_carry.split(source, tmp_path / "aa", tmp_path / "ab", part_bytes=4096)
    assert (tmp_path / "aa").stat().st_size == 4096
    assert (tmp_path / "aa").read_bytes() + (tmp_path / "ab").read_bytes() == source.read_bytes()


def test_the_lego_parcel_is_a_scene_with_its_first_test_views(shared_data, tmp_path):
    lego = shared_data / "nerf_synthetic_lego_400" / "lego"
    gpu_carry.lego_subset(lego, tmp_path / "lego", test_views=5)
    whole, subset = load_scene(lego), load_scene(tmp_path / "lego")
    assert len(subset.train) == len(whole.train) and len(subset.test) == 5
    assert [view.name for view in subset.test] == [view.name for view in whole.test[:5]]
    assert not list((tmp_path / "lego" / "test").glob("*depth*")), "the depth maps stay behind"
