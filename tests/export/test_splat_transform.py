"""What PlayCanvas's own reader makes of mcsplat's .sog and .spz (versions 3 and 4): @playcanvas/splat-transform
(npm, pinned; .ci/run installs it) converts each file back to a 3DGS .ply, which must hold every Gaussian with every
attribute within the format's quantisation, say whether the scene was trained with the 2D filter, and agree with
mcsplat's own reader. It runs with Node (tests/export/test_gltf.py finds npm packages the same way); the tests skip,
with the reason, without Node or the package.

splat-transform reads a .spz as raw numbers in the .ply's axes; the file holds Niantic's RUB axes (spz.py), so
what it decodes is the scene turned 180 degrees about x, which the comparisons turn back."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from mcsplat.io.formats import read_gaussians, write_gaussians
from mcsplat.io.formats.compressed_ply import morton_order
from mcsplat.io.ply import read_ply

from tests.export.test_formats import assert_same_rotations, random_gaussians, sigmoid
from tests.export.test_gltf import SH_FLIP, node_modules_with

SPLAT_TRANSFORM = "@playcanvas/splat-transform"
PINNED = f"{SPLAT_TRANSFORM}@3.7.0"  # what .ci/run installs
MINIMUM_NODE = 20  # the package asks for Node 22; its readers run on 20, the oldest tried


def splat_transform_to_ply(source: Path) -> tuple[dict[str, np.ndarray], str]:
    """(the Gaussians of the .ply that splat-transform converts `source` to, that .ply's header)."""
    modules = node_modules_with(SPLAT_TRANSFORM)
    if modules is None:
        pytest.skip(f"no Node with the npm package {SPLAT_TRANSFORM}: npm install -g {PINNED} or set NODE_PATH "
                    "(.ci/run installs it on CI)")
    node = subprocess.run(["node", "--version"], capture_output=True, text=True, timeout=60).stdout
    if int(node.strip().lstrip("v").split(".")[0]) < MINIMUM_NODE:
        pytest.skip(f"Node {node.strip()} is older than {MINIMUM_NODE}, on which {PINNED} was tried")
    out = source.with_name(f"{source.name}.ply")
    done = subprocess.run(["node", str(modules / SPLAT_TRANSFORM / "bin" / "cli.mjs"), "--quiet", "--overwrite",
                           str(source), str(out)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, (done.stdout + done.stderr)[-2000:]
    header = out.read_bytes()[:2000].split(b"end_header")[0].decode("ascii")
    return {key: value.numpy().astype(np.float64) for key, value in read_ply(out).items()}, header


def assert_within(actual, expected, tolerance, what):
    error = np.abs(np.asarray(actual, np.float64) - np.asarray(expected, np.float64)).max(initial=0.0)
    assert error <= tolerance, f"{what}: error {error} above {tolerance}"


def assert_agrees_with_our_reader(theirs, ours):
    for key in ("means", "log_scales", "sh0", "shN"):
        assert_within(theirs[key], ours[key], 1e-5, f"{key}: splat-transform against mcsplat's reader")
    assert_within(sigmoid(theirs["opacity_logits"]), sigmoid(ours["opacity_logits"]), 1e-6, "alpha")
    assert_same_rotations(theirs["quats"], ours["quats"].astype(np.float64), 1e-5)


@pytest.mark.parametrize("degree", [3, 0])
def test_splat_transform_reads_a_sog(tmp_path, degree):
    g = random_gaussians(1000, degree=degree, seed=7)  # 1,000: each its own SH palette entry
    write_gaussians("sog", tmp_path / "g.sog", g, antialiased=degree == 0)
    theirs, header = splat_transform_to_ply(tmp_path / "g.sog")
    assert theirs["means"].shape == (1000, 3) and theirs["shN"].shape == (1000, (degree + 1) ** 2 - 1, 3)
    assert ("SplatRenderMode: mip" in header) == (degree == 0), "the 2D filter, as meta.json's model says"
    order = morton_order(g["means"].astype(np.float64))  # the .sog's order
    g = {key: value[order].astype(np.float64) for key, value in g.items()}
    # 16-bit steps of sign(v) ln(|v| + 1) over [-ln 4, ln 4] (the positions lie within +-3)
    assert_within(theirs["means"], g["means"], 4 * 2 * np.log(4) / 65535, "positions")
    assert_within(theirs["log_scales"], g["log_scales"], 0.02, "log-scales (256 codes over 6 units)")
    assert_within(theirs["sh0"], g["sh0"], 0.01, "SH DC (256 codes over 3 units)")
    assert_within(sigmoid(theirs["opacity_logits"]), sigmoid(g["opacity_logits"]), 0.5 / 255 + 1e-6, "alpha")
    assert_same_rotations(theirs["quats"], g["quats"], 0.006)
    assert_within(theirs["shN"], g["shN"], 0.01, "SH rest (256 codes over 0.8 units)")
    assert_agrees_with_our_reader(theirs, read_gaussians("sog", tmp_path / "g.sog"))


@pytest.mark.parametrize("version", [3, 4])
def test_splat_transform_reads_an_spz(tmp_path, version):
    g = random_gaussians(1000, degree=3, seed=version)
    write_gaussians("spz", tmp_path / "g.spz", g, antialiased=version == 4, spz_version=version)
    theirs, header = splat_transform_to_ply(tmp_path / "g.spz")
    assert theirs["means"].shape == (1000, 3) and theirs["shN"].shape == (1000, 15, 3)
    assert ("SplatRenderMode: mip" in header) == (version == 4), "the flags' antialiasing bit"
    # Turn what splat-transform decoded (the file's RUB axes taken as the .ply's) back into the scene's axes.
    turned = {**theirs, "means": theirs["means"] * [1.0, -1.0, -1.0], "quats": theirs["quats"] * [1, 1, -1, -1],
              "shN": theirs["shN"] * SH_FLIP[:, None]}
    assert_within(turned["means"], g["means"], 2.0 ** -13 + 1e-6, "positions (12 fractional bits)")
    assert_within(turned["log_scales"], g["log_scales"], 1 / 32 + 1e-6, "log-scales")
    assert_within(turned["sh0"], g["sh0"], 0.5 / (0.15 * 255) + 1e-6, "SH DC")
    assert_within(sigmoid(turned["opacity_logits"]), sigmoid(g["opacity_logits"]), 0.5 / 255 + 1e-5, "alpha")
    assert_same_rotations(turned["quats"], g["quats"].astype(np.float64), 0.003)
    assert_within(turned["shN"][:, :3], g["shN"][:, :3], 4.5 / 128, "SH degree 1 (5 bits)")
    assert_within(turned["shN"][:, 3:], g["shN"][:, 3:], 8.5 / 128, "SH degrees 2-3 (4 bits)")
    assert_agrees_with_our_reader(turned, read_gaussians("spz", tmp_path / "g.spz"))


def test_the_pinned_reader_is_the_one_ci_installs():
    """The version named here and in .ci/run's npm line are the same."""
    ci = (Path(__file__).resolve().parents[2] / ".ci" / "run").read_text()
    assert PINNED in ci
