"""Per-view inputs (data/attachments/): found beside the photos after the loader has run, brought through what their
image went through, held by the view. Masks are tested in test_masks.py; here the seam itself and its second kind,
depth maps: NeRF-synthetic's own depth renders decode as their SOURCE.md says and agree between views in space, a
16-bit depth is resized by nearest, a depth follows its image's undistortion, IDR's scale reaches it, and bad depth
files are one line each."""

from __future__ import annotations

import ast
import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from mcsplat.data import load_scene
from mcsplat.data.attachments import KINDS, DepthOptions, MaskOptions, kind_for, resampling
from mcsplat.errors import DataError

SOURCE_ROOT = Path(__file__).resolve().parents[3] / "src" / "mcsplat" / "data"
LEGO_TEST = "nerf_synthetic_lego_400/lego"
LEGO_VIEWS = ("r_0", "r_25", "r_50", "r_100")  # test views around the object: r_0 and r_100 half a turn apart
NERF_SYNTHETIC = DepthOptions(depth_encoding="nerf-synthetic")


# ----------------------------------------------------------------------------------------------------------- seam
def test_loaders_know_nothing_of_attachments():
    """The point of the seam: masks and depth maps reach the views without any loader (or assemble) importing or
    passing them, so that the next kind touches none of them."""
    for name in ("colmap", "blender", "llff", "idr", "assemble"):
        tree = ast.parse((SOURCE_ROOT / f"{name}.py").read_text())
        imported = {node.module or "" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
        imported |= {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
        assert not [module for module in imported if "attachments" in module or module.endswith("masks")], name
        assert "mask_options" not in (SOURCE_ROOT / f"{name}.py").read_text(), name


def test_every_kind_is_registered_under_its_name():
    for name, kind in KINDS.items():
        assert kind.name == name and kind.label
        assert kind.resampling in (resampling.AREA, resampling.NEAREST)
        assert kind_for(kind.options()) is kind
    assert KINDS["mask"].resampling is resampling.AREA and KINDS["depth"].resampling is resampling.NEAREST
    with pytest.raises(TypeError, match="asks for no kind"):
        kind_for(object())


def test_requests_name_each_kind_once(mini_demo):
    """masks= and attachments= are two ways to ask for masks (the scene's masks/ folder unless asked otherwise); a
    request for no kind or two for one is the caller's mistake, said before any file is read, not a DataError."""
    asked_here = load_scene(mini_demo, attachments=[MaskOptions("alpha")]).train[0].mask
    assert asked_here is not None and torch.equal(asked_here, load_scene(mini_demo, masks=MaskOptions("alpha"))
                                                  .train[0].mask)
    with pytest.raises(ValueError, match="one request per kind"):
        load_scene(mini_demo, masks=MaskOptions("alpha"), attachments=[MaskOptions()])
    with pytest.raises(TypeError, match="asks for no kind"):
        load_scene(mini_demo / "nowhere", attachments=["depth"])


def test_a_view_gives_its_attachments_by_kind(mini_demo):
    """At a reduced training resolution a mask is a weight averaged over each pixel's footprint, as the image is."""
    scene = load_scene(mini_demo, masks=MaskOptions("alpha"))
    view = scene.train[0]
    height, width = view.mask.shape
    keep = view.mask.numpy().astype(np.float64) / 255
    blocks = keep.reshape(height // 2, 2, width // 2, 2).mean(axis=(1, 3))
    half = view.attachment("mask", size=(width // 2, height // 2))
    assert half.shape == (height // 2, width // 2, 1)
    np.testing.assert_allclose(half[:, :, 0].numpy(), blocks, atol=1e-6)
    assert 0 < ((blocks > 0) & (blocks < 1)).mean()  # the object's edge: weights between kept and left out
    assert view.attachment("depth") is None  # a registered kind the scene has none of
    with pytest.raises(KeyError, match="no attachment kind 'depths'.*mask, depth"):
        view.attachment("depths")  # a misspelt kind is not "none here"


def test_nearest_resampling_is_one_rule_in_numpy_and_torch():
    values = np.random.default_rng(0).random((37, 53)).astype(np.float32)
    for size in ((53, 37), (26, 18), (17, 12), (80, 50)):
        in_numpy = resampling.NEAREST.resize(values, size)
        in_torch = resampling.NEAREST.resize_tensor(torch.from_numpy(values)[:, :, None], size)[:, :, 0]
        assert np.array_equal(in_numpy, in_torch.numpy()), size
        assert np.isin(in_numpy, values).all()  # nothing mixed


# ---------------------------------------------------------------------------------------------- depth: real files
def _lego_subset(shared_data: Path, root: Path) -> Path:
    """A Blender scene of a few lego test views and their depth renders (links to the shared files, read only)."""
    source = shared_data / LEGO_TEST
    meta = json.loads((source / "transforms_test.json").read_text())
    meta["frames"] = [frame for frame in meta["frames"] if Path(frame["file_path"]).name in LEGO_VIEWS]
    (root / "test").mkdir(parents=True)
    for frame in meta["frames"]:
        name = Path(frame["file_path"]).name
        for file in (f"{name}.png", f"{name}_depth_0001.png"):
            os.symlink(source / "test" / file, root / "test" / file)
    (root / "transforms_train.json").write_text(json.dumps(meta))
    return root


def test_nerf_synthetic_depth_decodes_as_its_source_says(shared_data, tmp_path):
    """Every pixel: 8 (1 - R/255) along the ray (SOURCE.md), over the ray's length through that pixel at the json's
    focal length (worked out here, not by the camera mcsplat made), 0 where R = 0; at half the size and at a
    quarter for training, the value of the pixel under each new centre (nearest), never a mix."""
    root = _lego_subset(shared_data, tmp_path / "lego")
    scene = load_scene(root, test_every=0, attachments=[NERF_SYNTHETIC])
    assert any(note.startswith(f"depth maps for {len(LEGO_VIEWS)} of {len(LEGO_VIEWS)} images from beside the "
                               "photos") for note in scene.notes), scene.notes
    focal = 0.5 * 400 / math.tan(0.5 * json.loads((root / "transforms_train.json").read_text())["camera_angle_x"])
    offsets = (np.arange(400) + 0.5 - 200) / focal
    ray_length = np.sqrt(1 + offsets[None, :] ** 2 + offsets[:, None] ** 2)
    half = load_scene(root, downscale=2, test_every=0, attachments=[NERF_SYNTHETIC])
    for view, small in zip(scene.train, half.train):
        red = np.asarray(Image.open(root / f"{view.name}_depth_0001.png"))[:, :, 0].astype(np.float64)
        expected = np.where(red > 0, 8 * (1 - red / 255) / ray_length, 0)
        depth = view.attachment("depth")[:, :, 0].numpy()
        assert depth.shape == (400, 400) and view.attachment("depth").dtype == torch.float32
        np.testing.assert_allclose(depth, expected, rtol=1e-6, atol=1e-6)
        assert 0.1 < (depth > 0).mean() < 0.6  # the object, not the background
        assert np.array_equal(small.attachment("depth")[:, :, 0].numpy(), depth[1::2, 1::2])
        assert np.array_equal(view.attachment("depth", size=(100, 100))[:, :, 0].numpy(), depth[2::4, 2::4])


def _back_projected(view) -> torch.Tensor:
    """[P, 3] world points of the view's depth (pixels with one)."""
    depth = view.attachment("depth")[:, :, 0].double()
    K, w2c = view.camera.K.double(), view.camera.world_to_camera.double()
    v, u = torch.meshgrid(torch.arange(depth.shape[0]) + 0.5, torch.arange(depth.shape[1]) + 0.5, indexing="ij")
    known = depth > 0
    z = depth[known]
    camera = torch.stack([(u[known] - K[0, 2]) / K[0, 0] * z, (v[known] - K[1, 2]) / K[1, 1] * z, z], dim=1)
    return (camera - w2c[:3, 3]) @ w2c[:3, :3]


def _agreement(source, target) -> tuple[float, float]:
    """Of `source`'s depth points that `target` sees in its frame: the share on `target`'s object (its depth > 0),
    and the median |z - target's depth| where target sees the same surface (within 0.1 units)."""
    w2c, K = target.camera.world_to_camera.double(), target.camera.K.double()
    camera = _back_projected(source) @ w2c[:3, :3].T + w2c[:3, 3]
    u = K[0, 0] * camera[:, 0] / camera[:, 2] + K[0, 2]
    v = K[1, 1] * camera[:, 1] / camera[:, 2] + K[1, 2]
    inside = (u >= 0) & (u < target.camera.width) & (v >= 0) & (v < target.camera.height)
    there = target.attachment("depth")[:, :, 0].double()[v[inside].long(), u[inside].long()]
    on_object = there > 0
    gap = (camera[inside, 2] - there)[on_object].abs()
    return float(on_object.double().mean()), float(gap[gap < 0.1].median())


@pytest.mark.parametrize("downscale", [1, 2])
def test_nerf_synthetic_depths_of_different_views_agree_in_space(shared_data, tmp_path, downscale):
    """Each view's depth, lifted into the world with its camera and looked at from another test view, lands on that
    view's object and on its depth: 98.5-99.2% on it and a median gap of 0.017-0.020 units here (SOURCE.md found
    0.013 over more views; one 8-bit step is 0.031). Decoding along the axis instead of the ray puts 4-13% off the
    object and doubles the gap; depths 3% too long give a gap of 0.052 and up: the bounds below tell them apart."""
    root = _lego_subset(shared_data, tmp_path / "lego")
    views = load_scene(root, downscale=downscale, test_every=0, attachments=[NERF_SYNTHETIC]).train
    for a, b in ((0, 1), (1, 2), (0, 3)):
        on_object, median_gap = _agreement(views[a], views[b])
        assert on_object > 0.975 and median_gap < 0.025, (views[a].name, views[b].name, on_object, median_gap)


# ------------------------------------------------------------------------------------------ depth: how it follows
def test_a_16_bit_depth_is_resized_by_nearest_and_scaled_to_units(shared_data, tmp_path):
    """The cup's 800x600 photos loaded from images_4/ at 200x150: a 16-bit depth at 800x600 gives each pixel the
    value of the full-size pixel under its centre (4j + 2, 4i + 2), in png_step units; views without one have
    none (depth is often measured for some views only)."""
    folder = tmp_path / "depth-of-the-cup"  # beside, not inside, the shared scene: nothing is written into it
    folder.mkdir()
    y, x = np.mgrid[0:600, 0:800]
    steps = (1000 + 50 * x + y % 50).astype(np.uint16)  # the column and the row (mod 50) can be read back
    names = ["12", "30", "41"]
    for name in names:
        Image.fromarray(steps).save(folder / f"{name}.png")
    scene = load_scene(shared_data / "colmap_cup", downscale=4,
                       attachments=[DepthOptions(str(folder), depth_png_step=0.002)])
    views = {view.name: view for view in scene.train + scene.test}
    assert {name for name, view in views.items() if view.attachment("depth") is not None} == set(names)
    assert any(note.startswith(f"depth maps for 3 of {len(views)} images from {folder}") for note in scene.notes)
    depth = views["12"].attachment("depth")[:, :, 0].numpy()
    assert depth.shape == (150, 200)
    read_back = np.rint(depth / 0.002).astype(np.int64) - 1000
    rows, columns = np.mgrid[0:150, 0:200]
    assert np.array_equal(read_back // 50, 4 * columns + 2) and np.array_equal(read_back % 50, (4 * rows + 2) % 50)


def test_a_depth_is_undistorted_with_its_image(shared_data, tmp_path, monkeypatch):
    """ngp_fruit's OPENCV camera: a depth made from the photo's bright pixels (2 where bright, 1 elsewhere) lies
    where the same pixels as a mask lie once pycolmap has undistorted that mask with the photo: 98.5-99.4% of
    pixels agree, and a depth one pixel off agrees on 91.7-96.4% only. It stays two values (nearest, never mixed)."""
    monkeypatch.setenv("MCSPLAT_CACHE", str(tmp_path / "cache"))
    source = shared_data / "ngp_fruit"
    root = tmp_path / "fruit"
    meta = json.loads((source / "transforms.json").read_text())
    meta["frames"] = meta["frames"][:3]
    for folder in ("masks", "depths", "newfruit_small"):
        (root / folder).mkdir(parents=True)
    for frame in meta["frames"]:
        photo = source / frame["file_path"]
        shutil.copyfile(photo, root / "newfruit_small" / photo.name)
        grey = np.asarray(Image.open(photo).convert("L"))
        bright = grey > np.median(grey)
        Image.fromarray(np.where(bright, 255, 0).astype(np.uint8)).save(root / "masks" / f"{photo.stem}.png")
        np.save(root / "depths" / f"{photo.stem}.npy", np.where(bright, 2.0, 1.0))
    (root / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(root, test_every=0, attachments=[DepthOptions()])
    assert any("undistorted" in note for note in scene.notes)
    for view in scene.train:
        depth = view.attachment("depth")[:, :, 0].numpy()
        assert depth.shape == view.image.shape[:2] and set(np.unique(depth)) <= {1.0, 2.0}
        agree = ((depth > 1.5) == (view.mask.numpy() > 127)).mean()
        assert agree > 0.98, f"{view.name}: the depth agrees with the undistorted mask on {agree:.1%} of pixels"


def test_a_depth_is_in_the_scene_units_of_idr_scale_mat(shared_data, tmp_path):
    """IDR's cameras live in the unit sphere that scale_mat maps onto the object (223 mm across for DTU scan24):
    a depth in the capture's units (that of the sphere's centre, worked out from world_mat and scale_mat here)
    reads, once loaded, as that centre's depth in the scene's cameras."""
    root = shared_data / "dtu_scan24_monosdf" / "scan24"
    cameras = np.load(root / "cameras.npz")
    folder = tmp_path / "depths"
    folder.mkdir()
    for index in (0, 7):
        projection, centre = cameras[f"world_mat_{index}"][:3], cameras[f"scale_mat_{index}"][:3, 3]
        capture_depth = abs(projection[2] @ np.append(centre, 1.0)) / np.linalg.norm(projection[2, :3])
        np.save(folder / f"{index:06d}_rgb.npy", np.full((384, 384), capture_depth))
    scene = load_scene(root, test_every=0, attachments=[DepthOptions(str(folder))])
    for index in (0, 7):
        view = scene.train[index]
        depth = view.attachment("depth")
        scene_depth = float(view.camera.world_to_camera[2, 3])  # the sphere's centre is the scene's origin
        assert 1.5 < scene_depth < 10  # the unit sphere, not millimetres
        assert torch.allclose(depth, torch.full_like(depth, scene_depth), rtol=1e-5), (index, depth[0, 0, 0])


# ------------------------------------------------------------------------------------------------- depth: refusals
def test_bad_depth_files_are_one_line_errors(shared_data, tmp_path):
    cup = shared_data / "colmap_cup"
    folder = tmp_path / "depths"
    folder.mkdir()

    def error(options: DepthOptions) -> str:
        with pytest.raises(DataError) as info:
            load_scene(cup, downscale=4, attachments=[options])
        assert "\n" not in str(info.value)
        return str(info.value)

    assert "no such folder" in error(DepthOptions(str(tmp_path / "nowhere")))
    assert "holds no depth map for any of the 77 images" in error(DepthOptions(str(folder)))
    Image.new("L", (800, 600), 9).save(folder / "12.png")
    assert "8-bit L PNG, whose 256 steps cannot hold a depth" in error(DepthOptions(str(folder)))
    (folder / "12.png").unlink()
    Image.fromarray(np.full((100, 100), 500, dtype=np.uint16)).save(folder / "12.png")
    assert "12.png is 100x100 but its image is 200x150; a depth map must have its image's shape" in \
        error(DepthOptions(str(folder)))
    (folder / "12.png").unlink()
    np.save(folder / "12.npy", -np.ones((600, 800)))
    assert "holds negative depths" in error(DepthOptions(str(folder)))
    np.save(folder / "12.npy", np.ones((600, 800, 3)))
    assert "shape [600, 800, 3]" in error(DepthOptions(str(folder)))
    (folder / "12.npy").write_bytes(b"not numpy")
    assert "cannot read depth map" in error(DepthOptions(str(folder)))
    for bad in (dict(depth_encoding="kinect"), dict(depth_measure="planar"), dict(depth_png_step=0), dict(depths=" ")):
        with pytest.raises(DataError, match="depth"):
            DepthOptions(**bad)


def test_missing_or_empty_depth_is_no_depth(tmp_path, shared_data):
    """0, NaN and inf read as no depth at that pixel; a scene without depth files has no depth (auto)."""
    folder = tmp_path / "depths"
    folder.mkdir()
    depth = np.full((600, 800), 2.5)
    depth[:300] = np.nan
    depth[300:, :400] = np.inf
    depth[300:, 400:600] = 0
    np.save(folder / "12.npy", depth)
    scene = load_scene(shared_data / "colmap_cup", downscale=4, attachments=[DepthOptions(str(folder))])
    loaded = next(view for view in scene.train + scene.test if view.name == "12").attachment("depth")[:, :, 0]
    assert set(torch.unique(loaded).tolist()) == {0.0, 2.5}
    assert float((loaded == 2.5).float().mean()) == pytest.approx(0.125)  # the lower right quarter of the half
    bare = load_scene(shared_data / "colmap_cup", downscale=4, attachments=[DepthOptions()])
    assert all(view.attachment("depth") is None for view in bare.train)
    assert not any(note.startswith("depth maps") for note in bare.notes)


def test_depths_float32_cannot_hold_and_non_real_arrays_are_refused(shared_data, tmp_path):
    """A .npy of depths beyond float32's range would load as inf (read as "no depth" nowhere, a training target of
    inf); a complex array would lose its imaginary part with only numpy's ComplexWarning; object and string arrays
    are no depths either: each is one line naming the file (issue 58)."""
    import warnings

    folder = tmp_path / "depths"
    folder.mkdir()

    def error(array: np.ndarray, **save) -> str:
        np.save(folder / "12.npy", array, **save)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # numpy's ComplexWarning is no answer
            with pytest.raises(DataError) as info:
                load_scene(shared_data / "colmap_cup", downscale=4, attachments=[DepthOptions(str(folder))])
        assert "\n" not in str(info.value) and "12.npy" in str(info.value)
        return str(info.value)

    huge = np.full((600, 800), 2.5)
    huge[0, 0] = 1e300
    assert "float32" in error(huge) and "1e+300" in error(huge)
    assert "complex128" in error(np.full((600, 800), 2.5 + 1j))
    assert "<U3" in error(np.full((600, 800), "2.5"))
    assert "object" in error(np.full((600, 800), 2.5, dtype=object), allow_pickle=True).lower()
    assert "timedelta64" in error(np.full((600, 800), 3, dtype="timedelta64[s]"))


# ------------------------------------------------------------------------------------------ depth: mcsplat train
def _train_config(argv: list[str]):
    """The configuration `mcsplat train ARGV` runs with (parsed as cli.main parses it, without training)."""
    import tyro

    from mcsplat import cli

    return tyro.extras.subcommand_cli_from_dict(cli.COMMANDS, prog="mcsplat", args=["train", *argv])


def test_train_loads_the_depth_maps_its_options_name(mini_demo, tmp_path):
    """--depths FOLDER (with --depth-encoding, --depth-measure, --depth-png-step) puts the depth maps on the views of
    the run's scene, also when the run is read back from config.json (eval, resume); without it a run loads none."""
    from mcsplat.config import from_jsonable, to_jsonable
    from mcsplat.run.scene import scene_of

    folder = tmp_path / "depths"
    (folder / "train").mkdir(parents=True)
    Image.fromarray(np.full((200, 200), 1500, dtype=np.uint16)).save(folder / "train" / "r_1.png")
    np.save(folder / "train" / "r_2.npy", np.full((200, 200), 2.0))
    config = _train_config([str(mini_demo), "--depths", str(folder), "--depth-png-step", "0.002"])
    for loaded in (config, from_jsonable(to_jsonable(config))):
        scene = scene_of(loaded)
        depths = {view.name: view.attachment("depth") for view in scene.train + scene.test}
        assert float(depths["train/r_1"].max()) == pytest.approx(3.0) and float(depths["train/r_2"].min()) == 2.0
        assert sum(depth is not None for depth in depths.values()) == 2
        assert any(note.startswith("depth maps for 2 of 15 images") for note in scene.notes), scene.notes
    assert all(view.attachment("depth") is None for view in scene_of(_train_config([str(mini_demo)])).train)


def test_train_with_a_missing_depth_folder_is_one_line(mini_demo, tmp_path, capsys):
    from mcsplat.cli import main

    missing = tmp_path / "no_depths"
    status = main(["train", str(mini_demo), "--out", str(tmp_path / "run"), "--steps", "1", "--depths", str(missing)])
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert status == 2 and error.startswith(f"mcsplat: error: --depths {missing}: no such folder"), error
    assert "'auto'" in error and "'none'" in error and not (tmp_path / "run").exists()
