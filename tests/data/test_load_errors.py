"""Bad input: every problem is a one-line DataError that names the offending file (tmp copies of the real data)."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import struct
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

from mcsplat.data import load_scene
from mcsplat.errors import DataError, MCSplatError

DEMO = Path(__file__).resolve().parents[2] / "data" / "lego_demo"


def load_error(path: Path, **options) -> str:
    """Load, expect a DataError, check it is one line, return its message."""
    with pytest.raises(DataError) as info:
        load_scene(path, **options)
    message = str(info.value)
    assert "\n" not in message and message.strip() == message and len(message) < 600
    return message


def resized_image_error(root: Path, image: str, size: tuple[int, int], **options) -> tuple[Path, str]:
    """Resize one image in place so it disagrees with the rest, load, return its path and the error message."""
    path = root / image
    Image.open(path).resize(size).save(path)
    return path, load_error(root, **options)


@pytest.fixture
def bird(copy_shared) -> Path:
    return copy_shared("colmap_bird")


@pytest.fixture
def fern(copy_shared) -> Path:
    return copy_shared("llff_fern/fern")


@pytest.fixture
def mini_lego(tmp_path: Path) -> Path:
    """A 3 train + 2 test view copy of the bundled demo scene (test views r_0 and r_8)."""
    root = tmp_path / "lego"
    for split, count in (("train", 3), ("test", 2)):
        meta = json.loads((DEMO / f"transforms_{split}.json").read_text())
        meta["frames"] = meta["frames"][:count]
        (root / split).mkdir(parents=True)
        for frame in meta["frames"]:
            relative = frame["file_path"].removeprefix("./") + ".png"
            shutil.copyfile(DEMO / relative, root / relative)
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root


# --- folders ---------------------------------------------------------------------------------------------------

def test_missing_folder(tmp_path: Path) -> None:
    message = load_error(tmp_path / "nowhere")
    assert str(tmp_path / "nowhere") in message and "does not exist" in message


def test_file_instead_of_folder(tmp_path: Path) -> None:
    (tmp_path / "scene.txt").write_text("hello")
    assert str(tmp_path / "scene.txt") in load_error(tmp_path / "scene.txt")


def test_no_recognised_format(tmp_path: Path) -> None:
    (tmp_path / "images").mkdir()
    (tmp_path / "notes.txt").write_text("not a scene")
    message = load_error(tmp_path)
    assert str(tmp_path) in message
    for looked_for in ("sparse/0", "cameras", "transforms_train.json", "transforms.json", "poses_bounds.npy"):
        assert looked_for in message


def test_incomplete_colmap_model_is_named(tmp_path: Path, shared_data: Path) -> None:
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    shutil.copyfile(shared_data / "colmap_bird" / "sparse" / "0" / "cameras.bin",
                    tmp_path / "sparse" / "0" / "cameras.bin")
    message = load_error(tmp_path)
    assert "images.bin" in message and "points3D.bin" in message and "incomplete" in message


# --- COLMAP files -----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
@pytest.mark.parametrize("keep", [0.0, 0.5, 0.999])
def test_truncated_colmap_bin(bird: Path, name: str, keep: float) -> None:
    path = bird / "sparse" / "0" / name
    with open(path, "r+b") as f:
        f.truncate(int(path.stat().st_size * keep))
    assert str(path) in load_error(bird)


def test_truncated_colmap_bin_at_many_offsets(bird: Path) -> None:
    """pycolmap can hang or eat all memory on a cut .bin file: no cut may reach it."""
    model = bird / "sparse" / "0"
    originals = {name: (model / name).read_bytes() for name in ("cameras.bin", "images.bin", "points3D.bin")}
    rng = np.random.default_rng(0)
    for name, data in originals.items():
        for cut in sorted({1, 7, 8, 9, 20, len(data) - 1, *rng.integers(0, len(data), 12).tolist()}):
            (model / name).write_bytes(data[:cut])
            assert str(model / name) in load_error(bird)
        (model / name).write_bytes(data)


def test_corrupt_count_in_images_bin(bird: Path) -> None:
    path = bird / "sparse" / "0" / "images.bin"
    data = bytearray(path.read_bytes())
    name_end = data.index(b"\0", 8 + 64)
    data[name_end + 1:name_end + 9] = struct.pack("<Q", 2**40)  # number of 2D points of the first image
    path.write_bytes(bytes(data))
    assert str(path) in load_error(bird)


def model_as_text(scene: Path) -> Path:
    """Rewrite the scene's COLMAP model as .txt files and drop the .bin ones, so the text reader is the one used."""
    model = scene / "sparse" / "0"
    pycolmap.Reconstruction(str(model)).write_text(str(model))
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        (model / name).unlink()
    return model


