"""Export formats (.splat, PlayCanvas compressed .ply, .spz versions 3 and 4; glTF's in test_gltf.py, SOG's in
test_sog.py, what PlayCanvas's splat-transform reads in test_splat_transform.py): byte layout checked on
hand-computed values, and every field read back within the format's quantisation; a damaged file is one line;
`mcsplat export --format` with pruning on a trained run."""

from __future__ import annotations

import gzip
import struct
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import zstandard

from mcsplat.cli import main
from mcsplat.errors import MCSplatError
from mcsplat.io.formats import EXTENSIONS, read_gaussians, select_gaussians, write_gaussians
from mcsplat.io.formats.compressed_ply import CHUNK, morton_order
from mcsplat.io.ply import read_ply

C0 = 0.28209479177387814


def random_gaussians(n: int, degree: int = 3, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1
    return {"means": rng.uniform(-3, 3, (n, 3)).astype(np.float32),
            "log_scales": rng.uniform(-6, 0, (n, 3)).astype(np.float32),
            "quats": rng.normal(size=(n, 4)).astype(np.float32),
            "opacity_logits": rng.uniform(-4, 4, n).astype(np.float32),
            "sh0": rng.uniform(-1.5, 1.5, (n, 1, 3)).astype(np.float32),
            "shN": rng.uniform(-0.4, 0.4, (n, k, 3)).astype(np.float32)}


def sigmoid(x):
    return 1 / (1 + np.exp(-x.astype(np.float64)))


def assert_same_rotations(actual, expected, tolerance):
    a = actual / np.linalg.norm(actual, axis=1, keepdims=True)
    e = expected / np.linalg.norm(expected, axis=1, keepdims=True)
    error = np.minimum(np.abs(a - e).max(1), np.abs(a + e).max(1)).max()  # q and -q are one rotation
    assert error <= tolerance, f"rotations: error {error} above {tolerance}"


def assert_close_to(actual, expected, tolerance, what):
    error = np.abs(np.asarray(actual, np.float64) - np.asarray(expected, np.float64)).max()
    assert error <= tolerance, f"{what}: error {error} above {tolerance}"


def test_splat_bytes_of_one_known_gaussian(tmp_path):
    g = {"means": np.array([[1.0, -2.0, 0.5]], np.float32), "log_scales": np.log([[0.1, 0.2, 0.4]]).astype(np.float32),
         "quats": np.array([[2.0, 0.0, 0.0, 0.0]], np.float32), "opacity_logits": np.array([0.0], np.float32),
         "sh0": np.array([[[0.0, 1.0, -10.0]]], np.float32), "shN": np.zeros((1, 15, 3), np.float32)}
    write_gaussians("splat", tmp_path / "one.splat", g)
    data = (tmp_path / "one.splat").read_bytes()
    assert len(data) == 32
    assert struct.unpack("<6f", data[:24]) == pytest.approx((1.0, -2.0, 0.5, 0.1, 0.2, 0.4), rel=1e-6)
    # r = 0.5 * 255, g = (0.5 + C0) * 255, b clipped to 0, a = 0.5 * 255; w = 1 -> 256 clipped to 255
    assert list(data[24:]) == [128, round((0.5 + C0) * 255), 0, 128, 255, 128, 128, 128]


def test_splat_reads_back_within_quantisation(tmp_path):
    g = random_gaussians(1000, degree=0)
    write_gaussians("splat", tmp_path / "g.splat", g)
    back = read_gaussians("splat", tmp_path / "g.splat")
    volume_opacity = np.exp(g["log_scales"].astype(np.float64).sum(1)) * sigmoid(g["opacity_logits"])
    order = np.argsort(-volume_opacity, kind="stable")
    assert np.array_equal(back["means"], g["means"][order])
    assert_close_to(back["log_scales"], g["log_scales"][order], 1e-6, "log-scales")
    colour = np.clip(0.5 + C0 * g["sh0"][order, 0], 0, 1)
    assert_close_to(0.5 + C0 * back["sh0"][:, 0], colour, 0.5 / 255 + 1e-6, "colours")
    assert_close_to(sigmoid(back["opacity_logits"]), sigmoid(g["opacity_logits"][order]), 0.5 / 255 + 1e-6, "alpha")
    assert_same_rotations(back["quats"], g["quats"][order], 0.02)


def test_compressed_ply_reads_back_within_chunk_quantisation(tmp_path):
    n = 1000  # four chunks, the last one partial
    g = random_gaussians(n)
    write_gaussians("compressed-ply", tmp_path / "g.compressed.ply", g)
    data = (tmp_path / "g.compressed.ply").read_bytes()
    assert data.startswith(b"ply\nformat binary_little_endian 1.0\n")
    assert b"element chunk 4\n" in data and b"element vertex 1000\n" in data and b"element sh 1000\n" in data
    back = read_gaussians("compressed-ply", tmp_path / "g.compressed.ply")
    order = morton_order(g["means"].astype(np.float64))
    chunks = np.arange(n) // CHUNK

    def chunk_step(values, bits):  # the quantisation step of each Gaussian's chunk, per axis
        span = np.stack([np.ptp(values[chunks == c], axis=0) for c in range(chunks[-1] + 1)])[chunks]
        return span / (2.0 ** np.array(bits) - 1)

    means = g["means"][order].astype(np.float64)
    error = np.abs(back["means"] - means)
    assert (error <= chunk_step(means, [11, 10, 11]) / 2 + 1e-5).all()
    assert error.max() < 0.05, "Morton order keeps chunks compact: much finer than the scene's 6-unit extent"
    scales = g["log_scales"][order].astype(np.float64)
    assert (np.abs(back["log_scales"] - scales) <= chunk_step(scales, [11, 10, 11]) / 2 + 1e-5).all()
    colour = 0.5 + C0 * g["sh0"][order, 0].astype(np.float64)
    assert (np.abs(0.5 + C0 * back["sh0"][:, 0] - colour) <= chunk_step(colour, [8, 8, 8]) / 2 + 1e-5).all()
    assert_close_to(sigmoid(back["opacity_logits"]), sigmoid(g["opacity_logits"][order]), 0.5 / 255 + 1e-5, "alpha")
    assert_same_rotations(back["quats"], g["quats"][order], 0.003)
    assert_close_to(back["shN"], g["shN"][order], 8 / 256 / 2 + 1e-6, "SH rest")


def test_spz_header_and_read_back_within_quantisation(tmp_path):
    g = random_gaussians(500)
    write_gaussians("spz", tmp_path / "g.spz", g)
    raw = gzip.decompress((tmp_path / "g.spz").read_bytes())
    assert struct.unpack_from("<IIIBBBB", raw) == (0x5053474E, 3, 500, 3, 12, 0, 0)
    assert raw[:4] == b"NGSP"
    assert len(raw) == 16 + 500 * (9 + 1 + 3 + 3 + 4 + 45)
    # RUB on disk: the first point's y is stored negated.
    first_y = int.from_bytes(raw[16 + 3:16 + 6], "little", signed=True) / 4096
    assert first_y == pytest.approx(-g["means"][0, 1], abs=2 ** -12)
    back = read_gaussians("spz", tmp_path / "g.spz")
    assert_close_to(back["means"], g["means"], 2.0 ** -13 + 1e-6, "positions")
    assert_close_to(back["log_scales"], g["log_scales"], 1 / 32 + 1e-6, "log-scales")
    assert_close_to(back["sh0"], g["sh0"], 0.5 / (0.15 * 255) + 1e-6, "colours (f_dc)")
    assert_close_to(sigmoid(back["opacity_logits"]), sigmoid(g["opacity_logits"]), 0.5 / 255 + 1e-5, "alpha")
    assert_same_rotations(back["quats"], g["quats"], 0.003)
    assert_close_to(back["shN"][:, :3], g["shN"][:, :3], 4.5 / 128, "SH degree 1 (5 bits)")
    assert_close_to(back["shN"][:, 3:], g["shN"][:, 3:], 8.5 / 128, "SH degrees 2-3 (4 bits)")


def test_spz_version_4_is_the_same_blocks_as_zstd_streams_behind_a_plain_header(tmp_path):
    for degree in (3, 0):
        g = random_gaussians(500, degree=degree, seed=degree)
        write_gaussians("spz", tmp_path / "v3.spz", g, antialiased=True)
        write_gaussians("spz", tmp_path / "v4.spz", g, antialiased=True, spz_version=4)
        legacy = gzip.decompress((tmp_path / "v3.spz").read_bytes())
        data = (tmp_path / "v4.spz").read_bytes()
        streams = 6 if degree else 5  # degree 0 has no SH block, and an empty block is no stream
        assert struct.unpack_from("<IIIBBBBI", data) == (0x5053474E, 4, 500, degree, 12, 1, streams, 32)
        assert data[20:32] == bytes(12), "reserved"
        blocks, start = [], 32 + 16 * streams
        for index in range(streams):
            compressed, size = struct.unpack_from("<QQ", data, 32 + 16 * index)
            blocks.append(zstandard.ZstdDecompressor().decompress(data[start:start + compressed]))
            assert len(blocks[-1]) == size
            start += compressed
        assert start == len(data)
        assert b"".join(blocks) == legacy[16:], "version 4 holds the very bytes of version 3, split into streams"
        assert legacy[4] == 3 and legacy[14] == 1
        v3, v4 = read_gaussians("spz", tmp_path / "v3.spz"), read_gaussians("spz", tmp_path / "v4.spz")
        assert all(np.array_equal(v3[key], v4[key]) for key in v3)
    with pytest.raises(MCSplatError, match="versions 3 and 4"):
        write_gaussians("spz", tmp_path / "v5.spz", g, spz_version=5)


def damaged_copies(good: Path, cuts: dict[str, Callable[[bytes], bytes]]) -> dict[str, Path]:
    """name -> a copy of `good` changed by cuts[name] (bytes -> bytes), beside it."""
    paths = {}
    for name, change in cuts.items():
        paths[name] = good.with_name(f"{name}{good.suffix}")
        paths[name].write_bytes(change(good.read_bytes()))
    return paths


def assert_one_line_naming(path, read):
    with pytest.raises(MCSplatError) as error:
        read(path)
    assert str(error.value).startswith(f"{path}: ") and "\n" not in str(error.value), str(error.value)


def test_a_damaged_spz_is_one_line_naming_it(tmp_path, capsys):
    """`view` reads any .spz a user hands it: cut short, a bad stream, a wrong version or a count that does not
    match is one line naming the file, never a traceback."""
    g = random_gaussians(300, degree=2)
    write_gaussians("spz", tmp_path / "v3.spz", g)
    write_gaussians("spz", tmp_path / "v4.spz", g, spz_version=4)
    v3 = damaged_copies(tmp_path / "v3.spz", {
        "v3_cut": lambda b: b[:len(b) // 2],
        "v3_version_2": lambda b: gzip.compress(gzip.decompress(b)[:4] + struct.pack("<I", 2) + gzip.decompress(b)[8:]),
        "v3_count": lambda b: gzip.compress(gzip.decompress(b)[:8] + struct.pack("<I", 301) + gzip.decompress(b)[12:]),
        "not_spz": lambda b: b"PK\x03\x04" + b[4:]})
    v4 = damaged_copies(tmp_path / "v4.spz", {
        "v4_cut": lambda b: b[:len(b) - 100],
        "v4_trailing": lambda b: b + b"\0",
        "v4_count": lambda b: b[:8] + struct.pack("<I", 10 ** 9) + b[12:],
        "v4_streams": lambda b: b[:15] + bytes([7]) + b[16:],
        "v4_frame": lambda b: b[:32 + 16 * 6 + 4] + bytes(20) + b[32 + 16 * 6 + 24:],
        "v4_short": lambda b: b[:20]})
    for path in (*v3.values(), *v4.values()):
        assert_one_line_naming(path, lambda p: read_gaussians("spz", p))
    pytest.importorskip("viser", reason="the viewer's optional dependency viser is not installed")
    capsys.readouterr()
    assert main(["view", str(v4["v4_frame"])]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and str(v4["v4_frame"]) in error


def test_view_opens_every_format_export_writes(tmp_path):
    """`mcsplat view` reads each file of Gaussians by its ending, and what it reads renders, a degree-0 file's empty
    SH included (numpy hands it over with strides of 0, which the kernels refuse)."""
    pytest.importorskip("viser", reason="the viewer's optional dependency viser is not installed")
    import torch

    from mcsplat.camera import Camera
    from mcsplat.render import render
    from mcsplat.viewer.saved import load_for_viewing

    g = random_gaussians(200, degree=1, seed=9)
    world_to_camera = torch.eye(4)
    world_to_camera[2, 3] = 10.0  # the Gaussians lie within +-3 of the origin, 10 in front of the camera
    camera = Camera(torch.tensor([[40.0, 0, 32], [0, 40.0, 32], [0, 0, 1]]), world_to_camera, 64, 64)
    for name in ("splat", "compressed-ply", "spz", "sog"):
        path = tmp_path / f"x{EXTENSIONS[name]}"
        write_gaussians(name, path, g)
        model, cameras, _, _ = load_for_viewing(path, torch.device("cpu"))
        assert model.num_gaussians == 200 and cameras == [], name
        assert model.sh_degree == (0 if name == "splat" else 1), name
        assert torch.isfinite(render(model, camera, (0.0, 0.0, 0.0)).rgb).all(), name


def test_pruning_keeps_the_most_contributing_gaussians():
    g = random_gaussians(200, degree=0)
    g["opacity_logits"][:50] = -8.0  # opacity 0.0003: dead
    keep = select_gaussians(g, min_opacity=0.005)
    assert keep.tolist() == list(range(50, 200))
    g["log_scales"][60] = 1.0  # by far the largest footprint
    top = select_gaussians(g, min_opacity=0.005, max_gaussians=10)
    assert len(top) == 10 and 60 in top and (top >= 50).all()
    with pytest.raises(MCSplatError, match="--max-gaussians"):
        select_gaussians(g, max_gaussians=0)


def test_cli_export_each_format_with_pruning(tiny_run, tmp_path, capsys):
    total = read_ply(tiny_run / "point_cloud.ply")["means"].shape[0]
    for name in ("ply", "splat", "compressed-ply", "spz", "sog", "glb", "gltf"):
        out = tmp_path / f"x{EXTENSIONS.get(name, '.ply')}"
        assert main(["export", str(tiny_run), "--format", name, "--out", str(out), "--max-gaussians", "300"]) == 0
        back = read_ply(out) if name == "ply" else read_gaussians(name, out)
        assert back["means"].shape[0] == min(300, total), name
    assert main(["export", str(tiny_run), "--out", str(tmp_path / "x4.spz"), "--max-gaussians", "300",
                 "--spz-version", "4"]) == 0
    assert (tmp_path / "x4.spz").read_bytes()[:8] == b"NGSP\x04\0\0\0"
    assert main(["export", str(tiny_run), "--format", "spz"]) == 0
    assert (tiny_run / "point_cloud.spz").is_file(), "the default name is the run's point_cloud.<format>"
    assert (tiny_run / "point_cloud.spz").read_bytes()[:2] == b"\x1f\x8b", "version 3 (gzip) unless asked"
    sizes = {name: (tmp_path / f"x{EXTENSIONS.get(name, '.ply')}").stat().st_size for name in EXTENSIONS}
    sizes["ply"] = (tmp_path / "x.ply").stat().st_size
    assert sizes["splat"] == 300 * 32
    assert sizes["spz"] < sizes["compressed-ply"] < sizes["ply"] / 3, sizes  # both keep SH degree 3
    assert (tmp_path / "x4.spz").stat().st_size < sizes["spz"]
    capsys.readouterr()
    assert main(["export", str(tiny_run), "--format", "spz", "--min-opacity", "0.9999"]) == 2
    error = capsys.readouterr().err
    assert error.startswith("mcsplat: error:") and "--min-opacity" in error and error.count("\n") == 1


def test_export_never_replaces_a_run_file_and_the_format_follows_the_name(tiny_run, tmp_path, capsys):
    checkpoint = (tiny_run / "checkpoint.pt").read_bytes()
    folder = tmp_path / "a_folder"
    folder.mkdir()
    refused = [(["--out", str(tiny_run / "checkpoint.pt")], "would replace the run's own checkpoint.pt"),
               (["--out", str(tiny_run / "config.json")], "would replace the run's own config.json"),
               (["--format", "spz", "--out", str(tmp_path / "x.ply")], "names a ply file but --format is spz"),
               (["--out", str(tmp_path / "x.bin")], "must end in"),
               (["--out", str(folder)], "is a folder")]
    for args, expected in refused:
        capsys.readouterr()
        assert main(["export", str(tiny_run), *args]) == 2, args
        error = capsys.readouterr().err
        assert expected in error and error.count("\n") == 1, (args, error)
    assert (tiny_run / "checkpoint.pt").read_bytes() == checkpoint
    assert list(folder.iterdir()) == [] and not (tmp_path / "x.ply").exists()
    # Without --format the name decides: an .spz is written as spz, a .compressed.ply as compressed-ply.
    for name, format_name in (("y.spz", "spz"), ("y.compressed.ply", "compressed-ply"), ("y.splat", "splat"),
                              ("y.sog", "sog")):
        assert main(["export", str(tiny_run), "--out", str(tmp_path / name)]) == 0
        assert read_gaussians(format_name, tmp_path / name)["means"].shape[0] > 0, name


def test_no_command_writes_into_the_scene_the_run_trained_on(tiny_run, mini_demo, tmp_path, capsys):
    import json
    import shutil

    scene = shutil.copytree(mini_demo, tmp_path / "scene")
    run = shutil.copytree(tiny_run, tmp_path / "run")
    config = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**config, "data": str(scene)}))
    before = {p: p.read_bytes() for p in scene.rglob("*") if p.is_file()}
    cases = [["export", str(run), "--format", "mesh", "--out", str(scene / "mesh.ply"), "--voxel-budget", "300000"],
             ["export", str(run), "--out", str(scene / "train" / "r_0.ply")],
             ["export", str(run), "--out", str(scene / "x.spz")],
             ["render", str(run), "--out", str(scene / "renders")],
             ["render", str(run), "--video", "--frames", "4", "--out", str(scene / "loop.mp4")],
             ["report", str(run), "--out", str(scene)]]
    for argv in cases:
        capsys.readouterr()
        assert main(argv) == 2, argv
        error = capsys.readouterr().err
        assert error.startswith("mcsplat: error:") and "inside the scene folder" in error, (argv, error)
        assert error.count("\n") == 1, error
    assert {p: p.read_bytes() for p in scene.rglob("*") if p.is_file()} == before, "nothing written into the scene"


