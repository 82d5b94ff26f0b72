"""Very large and very far Gaussians: `mcsplat export` reports them, and --max-scale / --max-distance leave exactly
them out, printing what that does to the test PSNR."""

from __future__ import annotations

import math
import re
import shutil

import numpy as np
import pytest
import torch

from mcsplat.cli import main
from mcsplat.errors import MCSplatError
from mcsplat.io.checkpoint import load_checkpoint, save_checkpoint
from mcsplat.io.formats import outliers
from mcsplat.io.ply import read_ply
from mcsplat.run.trained import load


def params_at(means, largest_scales) -> dict[str, np.ndarray]:
    means = np.asarray(means, dtype=np.float32)
    scales = np.full((len(means), 3), 1e-3, dtype=np.float32)
    scales[:, 0] = largest_scales
    return {"means": means, "log_scales": np.log(scales)}


EXTENT = outliers.Extent(centre=np.array([1.0, 2.0, 3.0]), radius=2.0)


def test_sizes_and_distances_are_measured_in_scene_radii_from_the_cameras_centre():
    params = params_at([[1, 2, 3], [1, 2, 3 + 2 * 150], [1 + 2 * 5, 2, 3]], [2 * 0.01, 2 * 0.5, 2 * 3.0])
    np.testing.assert_allclose(outliers.distances(params, EXTENT), [0, 150, 5])
    np.testing.assert_allclose(outliers.largest_axes(params, EXTENT), [0.01, 0.5, 3.0], rtol=1e-6)
    assert outliers.within(params, EXTENT).tolist() == [True, True, True]
    assert outliers.within(params, EXTENT, max_scale=1.0).tolist() == [True, True, False]
    assert outliers.within(params, EXTENT, max_distance=100).tolist() == [True, False, True]
    assert outliers.within(params, EXTENT, 1.0, 100).tolist() == [True, False, False]
    line = outliers.describe(params, EXTENT)
    assert line.startswith("1 Gaussians larger than 1 scene radius and 1 farther than 100 scene radii"), line
    assert "largest 3 scene radii across, farthest 150 away" in line
    assert outliers.describe(params_at([[1, 2, 3]], [0.02]), EXTENT).startswith("no Gaussian larger than")
    for bad in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(MCSplatError, match="must be a positive number of scene radii"):
            outliers.within(params, EXTENT, max_scale=bad)


@pytest.fixture(scope="module")
def run_with_outliers(tiny_run, tmp_path_factory):
    """The tiny demo run plus two Gaussians: a black one 3 scene radii across over the object (it veils every test
    view) and one 500 scene radii away."""
    run = tmp_path_factory.mktemp("outliers") / "run"
    shutil.copytree(tiny_run, run)
    trained = load(run, torch.device("cpu"))
    scene = trained.scene
    centre, radius = scene.centre.float(), float(scene.radius)
    state = load_checkpoint(run / "checkpoint.pt")
    state.pop("version")
    model = state["model"]
    extra = {key: value[:2].clone() for key, value in model.items()}
    extra["params.means"][0] = centre
    extra["params.log_scales"][0] = math.log(3.0 * radius)
    extra["params.opacity_logits"][0] = 3.0  # opacity 0.95 ...
    extra["params.sh0"][0] = -0.5 / 0.28209479  # ... and black (SH degree 0: 0.5 + C0 x sh0)
    extra["params.shN"][0] = 0.0
    extra["params.means"][1] = centre + torch.tensor([500.0 * radius, 0.0, 0.0])
    extra["params.opacity_logits"][1] = 4.0
    state["model"] = type(model)((key, torch.cat([value, extra[key]])) for key, value in model.items())
    save_checkpoint(run / "checkpoint.pt", state)
    return run


def test_export_reports_them_and_keeps_them_by_default(run_with_outliers, tmp_path, capsys):
    out = tmp_path / "all.ply"
    assert main(["export", str(run_with_outliers), "--out", str(out), "--device", "cpu"]) == 0
    printed = capsys.readouterr().out
    assert re.search(r"1 Gaussians larger than 1 scene radius and 1 farther than 100 scene radii from the cameras "
                     r"\(largest 3 scene radii across, farthest 500 away\)", printed), printed
    model = load(run_with_outliers, torch.device("cpu")).model
    assert read_ply(out)["means"].shape[0] == int((model.opacities > 0.005).sum())


def test_the_limits_leave_out_exactly_them_and_say_what_that_does_to_the_test_psnr(run_with_outliers, tmp_path,
                                                                                  capsys):
    out = tmp_path / "within.ply"
    assert main(["export", str(run_with_outliers), "--max-scale", "1", "--max-distance", "100", "--out", str(out),
                 "--device", "cpu"]) == 0
    printed = capsys.readouterr().out
    assert "2 Gaussians beyond --max-scale / --max-distance: left out" in printed
    assert "no Gaussian larger than 1 scene radius or farther than 100" in printed
    full, kept = map(float, re.search(r"test PSNR on 25 views: ([\d.]+) dB with every Gaussian, ([\d.]+) dB",
                                      printed).groups())
    assert kept > full + 1.0, "the veil over the object is gone from the test views"
    model = load(run_with_outliers, torch.device("cpu")).model
    expected = model.opacities.detach() > 0.005
    expected[-2:] = False
    written = read_ply(out)
    assert torch.equal(written["means"], model.means.detach()[expected])


def test_a_limit_needs_the_scene_and_says_so_in_one_line(run_with_outliers, tmp_path, capsys):
    moved = tmp_path / "moved"
    shutil.copytree(run_with_outliers, moved)
    config = (moved / "config.json").read_text()
    (moved / "config.json").write_text(re.sub(r'"data": "[^"]*"', f'"data": "{tmp_path / "gone"}"', config))
    assert main(["export", str(moved), "--out", str(tmp_path / "plain.ply"), "--device", "cpu"]) == 0
    assert "not checked for very large or very far Gaussians" in capsys.readouterr().out
    assert main(["export", str(moved), "--max-distance", "100", "--out", str(tmp_path / "cut.ply"),
                 "--device", "cpu"]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("mcsplat: error: --max-scale / --max-distance need the run's scene:") and "\n" not in error
    assert not (tmp_path / "cut.ply").exists()
