"""COLMAP loading against the real bird and cup captures, checked against pycolmap and against the images."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from mcsplat.data import Scene, load_scene
from mcsplat.data.colmap_files import read_points3d_bin
from tests.support.helpers import visible_fraction


def pycolmap_cameras(model: Path) -> dict[str, tuple[np.ndarray, np.ndarray, tuple[int, int]]]:
    """name -> (K, world_to_camera 4x4, (w, h)) straight from pycolmap."""
    reconstruction = pycolmap.Reconstruction(str(model))
    out = {}
    for image in reconstruction.images.values():
        camera = reconstruction.cameras[image.camera_id]
        w2c = np.eye(4)
        w2c[:3, :4] = image.cam_from_world().matrix()
        out[image.name] = (camera.calibration_matrix(), w2c, (camera.width, camera.height))
    return out


@pytest.fixture(scope="module")
def bird(shared_data: Path) -> Scene:
    return load_scene(shared_data / "colmap_bird")


@pytest.fixture(scope="module")
def bird_reference(shared_data: Path):
    return pycolmap_cameras(shared_data / "colmap_bird" / "sparse" / "0")


def test_bird_counts_sizes_and_split(bird: Scene, bird_reference) -> None:
    assert bird.kind == "colmap"
    assert len(bird.train) + len(bird.test) == 184
    names = sorted(Path(n).stem for n in bird_reference)
    assert [v.name for v in bird.test] == names[::8]
    assert len(bird.test) == 23 and len(bird.train) == 161
    assert bird.background == (0.0, 0.0, 0.0)
    for view in bird.train + bird.test:
        assert (view.camera.width, view.camera.height) == (544, 960)
        assert view.image.dtype == torch.uint8 and tuple(view.image.shape) == (960, 544, 3)


def test_bird_cameras_equal_pycolmap(bird: Scene, bird_reference) -> None:
    for view in bird.train + bird.test:
        K, w2c, size = bird_reference[view.name + ".jpg"]
        assert size == (544, 960)
        np.testing.assert_allclose(view.camera.K.numpy(), K, rtol=1e-6)
        np.testing.assert_allclose(view.camera.world_to_camera.numpy(), w2c, atol=1e-6)
    focal = {v.camera.fx for v in bird.train}
    # one SIMPLE_PINHOLE camera per image (f spans 793-1037 px in the file, whatever SOURCE.md says)
    assert len(focal) > 100 and 700 < min(focal) < max(focal) < 1100


def test_bird_points_and_colors(bird: Scene, shared_data: Path) -> None:
    reconstruction = pycolmap.Reconstruction(str(shared_data / "colmap_bird" / "sparse" / "0"))
    ids = sorted(reconstruction.points3D.keys())
    xyz = np.array([reconstruction.points3D[i].xyz for i in ids])
    rgb = np.array([reconstruction.points3D[i].color for i in ids]) / 255.0
    assert bird.points is not None and bird.point_colors is not None
    assert bird.points.shape == (6271, 3) and bird.points.dtype == torch.float32
    # points3D.bin stores the points in id order, the order the loader keeps
    np.testing.assert_allclose(bird.points.double().numpy(), xyz, rtol=1e-6, atol=1e-6)
    assert 0.0 <= bird.point_colors.min() and bird.point_colors.max() <= 1.0
    np.testing.assert_allclose(bird.point_colors.double().numpy(), rgb, atol=1e-6)


def test_points3d_reader_matches_pycolmap(shared_data: Path) -> None:
    for scene in ("colmap_bird", "colmap_cup"):
        model = shared_data / scene / "sparse" / "0"
        reconstruction = pycolmap.Reconstruction(str(model))
        xyz, rgb = read_points3d_bin(model / "points3D.bin")
        ids = sorted(reconstruction.points3D.keys())
        np.testing.assert_array_equal(xyz, np.array([reconstruction.points3D[i].xyz for i in ids]))
        np.testing.assert_array_equal(rgb, np.array([reconstruction.points3D[i].color for i in ids]))


def test_bird_cameras_look_at_the_points(bird: Scene) -> None:
    fractions = np.array([visible_fraction(v, bird.points) for v in bird.train + bird.test])
    assert (fractions >= 0.5).mean() >= 0.9


def test_bird_radius_from_pycolmap_centres(bird: Scene, shared_data: Path) -> None:
    reconstruction = pycolmap.Reconstruction(str(shared_data / "colmap_bird" / "sparse" / "0"))
    train_names = {v.name + ".jpg" for v in bird.train}
    centres = np.array([im.projection_center() for im in reconstruction.images.values() if im.name in train_names])
    assert len(centres) == 161
    expected = 1.1 * np.linalg.norm(centres - centres.mean(axis=0), axis=1).max()
    assert bird.radius == pytest.approx(expected, rel=1e-5)


def test_bird_images_are_the_files(bird: Scene, shared_data: Path) -> None:
    view = bird.test[1]
    expected = np.asarray(Image.open(shared_data / "colmap_bird" / "images" / f"{view.name}.jpg").convert("RGB"))
    np.testing.assert_array_equal(view.image.numpy(), expected)
    as_float = view.image_float()
    assert as_float.dtype == torch.float32 and as_float.shape == view.image.shape
    assert torch.allclose(as_float * 255, view.image.float())


def test_cup_full_and_images_4(shared_data: Path) -> None:
    full = load_scene(shared_data / "colmap_cup")
    small = load_scene(shared_data / "colmap_cup", downscale=4)
    assert len(full.train) + len(full.test) == 77 == len(small.train) + len(small.test)
    assert len(full.test) == 10  # ceil(77 / 8)
    reference = pycolmap_cameras(shared_data / "colmap_cup" / "sparse" / "0")
    for big, little in zip(full.train + full.test, small.train + small.test):
        assert big.name == little.name
        assert (big.camera.width, big.camera.height) == (800, 600)
        assert (little.camera.width, little.camera.height) == (200, 150)
        K, w2c, _ = reference[big.name + ".jpg"]
        np.testing.assert_allclose(big.camera.K.numpy(), K, rtol=1e-6)
        scaled = K.copy()
        scaled[:2] /= 4
        np.testing.assert_allclose(little.camera.K.numpy(), scaled, rtol=1e-6)
        assert torch.equal(big.camera.world_to_camera, little.camera.world_to_camera)
    # downscale=4 reads images_4/ as it is (no resizing of images/)
    view = small.train[0]
    expected = np.asarray(Image.open(shared_data / "colmap_cup" / "images_4" / f"{view.name}.jpg").convert("RGB"))
    np.testing.assert_array_equal(view.image.numpy(), expected)
    fractions = np.array([visible_fraction(v, small.points) for v in small.train + small.test])
    assert (fractions >= 0.5).mean() >= 0.9
    assert small.points.shape == (9262, 3)


def test_cup_downscale_without_folder_resizes(shared_data: Path) -> None:
    scene = load_scene(shared_data / "colmap_cup", downscale=2, test_every=0)
    assert len(scene.test) == 0 and len(scene.train) == 77
    view = scene.train[0]
    assert (view.camera.width, view.camera.height) == (400, 300)
    assert tuple(view.image.shape) == (300, 400, 3)
    full = np.asarray(Image.open(shared_data / "colmap_cup" / "images" / f"{view.name}.jpg").convert("RGB"))
    area = full.reshape(300, 2, 400, 2, 3).astype(np.float64).mean(axis=(1, 3))  # 2x2 area average
    assert np.abs(view.image.numpy() - area).max() <= 1.0
    assert view.camera.cx == pytest.approx(200.0) and view.camera.cy == pytest.approx(150.0)


def test_text_model_round_trip(shared_data: Path, tmp_path: Path, bird: Scene) -> None:
    reconstruction = pycolmap.Reconstruction(str(shared_data / "colmap_bird" / "sparse" / "0"))
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    reconstruction.write_text(str(tmp_path / "sparse" / "0"))
    assert not list((tmp_path / "sparse" / "0").glob("*.bin"))
    (tmp_path / "images").symlink_to(shared_data / "colmap_bird" / "images")
    text = load_scene(tmp_path)
    assert [v.name for v in text.train + text.test] == [v.name for v in bird.train + bird.test]
    for a, b in zip(text.train + text.test, bird.train + bird.test):
        torch.testing.assert_close(a.camera.K, b.camera.K, rtol=1e-6, atol=0)
        torch.testing.assert_close(a.camera.world_to_camera, b.camera.world_to_camera, rtol=0, atol=1e-6)
    torch.testing.assert_close(text.points, bird.points)
    torch.testing.assert_close(text.point_colors, bird.point_colors)


def test_pinhole_model(shared_data: Path, tmp_path: Path) -> None:
    """A PINHOLE camera (fx != fy) written by pycolmap in binary is read with its own fx, fy, cx, cy; the model sits
    directly in sparse/ (no 0/), which is also accepted."""
    reconstruction = pycolmap.Reconstruction(str(shared_data / "colmap_bird" / "sparse" / "0"))
    for camera in reconstruction.cameras.values():
        f, cx, cy = camera.params
        camera.model = pycolmap.CameraModelId.PINHOLE
        camera.params = [f, 1.01 * f, cx + 0.25, cy - 0.5]
    (tmp_path / "sparse").mkdir()
    reconstruction.write_binary(str(tmp_path / "sparse"))
    (tmp_path / "images").symlink_to(shared_data / "colmap_bird" / "images")
    scene = load_scene(tmp_path, downscale=2)
    for view in scene.train + scene.test:
        image = reconstruction.find_image_with_name(view.name + ".jpg")
        fx, fy, cx, cy = reconstruction.cameras[image.camera_id].params
        expected = np.array([[fx / 2, 0, cx / 2], [0, fy / 2, cy / 2], [0, 0, 1]])
        np.testing.assert_allclose(view.camera.K.numpy(), expected, rtol=1e-6)
        assert (view.camera.width, view.camera.height) == (272, 480)


def test_a_byte_identical_copy_is_one_view_not_a_test_view_of_a_trained_image(shared_data: Path,
                                                                              tmp_path: Path) -> None:
    """A copy of 1.jpg registered under another name (COLMAP registers both): used once, with a warning naming it, so
    that no test view is a training image (issue 58)."""
    cup = shared_data / "colmap_cup"
    reconstruction = pycolmap.Reconstruction(str(cup / "sparse" / "0"))
    names = sorted(image.name for image in reconstruction.images.values())
    next(image for image in reconstruction.images.values() if image.name == names[-1]).name = "zz_copy.jpg"
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    reconstruction.write_binary(str(tmp_path / "sparse" / "0"))
    (tmp_path / "images_4").mkdir()
    for name in names[:-1]:
        (tmp_path / "images_4" / name).symlink_to(cup / "images_4" / name)
    (tmp_path / "images_4" / "zz_copy.jpg").write_bytes((cup / "images_4" / names[0]).read_bytes())
    with pytest.warns(UserWarning, match="1 image repeats an image listed before") as record:
        scene = load_scene(tmp_path, downscale=4, test_every=2)
    assert "images_4/zz_copy.jpg, a copy of images_4/1.jpg" in str(record[0].message)
    views = scene.train + scene.test
    assert len(views) == 76 and "zz_copy" not in {view.name for view in views}
    trained = {view.image_file.read_bytes() for view in scene.train}
    assert not any(view.image_file.read_bytes() in trained for view in scene.test), "a test view is trained on"
