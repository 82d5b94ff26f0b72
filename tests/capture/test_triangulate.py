"""The cache of the points triangulated from known poses (capture/triangulate.py): an entry is served only when its
bytes are those it was written with and its points are what a fresh triangulation gives (enough of them, finite,
inside the cameras' views); any other entry is made again, saying so. A cache file that is not a regular file never
blocks a run, a read-only cache never stops one, and a signal during triangulation ends it as Ctrl-C does, with its
temporary folder removed.

The scene is ten of the cup's photos with their poses, as a transforms.json without points: it triangulates in a
couple of seconds."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.support.helpers import on_a_small_disk, small_disks_work
from mcsplat.capture import triangulate
from mcsplat.capture.triangulate import triangulated_points
from mcsplat.data import load_scene
from mcsplat.data.undistort import CACHE_ENV
from mcsplat.io.transforms import write_transforms

CUP_VIEWS = ["1", "4", "7", "10", "13", "16", "19", "22", "25", "28"]


@pytest.fixture(scope="module")
def cup_scene(shared_data, tmp_path_factory) -> Path:
    """Ten of the cup's photos and their poses, as a transforms.json (no points)."""
    cup = load_scene(shared_data / "colmap_cup", test_every=0)
    root = tmp_path_factory.mktemp("cup10")
    write_transforms([view for view in cup.train if view.name in CUP_VIEWS], root / "transforms.json")
    return root


@pytest.fixture(scope="module")
def cup_views(cup_scene):
    return load_scene(cup_scene, test_every=0).train


@pytest.fixture(scope="module")
def made_entry(cup_views, tmp_path_factory) -> tuple[Path, triangulate.Triangulated]:
    """A cache entry made by a real triangulation (once for the module), and what it holds."""
    cache = tmp_path_factory.mktemp("made")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(CACHE_ENV, str(cache))
        made = triangulated_points(cup_views, threads=2, progress=False)
    entries = list((cache / triangulate.CACHE_VERSION).iterdir())
    assert not made.cached and len(entries) == 1
    return entries[0], made


@pytest.fixture
def entry(made_entry, tmp_path, monkeypatch) -> Path:
    """A private copy of the made entry, in a private cache, under the key of the cup's views."""
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    copy = tmp_path / "cache" / triangulate.CACHE_VERSION / made_entry[0].name
    shutil.copytree(made_entry[0], copy)
    return copy


