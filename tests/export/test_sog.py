"""PlayCanvas's SOG (.sog): the bundle's members and meta.json, texels checked on hand-computed values, every field
read back within the format's quantisation, the SH palette, the same bytes for the same scene, and a damaged .sog as
one line. What splat-transform itself decodes from a .sog is in test_splat_transform.py."""

from __future__ import annotations

import io
import json
import math
import zipfile

import numpy as np
import pytest
from PIL import Image

from mcsplat.cli import main
from mcsplat.io.formats import read_gaussians, write_gaussians
from mcsplat.io.formats.compressed_ply import morton_order
from mcsplat.io.formats.sog import palette_size

from tests.export.test_formats import assert_one_line_naming, assert_same_rotations, random_gaussians, sigmoid

IMAGES = ["means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp"]
SH_IMAGES = ["shN_centroids.webp", "shN_labels.webp"]


def members(path) -> dict[str, bytes]:
    with zipfile.ZipFile(path) as bundle:
        return {info.filename: bundle.read(info) for info in bundle.infolist()}


def texels(data: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(data)) as image:
        assert image.format == "WEBP"
        return np.asarray(image.convert("RGBA")).reshape(-1, 4)


def test_bundle_members_and_texels_of_known_gaussians(tmp_path):
    e = math.e
    g = {"means": np.array([[0.0, 0.0, 0.0], [e - 1, 1 - e, 2.0]], np.float32),
         "log_scales": np.array([[-3.0, -3.0, -3.0], [-1.0, -2.0, -3.0]], np.float32),
         # w x y z: the identity; -y (y the largest, negative: the quaternion is negated); w = x (the first wins)
         "quats": np.array([[2.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]], np.float32),
         "opacity_logits": np.array([0.0, 20.0], np.float32),
         "sh0": np.array([[[0.5, 0.5, 0.5]], [[-1.0, 0.0, 1.0]]], np.float32),
         "shN": np.zeros((2, 3, 3), np.float32)}
    order = morton_order(g["means"].astype(np.float64))
    write_gaussians("sog", tmp_path / "two.sog", g)
    files = members(tmp_path / "two.sog")
    assert list(files) == ["meta.json", *IMAGES, *SH_IMAGES]
    with zipfile.ZipFile(tmp_path / "two.sog") as bundle:
        assert {info.compress_type for info in bundle.infolist()} == {zipfile.ZIP_STORED}
    meta = json.loads(files["meta.json"])
    assert meta["version"] == 2 and meta["count"] == 2 and "model" not in meta
    assert meta["means"]["mins"] == pytest.approx([0.0, -1.0, 0.0]) and meta["means"]["files"] == IMAGES[:2]
    assert meta["means"]["maxs"] == pytest.approx([1.0, 0.0, math.log(3.0)])
    assert len(meta["scales"]["codebook"]) == len(meta["sh0"]["codebook"]) == len(meta["shN"]["codebook"]) == 256
    assert meta["shN"]["count"] == 2 and meta["shN"]["bands"] == 1
    pixels = {name: texels(files[name]) for name in IMAGES + SH_IMAGES}
    assert all(len(pixels[name]) == 4 * 4 for name in IMAGES), "4 x 4 texels: multiples of 4"
    first, second = (0, 1) if order[0] == 0 else (1, 0)  # the texel of each Gaussian (Morton order)
    # 16-bit steps of t = sign(v) ln(|v| + 1) over its bounds: the origin is the bottom of x and z, the top of y.
    steps = pixels["means_l.webp"][:2, :3].astype(int) + 256 * pixels["means_u.webp"][:2, :3].astype(int)
    assert steps[first].tolist() == [0, 65535, 0] and steps[second].tolist() == [65535, 0, 65535]
    assert pixels["quats.webp"][first].tolist() == [128, 128, 128, 252]
    assert pixels["quats.webp"][second].tolist() == [128, 128, 128, 254]
    assert pixels["sh0.webp"][first, 3] == 128 and pixels["sh0.webp"][second, 3] == 255  # sigmoid(0), sigmoid(20)
    assert pixels["shN_centroids.webp"].shape == (64 * 3, 4), "a row of 64 palette entries of 3 coefficients"
    assert pixels["means_l.webp"][2:, :3].max() == 0, "the texels after the last Gaussian are zero"
    back = read_gaussians("sog", tmp_path / "two.sog")
    assert np.allclose(back["means"], g["means"][order], atol=1e-4)
    quarter = {"quats": np.array([[1.0, 1.0, 0.0, 0.0]], np.float32)}
    write_gaussians("sog", tmp_path / "one.sog", {**{k: v[:1] for k, v in g.items()}, **quarter})
    assert texels(members(tmp_path / "one.sog")["quats.webp"])[0].tolist() == [255, 128, 128, 252]