def test_garbled_text_model(bird: Path) -> None:
    model = model_as_text(bird)
    lines = (model / "cameras.txt").read_text().splitlines()
    lines[5] = lines[5].replace("SIMPLE_PINHOLE 544 960", "SIMPLE_PINHOLE 544 nine-sixty")
    (model / "cameras.txt").write_text("\n".join(lines) + "\n")
    message = load_error(bird)
    assert str(model / "cameras.txt") in message and "line 6" in message


def test_truncated_text_images(bird: Path) -> None:
    model = model_as_text(bird)
    text = (model / "images.txt").read_text()
    (model / "images.txt").write_text(text[: len(text) // 3])
    assert str(model / "images.txt") in load_error(bird)


def test_camera_model_that_cannot_be_undistorted_text(bird: Path) -> None:
    model = model_as_text(bird)
    lines = (model / "cameras.txt").read_text().splitlines()
    index = next(i for i, line in enumerate(lines) if line.startswith("7 "))
    lines[index] = lines[index].replace("SIMPLE_PINHOLE", "SIMPLE_DIVISION") + " 0.01"
    (model / "cameras.txt").write_text("\n".join(lines) + "\n")
    message = load_error(bird)
    assert str(model / "cameras.txt") in message
    assert "SIMPLE_DIVISION" in message and "camera 7" in message and "cannot undistort" in message


def test_fisheye_wider_than_180_degrees_binary(bird: Path) -> None:
    """An OPENCV_FISHEYE camera whose image edge is 1.6 rad (92 degrees) off its axis: no pinhole image holds it."""
    model = bird / "sparse" / "0"
    reconstruction = pycolmap.Reconstruction(str(model))
    camera = reconstruction.cameras[3]
    f, cx, cy = camera.params
    camera.model = pycolmap.CameraModelId.OPENCV_FISHEYE
    camera.params = [cy / 1.6, cy / 1.6, cx, cy, 0.0, 0.0, 0.0, 0.0]
    reconstruction.write_binary(str(model))
    message = load_error(bird)
    assert str(model / "cameras.bin") in message and "OPENCV_FISHEYE" in message and "180 degrees" in message


@pytest.mark.parametrize("value, offset", [(math.nan, 12), (math.inf, 8 + 4 + 32 + 8)])
def test_non_finite_colmap_pose(bird: Path, value: float, offset: int) -> None:
    """A NaN in the quaternion (qw) or an inf in the translation (ty) of the first image, 001.jpg."""
    path = bird / "sparse" / "0" / "images.bin"
    data = bytearray(path.read_bytes())
    data[offset:offset + 8] = struct.pack("<d", value)
    path.write_bytes(bytes(data))
    message = load_error(bird)
    assert str(path) in message and "001.jpg" in message and "NaN or infinite" in message


# --- images -----------------------------------------------------------------------------------------------------

def test_colmap_image_missing(bird: Path) -> None:
    (bird / "images" / "017.jpg").unlink()
    message = load_error(bird)
    assert str(bird / "images" / "017.jpg") in message and "images.bin" in message


@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_colmap_unreadable_image(bird: Path, damage: str) -> None:
    path = bird / "images" / "042.jpg"
    if damage == "garbage":
        path.write_bytes(np.random.default_rng(1).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    else:
        path.write_bytes(path.read_bytes()[:2000])  # valid header, data cut short
    assert str(path) in load_error(bird)


def test_colmap_image_of_other_size(bird: Path) -> None:
    path, message = resized_image_error(bird, "images/100.jpg", (272, 480))
    assert str(path) in message and "272x480" in message and "544x960" in message


def test_colmap_images_n_of_wrong_size(copy_shared) -> None:
    cup = copy_shared("colmap_cup")
    path, message = resized_image_error(cup, "images_4/5.jpg", (100, 75), downscale=4)
    assert str(path) in message and "100x75" in message


def test_blender_image_missing(mini_lego: Path) -> None:
    (mini_lego / "train" / "r_1.png").unlink()
    message = load_error(mini_lego)
    assert str(mini_lego / "transforms_train.json") in message and "train/r_1" in message


def test_blender_unreadable_png(mini_lego: Path) -> None:
    path = mini_lego / "test" / "r_8.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 100)
    assert str(path) in load_error(mini_lego)


def test_blender_image_of_other_size(mini_lego: Path) -> None:
    path, message = resized_image_error(mini_lego, "test/r_8.png", (150, 150))
    assert str(path) in message and "150x150" in message and "200x200" in message


def test_blender_size_disagrees_with_w_h(mini_lego: Path) -> None:
    meta = json.loads((mini_lego / "transforms_train.json").read_text())
    meta["w"], meta["h"] = 800, 800
    (mini_lego / "transforms_train.json").write_text(json.dumps(meta))
    message = load_error(mini_lego)
    assert "transforms_train.json" in message and "r_0.png" in message and "w=800" in message and "200x200" in message


@pytest.mark.parametrize("bad", [math.nan, math.inf, None])
def test_blender_bad_transform_matrix(mini_lego: Path, bad) -> None:
    path = mini_lego / "transforms_test.json"
    meta = json.loads(path.read_text())
    meta["frames"][1]["transform_matrix"][0][3] = bad
    path.write_text(json.dumps(meta))  # json writes NaN / Infinity, which Python's json reads back
    message = load_error(mini_lego)
    assert str(path) in message and "frame 1" in message and "./test/r_8" in message


def test_blender_malformed_json(mini_lego: Path) -> None:
    path = mini_lego / "transforms_train.json"
    path.write_text(path.read_text()[:500])
    message = load_error(mini_lego)
    assert str(path) in message and "not valid JSON" in message and "line 1" in message


def test_blender_json_without_frames(mini_lego: Path) -> None:
    path = mini_lego / "transforms_test.json"
    path.write_text(json.dumps({"camera_angle_x": 0.69}))
    assert str(path) in load_error(mini_lego)


@pytest.mark.parametrize("change, expected", [
    ({"camera_model": "EQUIRECTANGULAR"}, "camera_model 'EQUIRECTANGULAR' is not supported"),
    ({"k1": 0.05, "camera_model": "PINHOLE"}, "k1=0.05"),
    ({"k4": 0.01}, "OPENCV_FISHEYE"),
    ({"camera_model": "OPENCV_FISHEYE", "p1": 0.001}, "no tangential terms"),
])
def test_blender_distortion_that_cannot_be_undistorted(mini_lego: Path, change: dict, expected: str) -> None:
    path = mini_lego / "transforms_train.json"
    meta = json.loads(path.read_text())
    meta.update(change)
    path.write_text(json.dumps(meta))
    message = load_error(mini_lego)
    assert str(path) in message and expected in message


def test_transforms_json_all_images_missing(tmp_path: Path) -> None:
    meta = json.loads((DEMO / "transforms_train.json").read_text())
    meta["frames"] = [{"file_path": f"images/{i}.png", "transform_matrix": f["transform_matrix"]}
                      for i, f in enumerate(meta["frames"][:4])]
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    message = load_error(tmp_path)
    assert str(tmp_path / "transforms.json") in message and "none of the 4 images" in message


# --- LLFF --------------------------------------------------------------------------------------------------------

def test_llff_image_count_mismatch(fern: Path) -> None:
    (fern / "images_8" / "image007.png").unlink()
    message = load_error(fern)
    assert str(fern / "images_8") in message and str(fern / "poses_bounds.npy") in message
    assert "19 images" in message and "20 poses" in message


def test_llff_unreadable_image(fern: Path) -> None:
    path = fern / "images_8" / "image003.png"
    path.write_bytes(b"not a png at all")
    assert str(path) in load_error(fern)


def test_llff_image_of_other_size(fern: Path) -> None:
    path, message = resized_image_error(fern, "images_8/image011.png", (500, 378))
    assert str(path) in message and "500x378" in message


@pytest.mark.parametrize("column", [0, 3, 14])  # a rotation entry, the x position, the focal length
def test_llff_non_finite_poses(fern: Path, column: int) -> None:
    path = fern / "poses_bounds.npy"
    array = np.load(path)
    array[4, column] = math.nan
    np.save(path, array)
    message = load_error(fern)
    assert str(path) in message and "row 4" in message


def test_llff_poses_bounds_wrong_shape_and_garbage(fern: Path) -> None:
    path = fern / "poses_bounds.npy"
    np.save(path, np.zeros((20, 15)))
    assert str(path) in load_error(fern) and "(N, 17)" in load_error(fern)
    path.write_bytes(b"\x93NUMPY garbage")
    assert str(path) in load_error(fern)


def test_llff_corrupt_points3d(fern: Path) -> None:
    path = fern / "sparse" / "0" / "points3D.bin"
    with open(path, "r+b") as f:
        f.truncate(1000)
    assert str(path) in load_error(fern)


# --- options -----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("options", [{"downscale": 0}, {"downscale": 1.5}, {"downscale": "2"}, {"test_every": -1},
                                     {"background": "purple"}, {"background": (1.0, 2.0, 0.0)},
                                     {"background": (1.0, 0.0)}])
def test_bad_options(options: dict) -> None:
    with pytest.raises(MCSplatError) as info:
        load_scene(DEMO, **options)
    assert list(options)[0] in str(info.value)


# --- too few frames ------------------------------------------------------------------------------------------------

def test_a_scene_of_one_frame_says_how_many_frames_are_needed(tmp_path: Path, capsys) -> None:
    from tests.support.helpers import demo_photos_scene
    from mcsplat.cli import main

    root, _ = demo_photos_scene(tmp_path / "one", 1)
    message = load_error(root)
    assert "1 view" in message and "at least 2" in message and "--test-every 0" in message
    for init in ("auto", "random"):
        capsys.readouterr()
        assert main(["train", str(root), "--out", str(tmp_path / f"run_{init}"), "--model.init", init,
                     "--steps", "5", "--quiet"]) == 2
        error = capsys.readouterr().err
        assert error.startswith("mcsplat: error:") and "at least 2" in error and error.count("\n") == 1, error


def test_points_from_the_poses_of_one_training_view_say_two_are_needed(tmp_path: Path, monkeypatch) -> None:
    """One frame with --test-every 0: one training view, from which nothing can be triangulated; `--model.init
    triangulate` says so in one line, and the automatic choice fills the camera's frustum instead."""
    import torch

    from tests.support.helpers import demo_photos_scene
    from mcsplat.config import TrainConfig
    from mcsplat.initialization import initial_model

    monkeypatch.setenv("MCSPLAT_CACHE", str(tmp_path / "cache"))
    root, _ = demo_photos_scene(tmp_path / "one", 1)
    scene = load_scene(root, test_every=0)
    assert len(scene.train) == 1 and scene.points is None and not scene.alpha
    config = TrainConfig(data=root, out=tmp_path / "run", quiet=True)
    config = dataclasses.replace(config, model=dataclasses.replace(config.model, init="triangulate"))
    with pytest.raises(MCSplatError, match="at least 2 training views"):
        initial_model(config, scene, torch.device("cpu"), torch.Generator().manual_seed(0))
    config = dataclasses.replace(config, model=dataclasses.replace(config.model, init="auto"))
    model, note = initial_model(config, scene, torch.device("cpu"), torch.Generator().manual_seed(0))
    assert model.num_gaussians > 0 and "frustum" in note and "at least 2 training views" in note
