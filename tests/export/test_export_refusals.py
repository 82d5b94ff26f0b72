"""What `mcsplat export` (and render, report) refuse before writing anything: a .gltf's buffer over a file it did not
write, any folder inside a scene, and options the chosen format would ignore. Each refusal is one line and leaves
every file as it was."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from mcsplat.cli import main
from mcsplat.errors import MCSplatError
from mcsplat.io.formats import read_gaussians, write_gaussians
from tests.export.test_formats import random_gaussians


def files_of(folder: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def refused(argv: list[str], capsys, expected: str) -> str:
    capsys.readouterr()
    assert main(argv) == 2, argv
    error = capsys.readouterr().err
    assert error.startswith("mcsplat: error:") and expected in error and error.count("\n") == 1, (argv, error)
    return error


def colmap_scene(root: Path) -> Path:
    """A folder that reads as a COLMAP scene (detect_kind needs only the model's three files)."""
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "images").mkdir()
    for name in ("cameras", "images", "points3D"):
        (root / "sparse" / "0" / f"{name}.bin").write_bytes(f"{name} of another scene".encode())
    (root / "images" / "a.png").write_bytes(b"a photo")
    return root


def test_a_gltf_never_replaces_a_bin_it_did_not_write(tiny_run, tmp_path, capsys):
    run = shutil.copytree(tiny_run, tmp_path / "run")
    mine = tmp_path / "x.bin"
    mine.write_bytes(b"the user's own file")
    (tmp_path / "y.bin").mkdir()
    (run / "point_cloud.bin").write_bytes(b"not the buffer of a .gltf")
    for argv, name in ((["--out", str(tmp_path / "x.gltf")], "x.bin"),
                       (["--out", str(tmp_path / "y.gltf")], "y.bin"),
                       (["--format", "gltf"], "point_cloud.bin")):
        error = refused(["export", str(run), *argv], capsys, name)
        assert "another name" in error, error
    assert mine.read_bytes() == b"the user's own file" and (tmp_path / "y.bin").is_dir()
    assert (run / "point_cloud.bin").read_bytes() == b"not the buffer of a .gltf"
    assert not any(tmp_path.glob("*.gltf")) and not (run / "point_cloud.gltf").exists()
    # The library's writer keeps the same rule.
    with pytest.raises(MCSplatError, match="x.bin"):
        write_gaussians("gltf", tmp_path / "x.gltf", random_gaussians(8))
    assert mine.read_bytes() == b"the user's own file"
    # The buffer a .gltf names is that .gltf's: exporting to the same name again replaces both.
    for _ in range(2):
        assert main(["export", str(run), "--out", str(tmp_path / "z.gltf")]) == 0
    assert read_gaussians("gltf", tmp_path / "z.gltf")["means"].shape[0] > 0


def test_a_gltf_into_another_scene_leaves_its_model_alone(tiny_run, tmp_path, capsys):
    scene = colmap_scene(tmp_path / "other")
    before = files_of(scene)
    refused(["export", str(tiny_run), "--out", str(scene / "sparse" / "0" / "cameras.gltf")], capsys,
            "inside the scene folder")
    assert files_of(scene) == before


def test_nothing_is_written_at_any_depth_inside_another_scene(tiny_run, tmp_path, capsys):
    scene = colmap_scene(tmp_path / "other")
    before, folders = files_of(scene), sorted(scene.rglob("*"))
    for argv in (["export", str(tiny_run), "--out", str(scene / "images" / "x.ply")],
                 ["export", str(tiny_run), "--out", str(scene / "images" / "a" / "b" / "x.spz")],
                 ["render", str(tiny_run), "--out", str(scene / "images" / "renders")],
                 ["report", str(tiny_run), "--out", str(scene / "sparse" / "report")]):
        refused(argv, capsys, f"inside the scene folder {scene.resolve()}")
    assert files_of(scene) == before and sorted(scene.rglob("*")) == folders


def test_an_option_the_chosen_format_does_not_read_is_refused(tiny_run, tmp_path, capsys):
    for argv, expected in ((["--out", str(tmp_path / "x.ply"), "--spz-version", "4"], "--spz-version 4"),
                           (["--out", str(tmp_path / "x.glb"), "--spz-version", "4"], "spz"),
                           (["--out", str(tmp_path / "x.spz"), "--voxel-size", "0.01", "--depth", "planar"],
                            "--voxel-size 0.01, --depth planar"),
                           (["--format", "mesh", "--out", str(tmp_path / "m.ply"), "--max-gaussians", "10",
                             "--prune"], "--max-gaussians 10, --prune")):
        refused(["export", str(tiny_run), *argv], capsys, expected)
    assert list(tmp_path.iterdir()) == []
    # An option the format reads is taken.
    assert main(["export", str(tiny_run), "--out", str(tmp_path / "x.spz"), "--spz-version", "4"]) == 0
    assert (tmp_path / "x.spz").read_bytes()[:4] != b"\x1f\x8b"  # zstd's version 4, not gzip's 3