def test_reads_back_within_quantisation(tmp_path):
    n = 1000  # up to 1,024 Gaussians each is its own palette entry: the SH are only the codebook's steps off
    g = random_gaussians(n, degree=3, seed=5)
    write_gaussians("sog", tmp_path / "g.sog", g)
    meta = json.loads(members(tmp_path / "g.sog")["meta.json"])
    back = read_gaussians("sog", tmp_path / "g.sog")
    order = morton_order(g["means"].astype(np.float64))
    g = {key: value[order].astype(np.float64) for key, value in g.items()}

    def half_step(codebook, values):  # the largest distance of a value in the codebook's range to its nearest entry
        codebook = np.asarray(codebook)
        return np.abs(values[..., None] - codebook).min(axis=-1).max()

    # Positions: 16-bit steps of t = sign(v) ln(|v| + 1); dv = (|v| + 1) dt.
    span = np.array(meta["means"]["maxs"]) - np.array(meta["means"]["mins"])
    assert (np.abs(back["means"] - g["means"]) <= (np.abs(g["means"]) + 1) * span / 65535 * 0.51 + 1e-6).all()
    assert np.abs(back["log_scales"] - g["log_scales"]).max() <= half_step(meta["scales"]["codebook"],
                                                                             g["log_scales"]) + 1e-6
    assert np.abs(back["sh0"] - g["sh0"]).max() <= half_step(meta["sh0"]["codebook"], g["sh0"]) + 1e-6
    assert np.abs(back["log_scales"] - g["log_scales"]).max() < 0.02, "256 codes over 6 units of log-scale"
    assert np.abs(sigmoid(back["opacity_logits"]) - sigmoid(g["opacity_logits"])).max() <= 0.5 / 255 + 1e-6
    assert_same_rotations(back["quats"], g["quats"], 0.006)
    assert meta["shN"]["count"] == n
    assert np.abs(back["shN"] - g["shN"]).max() <= half_step(meta["shN"]["codebook"], g["shN"]) + 1e-6
    assert np.abs(back["shN"] - g["shN"]).max() < 0.01


def test_many_gaussians_share_an_sh_palette_that_fits_them(tmp_path):
    assert [palette_size(n) for n in (1, 1024, 1025, 2400, 35_000, 10 ** 6, 10 ** 7)] == [
        1, 1024, 1024, 1024, 2048, 65536, 65536]
    rng = np.random.default_rng(1)
    g = random_gaussians(3000, degree=2, seed=2)
    # SH of a few dozen kinds of surface, with noise: what a palette is made for
    kinds = rng.uniform(-0.4, 0.4, (40, 8, 3))
    g["shN"] = (kinds[rng.integers(0, 40, 3000)] + rng.normal(0, 0.01, (3000, 8, 3))).astype(np.float32)
    write_gaussians("sog", tmp_path / "g.sog", g)
    files = members(tmp_path / "g.sog")
    meta = json.loads(files["meta.json"])
    assert meta["shN"]["count"] == 1024 and meta["shN"]["bands"] == 2
    labels = texels(files["shN_labels.webp"])[:3000]
    assert (labels[:, 0] + 256 * labels[:, 1].astype(int)).max() < 1024
    with Image.open(io.BytesIO(files["shN_centroids.webp"])) as palette:
        assert palette.size == (64 * 8, 16)
    back = read_gaussians("sog", tmp_path / "g.sog")
    error = back["shN"] - g["shN"][morton_order(g["means"].astype(np.float64))]
    assert np.sqrt((error ** 2).mean()) < 0.02
    write_gaussians("sog", tmp_path / "again.sog", g)
    assert (tmp_path / "again.sog").read_bytes() == (tmp_path / "g.sog").read_bytes(), "the same bytes again"


