"""Blender / NeRF loading: the shared lego at 400x400, the bundled demo scene, and instant-ngp style transforms.json."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from mcsplat.data import Scene, load_scene

LEGO = "nerf_synthetic_lego_400/lego"
DEMO = Path(__file__).resolve().parents[2] / "data" / "lego_demo"


def origin_in_view(view) -> bool:
    cam = view.camera
    p = cam.world_to_camera[:3, 3]  # the world origin in camera coordinates
    u, v = (cam.K @ p)[:2] / p[2]
    return bool(p[2] > 0 and 0 <= u < cam.width and 0 <= v < cam.height)


def assert_matches_json(scene: Scene, root: Path) -> None:
    """Poses and focal length follow the json: OpenCV axes = OpenGL axes with y and z flipped."""
    for split, views in (("train", scene.train), ("test", scene.test)):
        meta = json.loads((root / f"transforms_{split}.json").read_text())
        assert len(views) == len(meta["frames"])
        for view, frame in zip(views, meta["frames"]):
            assert view.name == frame["file_path"].removeprefix("./")
            c2w_gl = np.array(frame["transform_matrix"])
            c2w_cv = np.linalg.inv(view.camera.world_to_camera.double().numpy())
            np.testing.assert_allclose(c2w_cv[:3, 0], c2w_gl[:3, 0], atol=1e-5)
            np.testing.assert_allclose(c2w_cv[:3, 1:3], -c2w_gl[:3, 1:3], atol=1e-5)
            np.testing.assert_allclose(c2w_cv[:3, 3], c2w_gl[:3, 3], atol=1e-5)
            focal = 0.5 * view.camera.width / math.tan(0.5 * meta["camera_angle_x"])
            assert view.camera.fx == pytest.approx(focal, rel=1e-6) and view.camera.fy == pytest.approx(focal, rel=1e-6)
            assert view.camera.cx == view.camera.width / 2 and view.camera.cy == view.camera.height / 2


@pytest.fixture(scope="module")
def lego(shared_data: Path) -> Scene:
    return load_scene(shared_data / LEGO)


@pytest.fixture(scope="module")
def demo() -> Scene:
    return load_scene(DEMO)


def test_lego(lego: Scene, shared_data: Path) -> None:
    assert lego.kind == "blender" and lego.points is None and lego.point_colors is None
    assert len(lego.train) == 100 and len(lego.test) == 200  # the dataset's own split, not every 8th
    assert lego.background == (1.0, 1.0, 1.0)
    assert {(v.camera.width, v.camera.height) for v in lego.train + lego.test} == {(400, 400)}
    assert lego.train[0].camera.fx == pytest.approx(555.555, abs=1e-3)
    assert_matches_json(lego, shared_data / LEGO)
    assert all(origin_in_view(v) for v in lego.train + lego.test)
    centres = np.array([np.array(f["transform_matrix"])[:3, 3] for f in
                        json.loads((shared_data / LEGO / "transforms_train.json").read_text())["frames"]])
    assert lego.radius == pytest.approx(1.1 * np.linalg.norm(centres - centres.mean(0), axis=1).max(), rel=1e-5)


def test_lego_alpha_composited_on_background(lego: Scene, shared_data: Path) -> None:
    view = lego.test[0]
    rgba = np.asarray(Image.open(shared_data / LEGO / "test" / "r_0.png")).astype(np.float64)
    expected = rgba[..., :3] * rgba[..., 3:] / 255 + 255 * (1 - rgba[..., 3:] / 255)
    assert np.abs(view.image.numpy() - expected).max() <= 0.5 + 1e-9
    assert (rgba[..., 3] == 0).any() and (view.image.numpy()[rgba[..., 3] == 0] == 255).all()
    black = load_scene(shared_data / LEGO, background="black")
    assert black.background == (0.0, 0.0, 0.0)
    expected = rgba[..., :3] * rgba[..., 3:] / 255
    assert np.abs(black.test[0].image.numpy() - expected).max() <= 0.5 + 1e-9


def test_demo_scene(demo: Scene) -> None:
    assert demo.kind == "blender" and demo.background == (1.0, 1.0, 1.0)
    assert len(demo.train) == 100 and len(demo.test) == 25
    assert [v.name for v in demo.test] == [f"test/r_{i}" for i in range(0, 200, 8)]
    assert {(v.camera.width, v.camera.height) for v in demo.train + demo.test} == {(200, 200)}
    assert_matches_json(demo, DEMO)
    assert all(origin_in_view(v) for v in demo.train + demo.test)
    size = sum(p.stat().st_size for p in DEMO.rglob("*") if p.is_file())
    assert size < 8 * 2**20
    assert (DEMO / "SOURCE.md").is_file()


def test_demo_matches_fresh_downscale_of_lego(demo: Scene, shared_data: Path) -> None:
    """The bundled images equal the shared 400x400 lego loaded at downscale=2 (same poses, K, pixels)."""
    half = load_scene(shared_data / LEGO, downscale=2)
    by_name = {v.name: v for v in half.train + half.test}
    for view in demo.train + demo.test:
        fresh = by_name[view.name]
        assert torch.equal(view.camera.K, fresh.camera.K)
        assert torch.equal(view.camera.world_to_camera, fresh.camera.world_to_camera)
        difference = (view.image.int() - fresh.image.int()).abs()
        assert difference.max() <= 2 and difference.float().mean() < 0.1
    assert half.radius == pytest.approx(demo.radius)


def make_ngp_scene(shared_data: Path, target: Path, frames: int = 12, missing: int = 0) -> dict:
    """An instant-ngp style transforms.json (explicit fl_x/fl_y/cx/cy/w/h, file paths with extension)."""
    lego = shared_data / LEGO
    meta = json.loads((lego / "transforms_train.json").read_text())
    (target / "images").mkdir(parents=True)
    out = {"fl_x": 560.0, "fl_y": 550.0, "cx": 201.5, "cy": 198.25, "w": 400, "h": 400, "frames": []}
    for i, frame in enumerate(meta["frames"][:frames]):
        name = f"images/frame_{i:03d}.png"
        if i >= missing:
            shutil.copyfile(lego / (frame["file_path"].removeprefix("./") + ".png"), target / name)
        out["frames"].append({"file_path": name, "transform_matrix": frame["transform_matrix"]})
    (target / "transforms.json").write_text(json.dumps(out))
    return out


def test_single_transforms_json(shared_data: Path, tmp_path: Path) -> None:
    meta = make_ngp_scene(shared_data, tmp_path)
    scene = load_scene(tmp_path, downscale=2)
    assert scene.kind == "blender" and scene.background == (1.0, 1.0, 1.0)
    assert [v.name for v in scene.test] == ["images/frame_000", "images/frame_008"]  # every 8th
    assert len(scene.train) == 10
    K = scene.train[0].camera.K.double().numpy()
    np.testing.assert_allclose(K, [[280.0, 0, 100.75], [0, 275.0, 99.125], [0, 0, 1]], rtol=1e-6)
    frame = meta["frames"][1]
    c2w_cv = np.linalg.inv(scene.train[0].camera.world_to_camera.double().numpy())
    np.testing.assert_allclose(c2w_cv[:3, 3], np.array(frame["transform_matrix"])[:3, 3], atol=1e-5)


def test_single_transforms_json_skips_missing_images(shared_data: Path, tmp_path: Path) -> None:
    make_ngp_scene(shared_data, tmp_path, frames=10, missing=3)
    with pytest.warns(UserWarning, match="frame_000.png") as record:
        scene = load_scene(tmp_path, test_every=0)
    assert "3 frames" in str(record[0].message)
    assert len(scene.train) == 7 and scene.test == []


def test_camera_angle_x_fallback_and_val_split(shared_data: Path, tmp_path: Path) -> None:
    """transforms_train.json + transforms_val.json (no test file): val is the test split."""
    lego = shared_data / LEGO
    for split, source in (("train", "train"), ("val", "val")):
        meta = json.loads((lego / f"transforms_{source}.json").read_text())
        meta["frames"] = meta["frames"][:3]
        for frame in meta["frames"]:
            relative = frame["file_path"].removeprefix("./") + ".png"
            (tmp_path / relative).parent.mkdir(exist_ok=True)
            shutil.copyfile(lego / relative, tmp_path / relative)
        (tmp_path / f"transforms_{split}.json").write_text(json.dumps(meta))
    scene = load_scene(tmp_path, background=(0.25, 0.5, 0.75))
    assert [v.name for v in scene.test] == ["val/r_0", "val/r_1", "val/r_2"] and len(scene.train) == 3
    assert scene.background == (0.25, 0.5, 0.75)
    assert scene.train[0].camera.fx == pytest.approx(555.555, abs=1e-3)


def test_repeated_frames_are_used_once_and_never_in_both_splits(tmp_path: Path) -> None:
    """30 frames plus 5 repeats (4 of an image path listed before, 1 of a byte-identical copy of an image): 30
    views, with a warning, and none both a training and a test view."""
    from tests.support.helpers import demo_photos_scene

    root, frames = demo_photos_scene(tmp_path / "scene", 30)
    shutil.copyfile(root / "5.png", root / "copy_of_5.png")
    repeats = frames[:4] + [{**frames[5], "file_path": "copy_of_5.png"}]
    meta = json.loads((root / "transforms.json").read_text())
    (root / "transforms.json").write_text(json.dumps({**meta, "frames": frames + repeats}))
    with pytest.warns(UserWarning, match="5 images repeat an image") as record:
        scene = load_scene(root)
    assert "copy_of_5.png" in str(record[0].message)
    assert len(scene.train) + len(scene.test) == 30 and len(scene.test) == 4
    train_files = {view.image_file.read_bytes() for view in scene.train}
    assert not any(view.image_file.read_bytes() in train_files for view in scene.test), "a test view is trained on"


def test_a_test_frame_repeating_a_training_image_is_left_out_of_the_test_split(tmp_path: Path) -> None:
    from tests.support.helpers import demo_photos_scene

    root, frames = demo_photos_scene(tmp_path / "scene", 6)
    meta = json.loads((root / "transforms.json").read_text())
    (root / "transforms.json").unlink()
    (root / "transforms_train.json").write_text(json.dumps({**meta, "frames": frames[:4]}))
    (root / "transforms_test.json").write_text(json.dumps({**meta, "frames": frames[4:] + frames[1:2]}))
    with pytest.warns(UserWarning, match="1 image repeats an image"):
        scene = load_scene(root)
    assert [view.name for view in scene.train] == ["0", "1", "2", "3"]
    assert [view.name for view in scene.test] == ["4", "5"]
