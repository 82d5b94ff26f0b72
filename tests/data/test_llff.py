"""LLFF loading: the shared fern (images_8 only, partial COLMAP model), and bird's poses_bounds.npy vs its COLMAP."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from mcsplat.data import Scene, load_scene
from mcsplat.data.llff import load_llff
from tests.support.helpers import visible_fraction

FERN = "llff_fern/fern"


@pytest.fixture(scope="module")
def fern(shared_data: Path) -> Scene:
    return load_scene(shared_data / FERN)


def test_fern(fern: Scene, shared_data: Path) -> None:
    poses_bounds = np.load(shared_data / FERN / "poses_bounds.npy")
    height, width, focal = poses_bounds[0, :15].reshape(3, 5)[:, 4]
    assert (height, width) == (3024, 4032) and focal == pytest.approx(3260.526, abs=1e-3)
    assert fern.kind == "llff" and fern.background == (0.0, 0.0, 0.0)
    views = fern.train + fern.test
    assert len(views) == 20 and [v.name for v in fern.test] == ["image000", "image008", "image016"]
    for view in views:
        assert (view.camera.width, view.camera.height) == (504, 378)
        np.testing.assert_allclose(view.camera.K.numpy(), [[focal / 8, 0, 252], [0, focal / 8, 189], [0, 0, 1]],
                                   rtol=1e-6)
    assert fern.points is not None and fern.points.shape == (10091, 3)
    assert fern.point_colors.shape == (10091, 3)
    fractions = np.array([visible_fraction(v, fern.points) for v in views])
    assert (fractions >= 0.5).mean() >= 0.9


def test_fern_poses_follow_llff_convention(fern: Scene, shared_data: Path) -> None:
    """Camera-to-world columns are [down, right, backwards]: OpenCV x = right, y = down, z = -backwards."""
    poses = np.load(shared_data / FERN / "poses_bounds.npy")[:, :15].reshape(-1, 3, 5)
    views = sorted(fern.train + fern.test, key=lambda v: v.name)
    for pose, view in zip(poses, views):
        c2w = np.linalg.inv(view.camera.world_to_camera.double().numpy())
        np.testing.assert_allclose(c2w[:3, 0], pose[:, 1], atol=1e-5)
        np.testing.assert_allclose(c2w[:3, 1], pose[:, 0], atol=1e-5)
        np.testing.assert_allclose(c2w[:3, 2], -pose[:, 2], atol=1e-5)
        np.testing.assert_allclose(c2w[:3, 3], pose[:, 3], atol=1e-4)
    centres = poses[[int(v.name[-3:]) for v in fern.train], :, 3]
    assert fern.radius == pytest.approx(1.1 * np.linalg.norm(centres - centres.mean(0), axis=1).max(), rel=1e-5)


def test_fern_downscale_resizes_images_8(shared_data: Path) -> None:
    scene = load_scene(shared_data / FERN, downscale=16, test_every=0)
    assert len(scene.train) == 20 and scene.test == []
    view = scene.train[0]
    assert (view.camera.width, view.camera.height) == (252, 189)
    assert view.camera.fx == pytest.approx(3260.526 / 16, abs=1e-3)


def test_bird_poses_bounds_agree_with_its_colmap_model(shared_data: Path) -> None:
    """bird ships both formats (poses_bounds.npy made from sparse/0 by LLFF's imgs2poses): the poses must agree."""
    root = shared_data / "colmap_bird"
    as_llff = load_llff(root, downscale=4, background=(0.0, 0.0, 0.0), test_every=8)
    as_colmap = load_scene(root, downscale=4)
    assert as_colmap.kind == "colmap"  # COLMAP has priority when a folder holds both
    for a, b in zip(as_llff.train + as_llff.test, as_colmap.train + as_colmap.test):
        assert a.name == b.name
        torch.testing.assert_close(a.camera.world_to_camera, b.camera.world_to_camera, atol=1e-5, rtol=0)
        assert (a.camera.width, a.camera.height) == (b.camera.width, b.camera.height) == (136, 240)
    assert as_llff.radius == pytest.approx(as_colmap.radius, rel=1e-5)
