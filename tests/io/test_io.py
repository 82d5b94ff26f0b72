"""The 3DGS .ply layout, checkpoints and atomic writes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from mcsplat.errors import MCSplatError
from mcsplat.io.atomic import atomic_path, atomic_write_text, remove_stale_temporaries
from mcsplat.io.checkpoint import load_checkpoint, save_checkpoint
from mcsplat.io.ply import read_ply, write_ply

EXPECTED_FIELDS = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                   + [f"f_rest_{i}" for i in range(45)] + ["opacity", "scale_0", "scale_1", "scale_2",
                                                            "rot_0", "rot_1", "rot_2", "rot_3"])


def random_params(n, seed=0, rest=15):
    g = torch.Generator().manual_seed(seed)
    return {"means": torch.randn(n, 3, generator=g), "log_scales": torch.randn(n, 3, generator=g) - 3,
            "quats": torch.randn(n, 4, generator=g), "opacity_logits": torch.randn(n, generator=g),
            "sh0": torch.randn(n, 1, 3, generator=g), "shN": torch.randn(n, rest, 3, generator=g)}


def test_ply_layout_is_exactly_the_3dgs_one(tmp_path):
    params = random_params(7)
    write_ply(tmp_path / "a.ply", params)
    vertex = PlyData.read(str(tmp_path / "a.ply"))["vertex"]
    assert list(vertex.data.dtype.names) == EXPECTED_FIELDS
    assert all(vertex.data.dtype[name] == np.float32 for name in EXPECTED_FIELDS)
    # f_rest is channel-major: all 15 red coefficients first.
    assert vertex["f_rest_0"][3] == pytest.approx(float(params["shN"][3, 0, 0]))
    assert vertex["f_rest_1"][3] == pytest.approx(float(params["shN"][3, 1, 0]))
    assert vertex["f_rest_15"][3] == pytest.approx(float(params["shN"][3, 0, 1]))
    assert vertex["rot_0"][2] == pytest.approx(float(params["quats"][2, 0]))


def test_ply_round_trip_and_filter(tmp_path):
    params = random_params(50, seed=1)
    keep = params["opacity_logits"] > 0
    written = write_ply(tmp_path / "b.ply", params, keep=keep)
    back = read_ply(tmp_path / "b.ply")
    assert written == int(keep.sum())
    for key, value in params.items():
        assert torch.equal(back[key], value[keep]), key


def test_ply_from_another_tool_with_lower_sh_degree(tmp_path):
    """A degree-1 file (9 f_rest) written field by field, in a different field order, as other tools do."""
    n = 4
    names = ["x", "y", "z", "opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)] \
        + [f"f_dc_{i}" for i in range(3)] + [f"f_rest_{i}" for i in range(9)]
    data = np.zeros(n, dtype=[(name, "f4") for name in names])
    for i, name in enumerate(names):
        data[name] = np.arange(n) + i
    PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "other.ply"))
    params = read_ply(tmp_path / "other.ply")
    assert params["shN"].shape == (n, 3, 3)
    assert float(params["shN"][1, 0, 1]) == 1 + names.index("f_rest_3")  # green channel, first coefficient
    assert float(params["opacity_logits"][2]) == 2 + names.index("opacity")


def test_ply_bad_inputs(tmp_path):
    with pytest.raises(MCSplatError, match="no such .ply"):
        read_ply(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(MCSplatError, match="not a readable .ply"):
        read_ply(tmp_path / "junk.ply")
    data = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "points.ply"))
    with pytest.raises(MCSplatError, match="not a 3D Gaussian Splatting .ply"):
        read_ply(tmp_path / "points.ply")
    params = random_params(3)
    params["means"][1, 0] = float("nan")
    write_ply(tmp_path / "nan.ply", params)
    with pytest.raises(MCSplatError, match="NaN"):
        read_ply(tmp_path / "nan.ply")


def test_checkpoint_round_trip_and_damage(tmp_path):
    state = {"step": 12, "model": {"w": torch.arange(5.0)}, "nested": {"a": [1, 2.5, "x"]},
             "generator": torch.Generator().manual_seed(3).get_state()}
    save_checkpoint(tmp_path / "c.pt", state)
    back = load_checkpoint(tmp_path / "c.pt")
    assert back["step"] == 12 and torch.equal(back["model"]["w"], state["model"]["w"])
    assert back["nested"] == state["nested"] and torch.equal(back["generator"], state["generator"])
    data = (tmp_path / "c.pt").read_bytes()
    (tmp_path / "c.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(MCSplatError, match="damaged checkpoint"):
        load_checkpoint(tmp_path / "c.pt")
    with pytest.raises(MCSplatError, match="no checkpoint"):
        load_checkpoint(tmp_path / "none.pt")
    assert [p.name for p in tmp_path.iterdir()] == ["c.pt"], "no temporary files left behind"


def test_sigkill_during_checkpoint_writes_never_corrupts(tmp_path):
    """A writer killed at random moments leaves either the old or the new checkpoint, always loadable."""
    script = (
        "import sys, torch\n"
        "from mcsplat.io.checkpoint import save_checkpoint\n"
        "i = 0\n"
        "while True:\n"
        "    i += 1\n"
        "    save_checkpoint(sys.argv[1], {'step': i, 'w': torch.full((300_000,), float(i))})\n")
    path = tmp_path / "ckpt.pt"
    for delay in (0.6, 0.9, 1.3):
        proc = subprocess.Popen([sys.executable, "-c", script, str(path)])
        time.sleep(delay)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        if path.exists():
            state = load_checkpoint(path)
            assert torch.equal(state["w"], torch.full((300_000,), float(state["step"])))


def test_stale_temporaries_are_removed_and_nothing_else(tmp_path):
    target = tmp_path / "checkpoint.pt"
    with pytest.raises(RuntimeError):  # a writer that fails part-way cleans up after itself ...
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError
    assert list(tmp_path.iterdir()) == []
    # ... but a killed one cannot: these are the names it would leave.
    stale = [tmp_path / ".checkpoint.ab_3x9qz.tmp.pt", tmp_path / ".checkpoint.00000000.tmp.pt"]
    kept = [tmp_path / "checkpoint.pt", tmp_path / ".checkpoint.mine.tmp.pt", tmp_path / "checkpoint.ab_3x9qz.tmp.pt",
            tmp_path / ".checkpoint.ab_3x9qz.tmp.pth", tmp_path / ".other.ab_3x9qz.tmp.pt"]
    for path in stale + kept:
        path.write_bytes(b"x")
    assert sorted(remove_stale_temporaries(target)) == sorted(stale)
    assert sorted(tmp_path.iterdir()) == sorted(kept)


@pytest.mark.parametrize("umask", [0o022, 0o077, 0o002])
def test_written_files_follow_the_umask(tmp_path, umask):
    previous = os.umask(umask)
    try:
        atomic_write_text(tmp_path / "a.json", "{}")
        save_checkpoint(tmp_path / "b.pt", {"step": 1})
    finally:
        os.umask(previous)
    for name in ("a.json", "b.pt"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o666 & ~umask, name