def read_warning(entry: Path, views):
    """(what the cache serves from `entry`, the warnings it gave)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        found = triangulate.cached_points(entry, views)
    return found, [str(w.message) for w in caught]


def test_an_intact_entry_is_served_without_a_word(entry, made_entry, cup_views):
    found, said = read_warning(entry, cup_views)
    assert said == [] and found is not None and found.cached
    assert np.array_equal(found.xyz, made_entry[1].xyz) and np.array_equal(found.rgb, made_entry[1].rgb)
    assert found.views == len(CUP_VIEWS) and found.reprojection_error == made_entry[1].reprojection_error


def half_a_zip(entry: Path) -> None:
    path = entry / "points.npz"
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def emptied(entry: Path) -> None:
    (entry / "points.npz").write_bytes(b"")


def other_colours(entry: Path) -> None:  # a well-formed file, but not the one written
    with np.load(entry / "points.npz") as data:
        xyz, rgb = data["xyz"], data["rgb"]
    np.savez(entry / "points.npz", xyz=xyz, rgb=255 - rgb)


def facts_replaced(text: str):
    def damage(entry: Path) -> None:
        (entry / "facts.json").write_text(text)
    return damage


def entry_is_a_file(entry: Path) -> None:
    shutil.rmtree(entry)
    entry.write_text("not a folder")


def hash_removed(entry: Path) -> None:
    for path in entry.glob("*.blake2b"):
        path.unlink()


@pytest.mark.parametrize("damage", [half_a_zip, emptied, other_colours, facts_replaced("{}"),
                                    facts_replaced("[1, 2]"), entry_is_a_file, hash_removed],
                         ids=["half a zip", "0 bytes", "other colours", "facts {}", "facts [1,2]", "entry a file",
                              "no hash"])
def test_an_entry_damaged_since_it_was_written_is_made_again_saying_so(entry, made_entry, cup_views, damage):
    damage(entry)
    found, said = read_warning(entry, cup_views)
    assert found is None, "a damaged entry is never served"
    assert len(said) == 1 and str(entry) in said[0] and "triangulating again" in said[0], said
    triangulate.store_points(entry, made_entry[1])  # what triangulated_points does next
    again, said = read_warning(entry, cup_views)
    assert said == [] and again is not None and np.array_equal(again.xyz, made_entry[1].xyz)


def consistent(xyz=None, rgb=None, facts=None):
    """An entry written with its hashes, as a version with a bug (or a hand) could write it: only its content is
    wrong."""
    def damage(entry: Path, made: triangulate.Triangulated) -> None:
        from mcsplat.io.hashed import write_hashed

        triangulate.store_points(entry, replace(made, xyz=made.xyz if xyz is None else xyz(made.xyz),
                                                rgb=made.rgb if rgb is None else rgb(made.rgb)))
        if facts is not None:
            write_hashed(entry / "facts.json", json.dumps(facts).encode())
    return damage


@pytest.mark.parametrize("damage, reason", [
    (consistent(xyz=lambda xyz: xyz[:5], rgb=lambda rgb: rgb[:5]), "5 points"),
    (consistent(xyz=lambda xyz: xyz + 1e4), "outside every camera's view"),
    (consistent(xyz=lambda xyz: np.where(np.arange(len(xyz))[:, None] == 3, np.nan, xyz)), "not finite"),
    (consistent(xyz=lambda xyz: xyz[:, :2]), "shape"),
    (consistent(rgb=lambda rgb: rgb[:-1]), "shape"),
    (consistent(facts={}), "facts.json"),
    (consistent(facts=[1, 2]), "facts.json"),
    (consistent(facts={"views": "ten", "seconds": "2", "reprojection_error": "0.5"}), "facts.json"),
    (consistent(facts={"views": 3, "seconds": 2.0, "reprojection_error": 0.5}), "facts.json"),
], ids=["5 points", "moved by 1e4", "NaN", "xyz [P,2]", "rgb one short", "facts {}", "facts [1,2]",
        "facts strings", "facts other views"])
def test_an_entry_unlike_a_fresh_triangulation_is_made_again_saying_why(entry, made_entry, cup_views, damage,
                                                                         reason):
    damage(entry, made_entry[1])
    found, said = read_warning(entry, cup_views)
    assert found is None and len(said) == 1 and str(entry) in said[0] and reason in said[0], said


@pytest.mark.parametrize("name", ["points.npz", "facts.json", "points.blake2b"])
def test_a_cache_file_that_is_a_fifo_does_not_block(entry, cup_views, name):
    (entry / name).unlink()
    os.mkfifo(entry / name)
    result = {}
    reader = threading.Thread(target=lambda: result.update(zip(("found", "said"), read_warning(entry, cup_views))),
                              daemon=True)
    reader.start()
    reader.join(timeout=20)
    if reader.is_alive():
        with open(entry / name, "wb"):  # lets the blocked reader go
            pass
        pytest.fail(f"reading the cache blocked on the FIFO {name}")
    assert result["found"] is None and "not a regular file" in result["said"][0], result


def test_a_damaged_entry_is_triangulated_again_and_written_whole(entry, made_entry, cup_views):
    """The whole way through: the damaged entry is replaced by a good one, which the next run reads."""
    entry_is_a_file(entry)
    with pytest.warns(UserWarning, match="triangulating again"):
        made = triangulated_points(cup_views, threads=2, progress=False)
    assert not made.cached and abs(len(made.xyz) - len(made_entry[1].xyz)) < 0.2 * len(made_entry[1].xyz)
    assert entry.is_dir()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = triangulated_points(cup_views, threads=2, progress=False)
    assert again.cached and np.array_equal(again.xyz, made.xyz)


# Runs in a namespace of its own, where the cache folder is a read-only tmpfs (helpers.on_a_small_disk).
READ_ONLY = """
import json, sys, warnings
from pathlib import Path
from mcsplat.capture.triangulate import triangulated_points
from mcsplat.data import load_scene
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    made = triangulated_points(load_scene(Path(sys.argv[1]), test_every=0).train, threads=2, progress=False)
print(json.dumps({"points": len(made.xyz), "said": [str(w.message) for w in caught]}))
"""


def test_a_read_only_cache_gives_the_points_uncached_in_one_line(cup_scene, tmp_path, monkeypatch):
    if not small_disks_work(tmp_path / "probe"):
        pytest.skip("cannot mount a tmpfs in a user namespace here (unshare --user --mount)")
    cache = tmp_path / "cache"
    monkeypatch.setenv(CACHE_ENV, str(cache))
    done = on_a_small_disk(cache, "ro", READ_ONLY, str(cup_scene))
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr[-3000:]
    result = json.loads(done.stdout.splitlines()[-1])
    assert result["points"] >= triangulate.MIN_POINTS
    assert len(result["said"]) == 1, result
    said = result["said"][0]
    assert "\n" not in said and said.startswith(f"cannot write the points cache {cache}"), said
    assert "read-only file system" in said.lower() and CACHE_ENV in said, said


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_a_signal_during_triangulation_ends_it_as_ctrl_c_does(cup_scene, tmp_path, signum):
    """`train` stopped by kill (or a closed terminal) while it triangulates: "interrupted", exit 130, no C++ stack
    dump, no temporary folder left and nothing cached."""
    temporary, cache, run = tmp_path / "tmp", tmp_path / "cache", tmp_path / "run"
    temporary.mkdir()
    env = {**os.environ, CACHE_ENV: str(cache), "TMPDIR": str(temporary)}
    child = subprocess.Popen([sys.executable, "-m", "mcsplat.cli", "train", str(cup_scene), "--out", str(run),
                              "--steps", "5", "--quiet"], env=env, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not list(temporary.glob("mcsplat-triangulate-*/database.db")):  # pycolmap at work
            assert child.poll() is None and time.monotonic() < deadline, "the triangulation never started"
            time.sleep(0.02)
        child.send_signal(signum)
        _, stderr = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert child.returncode == 130 and stderr.strip().splitlines()[-1] == "mcsplat: interrupted", stderr[-3000:]
    assert "@ 0x" not in stderr and "Traceback" not in stderr, stderr[-3000:]
    assert not list(temporary.glob("mcsplat-triangulate-*")), "the temporary folder is removed"
    assert not list(cache.rglob("points.npz")), "nothing is cached"
    assert not (run / ".lock").exists(), "the run's lock is released"


def test_an_entry_with_float_colours_is_said_to_have_them(entry, made_entry, cup_views):
    """Colours of the right shape but floats (0-1) are what is wrong with the entry, not its shapes (issue 58)."""
    consistent(rgb=lambda rgb: rgb.astype(np.float32) / 255)(entry, made_entry[1])
    found, said = read_warning(entry, cup_views)
    assert found is None and len(said) == 1 and "triangulating again" in said[0], said
    assert "colours of float32, not uint8" in said[0] and "shape" not in said[0], said