def test_degree_0_has_no_palette_and_antialiasing_is_recorded(tmp_path):
    g = random_gaussians(100, degree=0)
    write_gaussians("sog", tmp_path / "g.sog", g, antialiased=True)
    files = members(tmp_path / "g.sog")
    meta = json.loads(files["meta.json"])
    assert list(files) == ["meta.json", *IMAGES] and "shN" not in meta
    assert meta["model"] == "antialiased" and meta["antialias"] is True
    assert read_gaussians("sog", tmp_path / "g.sog")["shN"].shape == (100, 0, 3)


def rewritten(source, target, change) -> None:
    """`target`: the bundle `source` with change(files) applied to its {name: bytes}."""
    files = members(source)
    change(files)
    with zipfile.ZipFile(target, "w") as bundle:
        for name, data in files.items():
            bundle.writestr(name, data)


def test_a_damaged_sog_is_one_line_naming_it(tmp_path, capsys):
    """`view` reads any .sog a user hands it: a cut zip, a missing image, a meta.json that is no JSON or lacks a
    field, a count larger than the images, a damaged image, labels past the palette are one line naming the file."""
    good = tmp_path / "good.sog"
    write_gaussians("sog", good, random_gaussians(200, degree=1))
    meta = json.loads(members(good)["meta.json"])

    def with_meta(**fields):  # meta.json with `fields` changed (None: left out)
        edited = {key: value for key, value in {**meta, **fields}.items() if value is not None}
        return lambda files: files.update({"meta.json": json.dumps(edited).encode()})

    def labels_past_the_palette(files):
        pixels = texels(files["shN_labels.webp"]).copy()
        pixels[0, :2] = 255
        buffer = io.BytesIO()
        Image.fromarray(pixels.reshape(16, 16, 4), "RGBA").save(buffer, format="WEBP", lossless=True)
        files["shN_labels.webp"] = buffer.getvalue()

    damaged = {"no_quats": lambda files: files.pop("quats.webp"),
               "not_json": lambda files: files.update({"meta.json": b"{not json"}),
               "version_1": with_meta(version=None),  # no "version": SOG 1's meta.json
               "no_means": with_meta(means={"files": meta["means"]["files"]}),
               "short_codebook": with_meta(scales={**meta["scales"], "codebook": [0.0] * 10}),
               "too_many": with_meta(count=10 ** 6),
               "bad_image": lambda files: files.update({"sh0.webp": files["sh0.webp"][:40]}),
               "past_palette": labels_past_the_palette}
    paths = []
    for name, change in damaged.items():
        paths.append(tmp_path / f"{name}.sog")
        rewritten(good, paths[-1], change)
    paths.append(tmp_path / "cut.sog")
    paths[-1].write_bytes(good.read_bytes()[:len(good.read_bytes()) // 2])
    for path in paths:
        assert_one_line_naming(path, lambda p: read_gaussians("sog", p))
    pytest.importorskip("viser", reason="the viewer's optional dependency viser is not installed")
    import torch

    from mcsplat.viewer.saved import load_for_viewing

    model, cameras, _, _ = load_for_viewing(good, torch.device("cpu"))
    assert model.num_gaussians == 200 and model.sh_degree == 1 and cameras == []
    capsys.readouterr()
    assert main(["view", str(tmp_path / "cut.sog")]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "cut.sog" in error


def test_a_write_cut_short_leaves_the_earlier_file_whole(tmp_path, monkeypatch):
    """The bundle is written beside its name and moved over it whole (io/atomic.py): a write that fails half-way
    (here the zip's third member) leaves the earlier .sog as it was and no temporary file."""
    write_gaussians("sog", tmp_path / "g.sog", random_gaussians(50, degree=1))
    before = (tmp_path / "g.sog").read_bytes()
    written = []
    real = zipfile.ZipFile.writestr

    def failing(self, info, data, *args, **kwargs):
        written.append(info)
        if len(written) == 3:
            raise OSError("the disk went away")
        return real(self, info, data, *args, **kwargs)

    monkeypatch.setattr(zipfile.ZipFile, "writestr", failing)
    with pytest.raises(OSError, match="went away"):
        write_gaussians("sog", tmp_path / "g.sog", random_gaussians(80, degree=1, seed=3))
    assert (tmp_path / "g.sog").read_bytes() == before
    assert [path.name for path in tmp_path.iterdir()] == ["g.sog"]
