"""IDR / NeuS / MonoSDF scenes (cameras.npz): the real DTU scan24 in MonoSDF's layout, the decomposition, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from mcsplat.data import load_scene
from mcsplat.data.idr import decompose
from mcsplat.errors import DataError


def rotation(seed: int) -> np.ndarray:
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


@pytest.mark.parametrize("scale", [1.0, 3.7, -2.0])
def test_decompose_recovers_k_and_the_pose_of_any_projection(scale):
    K = np.array([[900.0, 0.3, 201.0], [0.0, 880.0, 190.0], [0.0, 0.0, 1.0]])
    R, t = rotation(4), np.array([0.2, -0.1, 2.5])
    P = scale * K @ np.hstack([R, t[:, None]])
    K2, w2c = decompose(P, "test")
    np.testing.assert_allclose(K2, K, rtol=1e-10, atol=1e-8)
    np.testing.assert_allclose(w2c[:3, :3], R, atol=1e-10)
    np.testing.assert_allclose(w2c[:3, 3], t, atol=1e-10)


def test_dtu_scan24_in_monosdf_layout(shared_data):
    scene = load_scene(shared_data / "dtu_scan24_monosdf" / "scan24")
    assert scene.kind == "idr" and len(scene.train) == 42 and len(scene.test) == 7 and scene.points is None
    camera = scene.train[0].camera  # image 000001 (000000 is the first test view)
    assert (camera.width, camera.height) == (384, 384)
    first = scene.test[0].camera
    # SOURCE.md: world_mat_0 decomposes to fx 2892.3, fy 2883.2, cx 823.2, cy 619.1 at 1600x1200; MonoSDF's crop
    # takes cx - 200, then x 384/1200.
    np.testing.assert_allclose(first.K[[0, 1, 0, 1], [0, 1, 2, 2]].numpy(),
                               [2892.3 * 0.32, 2883.2 * 0.32, 623.2 * 0.32, 619.1 * 0.32], atol=0.05)
    for view in scene.train + scene.test:
        w2c = view.camera.world_to_camera.double()
        np.testing.assert_allclose((w2c[:3, :3] @ w2c[:3, :3].T).numpy(), np.eye(3), atol=1e-5)
        centre = w2c[:3, 3]  # the unit sphere's centre (the object's) in camera coordinates
        assert 2.5 < float(centre[2]) < 3.0, "in front of every camera, about 2.7 units away"
        u, v, w = (view.camera.K.double() @ centre).tolist()
        assert abs(u / w - 199.4) < 3 and abs(v / w - 198.1) < 3, "the object sits at the principal point"
    assert scene.train[0].image_float().shape == (384, 384, 3)


def write_scene(folder, count=2, size=(40, 30), cx=None, drop=None):
    folder.mkdir()
    K = np.array([[50.0, 0.0, size[0] / 2 if cx is None else cx], [0.0, 50.0, size[1] / 2], [0.0, 0.0, 1.0]])
    arrays = {}
    for i in range(count):
        world = np.eye(4)
        world[:3, :4] = K @ np.hstack([rotation(i), np.array([[0.0], [0.0], [3.0]])])
        if i != drop:
            arrays[f"world_mat_{i}"] = world
        Image.new("RGB", size, (10 * i, 20, 30)).save(folder / f"{i:06d}_rgb.png")
    np.savez(folder / "cameras.npz", **arrays)
    return folder


def test_a_plain_idr_scene_keeps_its_intrinsics_and_resizes(tmp_path):
    scene = load_scene(write_scene(tmp_path / "s", count=3), downscale=2, test_every=0)
    assert len(scene.train) == 3 and (scene.train[0].camera.width, scene.train[0].camera.height) == (20, 15)
    torch.testing.assert_close(scene.train[0].camera.K, torch.tensor([[25.0, 0, 10], [0, 25.0, 7.5], [0, 0, 1]]))


@pytest.mark.parametrize("kwargs, message", [
    ({"drop": 1}, "has no world_mat_1"),
    ({"cx": 5.0}, "principal point"),
])
def test_bad_cameras_give_one_line_errors(tmp_path, kwargs, message):
    with pytest.raises(DataError, match=message):
        load_scene(write_scene(tmp_path / "s", **kwargs))


def test_cameras_without_images(tmp_path):
    (tmp_path / "s").mkdir()
    np.savez(tmp_path / "s" / "cameras.npz", world_mat_0=np.eye(4))
    with pytest.raises(DataError, match="no images"):
        load_scene(tmp_path / "s")