def test_one_table_holds_every_format_and_the_cli_takes_it_as_it_is(tmp_path):
    """A format is its module and its entry in the table: --format's choices, its help and each default file follow
    from the table (export/formats.py), the Gaussian formats from io/formats' own; the library's defaults are the
    command's."""
    import dataclasses
    import typing

    import tyro

    from mcsplat.cli import Export
    from mcsplat.export import EXPORT_FORMATS, ExportOptions, format_help
    from mcsplat.io.formats import FORMATS
    from mcsplat.run.folder import RunDir

    assert list(EXPORT_FORMATS) == ["ply", "splat", "compressed-ply", "spz", "sog", "glb", "gltf", "mesh"]
    assert [name for name, entry in EXPORT_FORMATS.items() if entry.ending is not None] == list(FORMATS)
    annotation = typing.get_type_hints(ExportOptions, include_extras=True)["format"]
    choices, _ = typing.get_args(typing.get_args(annotation)[0])  # Annotated[Literal[...] | None, help]
    assert typing.get_args(choices) == tuple(EXPORT_FORMATS)
    assert all(f"{name}: " in format_help() for name in EXPORT_FORMATS)
    folder = RunDir(tmp_path)
    assert {name: entry.default_file(folder).name for name, entry in EXPORT_FORMATS.items()} == {
        "ply": "point_cloud.ply", "splat": "point_cloud.splat", "compressed-ply": "point_cloud.compressed.ply",
        "spz": "point_cloud.spz", "sog": "point_cloud.sog", "glb": "point_cloud.glb", "gltf": "point_cloud.gltf",
        "mesh": "mesh.ply"}
    # The command's options are the library's, declared once: the CLI nests ExportOptions itself, without a prefix.
    nested = typing.get_type_hints(Export, include_extras=True)["export"]
    assert typing.get_args(nested)[0] is ExportOptions and tyro.conf.OmitArgPrefixes in typing.get_args(nested)
    assert [field.name for field in dataclasses.fields(Export)] == ["run", "export"]
    assert dataclasses.fields(Export)[1].default_factory() == ExportOptions()


def test_the_plain_ply_through_the_table_is_the_ply_training_writes(tmp_path):
    import torch

    from mcsplat.io.ply import write_ply

    g = random_gaussians(50)
    keep = np.zeros(50, dtype=bool)
    keep[::3] = True
    write_ply(tmp_path / "direct.ply", {k: torch.from_numpy(v) for k, v in g.items()}, keep=torch.from_numpy(keep))
    write_gaussians("ply", tmp_path / "table.ply", {k: v[keep] for k, v in g.items()})
    assert (tmp_path / "table.ply").read_bytes() == (tmp_path / "direct.ply").read_bytes()
    back = read_gaussians("ply", tmp_path / "table.ply")
    assert all(np.array_equal(back[k], g[k][keep]) for k in g)
