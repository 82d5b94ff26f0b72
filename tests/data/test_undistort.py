"""Distorted cameras load directly: undistorted once to PINHOLE, consistent with the SfM points, cached outside.

No shared dataset has distorted cameras (bird and cup are SIMPLE_PINHOLE, DTU and fern have no distortion terms), so
the tests make distorted captures from the real cup: its photos are warped through a lens model (each distorted
pixel samples the original photo along its ray) and its COLMAP model is rewritten with that camera, keypoints
included. Undistorting must then give back the original photo, up to resampling, and the stored keypoints.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from mcsplat.data import load_scene
from mcsplat.data.undistort import CACHE_ENV
from mcsplat.metrics import psnr

pytestmark = pytest.mark.filterwarnings("ignore:.*images without a pose")

STEPS = 250
CUP_IMAGES = ["1.jpg", "10.jpg", "22.jpg", "35.jpg", "47.jpg", "60.jpg"]
LENSES = {  # model -> distortion parameters after the focal length(s) and principal point
    "SIMPLE_PINHOLE": [],  # the original camera, for comparison
    "SIMPLE_RADIAL": [-0.12],
    "RADIAL": [-0.12, 0.03],
    "OPENCV": [-0.12, 0.03, 0.002, -0.001],
    "FULL_OPENCV": [-0.12, 0.03, 0.002, -0.001, 0.01, 0.0, 0.0, 0.0],
    "OPENCV_FISHEYE": [0.05, -0.02, 0.0, 0.0],
}


@pytest.fixture(autouse=True)
def private_cache(tmp_path_factory, monkeypatch) -> Path:
    cache = tmp_path_factory.mktemp("cache")
    monkeypatch.setenv(CACHE_ENV, str(cache))
    return cache


def lens_camera(model: str, pinhole: pycolmap.Camera) -> pycolmap.Camera:
    f, cx, cy = pinhole.params
    head = [f, cx, cy] if model.startswith("SIMPLE") or model == "RADIAL" else [f, f, cx, cy]
    return pycolmap.Camera(model=model, width=pinhole.width, height=pinhole.height, params=head + LENSES[model])


def distort_photo(photo: np.ndarray, pinhole: pycolmap.Camera, lens: pycolmap.Camera) -> np.ndarray:
    """The photo `pinhole` took, as `lens` would have taken it: bilinear samples along each of lens's pixel rays."""
    height, width = lens.height, lens.width
    v, u = np.mgrid[0:height, 0:width].astype(np.float64) + 0.5  # COLMAP: pixel centres at +0.5
    rays = lens.cam_from_img(np.stack([u.ravel(), v.ravel()], axis=1))
    source = pinhole.img_from_cam(np.concatenate([rays, np.ones((len(rays), 1))], axis=1))
    grid = torch.from_numpy(np.stack([source[:, 0] / pinhole.width * 2 - 1, source[:, 1] / pinhole.height * 2 - 1],
                                     axis=1))
    image = torch.from_numpy(np.array(photo)).permute(2, 0, 1)[None].double()
    out = torch.nn.functional.grid_sample(image, grid.view(1, height, width, 2), mode="bilinear",
                                          padding_mode="border", align_corners=False)
    return out[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()


def make_distorted_cup(shared_data: Path, target: Path, model: str, names: list[str]) -> Path:
    """A COLMAP scene of the cup photos `names` taken through `model`'s lens, keypoints moved with the pixels."""
    source = shared_data / "colmap_cup"
    reconstruction = pycolmap.Reconstruction(str(source / "sparse" / "0"))
    keep = {image_id for image_id, image in reconstruction.images.items() if image.name in names}
    for image_id in list(reconstruction.images):
        if image_id not in keep:  # the others stay in the model without a pose: the loader skips them
            reconstruction.deregister_frame(reconstruction.images[image_id].frame_id)
    (target / "images").mkdir(parents=True)
    for image_id in keep:
        image = reconstruction.images[image_id]
        pinhole = reconstruction.cameras[image.camera_id]
        lens = lens_camera(model, pinhole)
        photo = np.asarray(Image.open(source / "images" / image.name).convert("RGB"))
        Image.fromarray(distort_photo(photo, pinhole, lens)).save(target / "images" / image.name, quality=95)
        for point in image.points2D:  # the keypoints, where the distorted photo shows them
            point.xy = lens.img_from_cam(np.append(pinhole.cam_from_img(point.xy[None]), [[1.0]], axis=1))[0]
        pinhole.model, pinhole.params = lens.model, lens.params
    (target / "sparse" / "0").mkdir(parents=True)
    reconstruction.write_binary(str(target / "sparse" / "0"))
    return target


def folder_state(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")}


@pytest.mark.parametrize("model", [m for m in LENSES if m != "SIMPLE_PINHOLE"])
def test_distorted_colmap_scene_gives_back_the_original_photos(shared_data, tmp_path, model):
    """Each model: the loaded PINHOLE image is the original photo (same focal, shifted principal point), and the
    scene folder is left exactly as it was."""
    scene_dir = make_distorted_cup(shared_data, tmp_path / model, model, CUP_IMAGES[:3])
    before = folder_state(scene_dir)
    scene = load_scene(scene_dir, test_every=0)
    assert folder_state(scene_dir) == before
    assert any("undistorted to PINHOLE" in note for note in scene.notes)
    original = pycolmap.Reconstruction(str(shared_data / "colmap_cup" / "sparse" / "0"))
    by_name = {image.name: image for image in original.images.values()}
    for view in scene.train:
        pinhole = original.cameras[by_name[view.name + ".jpg"].camera_id]
        camera = view.camera
        assert camera.fx == pytest.approx(pinhole.params[0]) and camera.fy == pytest.approx(pinhole.params[0])
        new = pycolmap.Camera(model="PINHOLE", width=camera.width, height=camera.height,
                              params=[camera.fx, camera.fy, camera.cx, camera.cy])
        # Same focal length: the undistorted image is the photo moved by the change of principal point.
        photo = np.asarray(Image.open(shared_data / "colmap_cup" / "images" / f"{view.name}.jpg"))
        expected = torch.from_numpy(distort_photo(photo, pinhole, new)).float() / 255
        raw = np.asarray(Image.open(scene_dir / "images" / f"{view.name}.jpg"))
        raw = torch.from_numpy(distort_photo(raw, pinhole, new)).float() / 255  # distorted, taken as a pinhole's
        # Compare where the original photo has pixels, away from the border the warps had to clamp.
        dx, dy = round(camera.cx - pinhole.params[1]), round(camera.cy - pinhole.params[2])
        ys = slice(max(dy, 0) + 8, min(camera.height, 600 + dy) - 8)
        xs = slice(max(dx, 0) + 8, min(camera.width, 800 + dx) - 8)
        loaded = view.image.float()[ys, xs] / 255
        assert psnr(loaded, expected[ys, xs]) > 30.0, (view.name, psnr(loaded, expected[ys, xs]))
        assert psnr(raw[ys, xs], expected[ys, xs]) < psnr(loaded, expected[ys, xs]) - 5.0  # distortion gone


def reprojection_errors(shared_data: Path, scene_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """Pixel distance between each stored keypoint and its SfM point projected: through the distorted model onto the
    distorted photo, and through the loaded PINHOLE camera onto the undistorted image (keypoint moved with it)."""
    model = pycolmap.Reconstruction(str(scene_dir / "sparse" / "0"))
    scene = load_scene(scene_dir, test_every=0)
    views = {view.name: view for view in scene.train}
    before, after = [], []
    for image in (i for i in model.images.values() if i.has_pose):
        lens = model.cameras[image.camera_id]
        view = views[Path(image.name).stem]
        pinhole = pycolmap.Camera(model="PINHOLE", width=view.camera.width, height=view.camera.height,
                                  params=[view.camera.fx, view.camera.fy, view.camera.cx, view.camera.cy])
        w2c = view.camera.world_to_camera.double().numpy()
        observed = [(p.xy, model.points3D[p.point3D_id].xyz) for p in image.points2D if p.has_point3D()]
        keypoints = np.array([xy for xy, _ in observed])
        xyz = np.array([x for _, x in observed])
        in_camera = xyz @ w2c[:3, :3].T + w2c[:3, 3]  # the loaded pose; the same as the model's
        before.append(np.linalg.norm(lens.img_from_cam(in_camera) - keypoints, axis=1))
        moved = pinhole.img_from_cam(np.append(lens.cam_from_img(keypoints), np.ones((len(keypoints), 1)), axis=1))
        projected = in_camera[:, :2] / in_camera[:, 2:] * [view.camera.fx, view.camera.fy] \
            + [view.camera.cx, view.camera.cy]
        after.append(np.linalg.norm(projected - moved, axis=1))
    return np.concatenate(before), np.concatenate(after)


def test_sfm_points_project_onto_the_same_keypoints_after_undistortion(shared_data, tmp_path):
    scene_dir = make_distorted_cup(shared_data, tmp_path / "opencv", "OPENCV", CUP_IMAGES)
    before, after = reprojection_errors(shared_data, scene_dir)
    assert len(before) > 1500  # observations of SfM points in the six photos
    print(f"median reprojection error {np.median(before):.3f} px distorted, {np.median(after):.3f} px undistorted")
    # COLMAP's own reprojection error on the cup is about half a pixel; undistortion must not add to it.
    assert np.median(before) < 1.0 and np.median(after) < 1.0
    assert abs(np.median(after) - np.median(before)) < 0.05
    assert np.percentile(after, 90) < np.percentile(before, 90) + 0.1
    # And the keypoints sit on the same image content: the undistorted image at the projected point matches the
    # distorted photo at the stored keypoint (nearest pixel, all views, SfM points are textured spots).
    scene = load_scene(scene_dir, test_every=0)
    model = pycolmap.Reconstruction(str(scene_dir / "sparse" / "0"))
    differences = []
    for view in scene.train:
        image = next(i for i in model.images.values() if i.has_pose and Path(i.name).stem == view.name)
        photo = np.asarray(Image.open(scene_dir / "images" / image.name), dtype=np.float64)
        undistorted = view.image.double().numpy()
        w2c = view.camera.world_to_camera.double().numpy()
        for p in image.points2D:
            if not p.has_point3D():
                continue
            c = w2c[:3, :3] @ model.points3D[p.point3D_id].xyz + w2c[:3, 3]
            u, v = c[0] / c[2] * view.camera.fx + view.camera.cx, c[1] / c[2] * view.camera.fy + view.camera.cy
            if 1 <= u < view.camera.width - 1 and 1 <= v < view.camera.height - 1:
                differences.append(np.abs(undistorted[int(v), int(u)] - photo[int(p.xy[1]), int(p.xy[0])]).mean())
    assert np.median(differences) < 12.0, np.median(differences)


def test_cache_is_outside_the_scene_reused_and_never_stale(shared_data, tmp_path, private_cache):
    scene_dir = make_distorted_cup(shared_data, tmp_path / "cup", "SIMPLE_RADIAL", CUP_IMAGES[:2])
    first = load_scene(scene_dir, test_every=0)
    cached = sorted(private_cache.rglob("*.png"))
    assert len(cached) == 2
    stamps = [p.stat().st_mtime_ns for p in cached]
    second = load_scene(scene_dir, test_every=0)
    assert sorted(private_cache.rglob("*.png")) == cached and [p.stat().st_mtime_ns for p in cached] == stamps
    assert all(torch.equal(a.image, b.image) for a, b in zip(first.train, second.train))
    # A replaced photo (same name, same size, even the same modification time) is undistorted again.
    name = first.train[0].name + ".jpg"
    path = scene_dir / "images" / name
    stat = path.stat()
    Image.open(path).transpose(Image.Transpose.FLIP_LEFT_RIGHT).save(path, quality=95)
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    third = load_scene(scene_dir, test_every=0)
    assert not torch.equal(third.train[0].image, first.train[0].image)
    assert torch.equal(third.train[1].image, first.train[1].image)
    # A changed lens in the model is too.
    model = pycolmap.Reconstruction(str(scene_dir / "sparse" / "0"))
    for camera in model.cameras.values():
        if camera.model.name == "SIMPLE_RADIAL":
            camera.params = [*camera.params[:3], -0.05]
    model.write_binary(str(scene_dir / "sparse" / "0"))
    fourth = load_scene(scene_dir, test_every=0)
    assert len(list(private_cache.rglob("*.png"))) == 5
    assert fourth.train[1].camera.width != first.train[1].camera.width


def test_a_replaced_or_damaged_cache_entry_is_made_again(shared_data, tmp_path, private_cache):
    scene_dir = make_distorted_cup(shared_data, tmp_path / "cup", "SIMPLE_RADIAL", CUP_IMAGES[:2])
    first = load_scene(scene_dir, test_every=0)
    entries = sorted(private_cache.rglob("*.png"))
    size = Image.open(entries[0]).size
    Image.new("RGB", size, (255, 0, 0)).save(entries[0])  # a red image of the right size
    entries[1].write_bytes(entries[1].read_bytes()[:100])  # a cut-short file
    second = load_scene(scene_dir, test_every=0)
    assert all(torch.equal(a.image, b.image) for a, b in zip(first.train, second.train)), "the photos, not the red"
    assert Image.open(entries[0]).getpixel((size[0] // 2, size[1] // 2)) != (255, 0, 0)
    assert sorted(private_cache.rglob("*.png")) == entries


def c2w_opengl(w2c: np.ndarray) -> list[list[float]]:
    c2w = np.linalg.inv(w2c)
    c2w[:3, 1:3] *= -1  # OpenCV (y down, z forward) -> OpenGL (y up, z back)
    return c2w.tolist()


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_distorted_transforms_json_matches_the_colmap_model(shared_data, tmp_path, model):
    """An instant-ngp / nerfstudio transforms.json with k1 k2 p1 p2 (or a fisheye's k1..k4) over the same photos
    loads to the same pinhole cameras and pixels as the COLMAP model."""
    scene_dir = make_distorted_cup(shared_data, tmp_path / "cup", model, CUP_IMAGES[:2])
    colmap_scene = load_scene(scene_dir, test_every=0)
    reconstruction = pycolmap.Reconstruction(str(scene_dir / "sparse" / "0"))
    frames = []
    for image in sorted((i for i in reconstruction.images.values() if i.has_pose), key=lambda i: i.name):
        camera = reconstruction.cameras[image.camera_id]
        fx, fy, cx, cy, *d = camera.params
        keys = ["k1", "k2", "k3", "k4"] if model == "OPENCV_FISHEYE" else ["k1", "k2", "p1", "p2"]
        w2c = np.eye(4)
        w2c[:3] = np.asarray(image.cam_from_world().matrix())
        frames.append({"file_path": f"images/{image.name}", "transform_matrix": c2w_opengl(w2c), "fl_x": fx,
                       "fl_y": fy, "cx": cx, "cy": cy, "w": camera.width, "h": camera.height,
                       **dict(zip(keys, d))})
    meta = {"camera_model": model, "frames": frames}
    (scene_dir / "transforms.json").write_text(json.dumps(meta))
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        (scene_dir / "sparse" / "0" / name).unlink()
    nerf_scene = load_scene(scene_dir, test_every=0)
    assert nerf_scene.kind == "blender"
    for a, b in zip(colmap_scene.train, nerf_scene.train):
        assert a.name == b.name.removeprefix("images/")
        assert torch.allclose(a.camera.K, b.camera.K)
        assert torch.allclose(a.camera.world_to_camera, b.camera.world_to_camera, atol=1e-5)
        assert torch.equal(a.image, b.image)


def test_train_runs_on_a_simple_radial_capture(shared_data, tmp_path):
    """`mcsplat train` on a COLMAP SIMPLE_RADIAL capture as it comes, at 1/4 size (undistorted, then resized),
    fits its views as well as it fits the same photos taken by the original pinhole camera."""
    from mcsplat.config import TrainConfig
    from mcsplat.run.evaluation import evaluate
    from mcsplat.initialization import initial_model
    from mcsplat.run.trained import load
    from mcsplat.train import train

    scores = {}
    for model in ("SIMPLE_RADIAL", "SIMPLE_PINHOLE"):
        scene_dir = make_distorted_cup(shared_data, tmp_path / model, model, CUP_IMAGES)
        run = tmp_path / f"run-{model}"
        metrics = train(TrainConfig(data=scene_dir, out=run, steps=STEPS, downscale=4, test_every=6, quiet=True,
                                    save_every=0, lpips_net="alex", scale_schedule=False))  # no refinement in 250 steps
        assert metrics["steps"] == STEPS
        scene = load_scene(scene_dir, downscale=4, test_every=6)
        assert scene.train[0].camera.width == (200 if model == "SIMPLE_PINHOLE" else 212)  # 849 / 4, rounded
        trained_run = load(run, torch.device("cpu"))
        trained, config = trained_run.model, trained_run.config
        initial, _ = initial_model(config, scene, torch.device("cpu"), torch.Generator().manual_seed(0))
        scores[model] = [evaluate(m, scene.train, scene.background, 0, torch.device("cpu")).psnr
                         for m in (initial, trained)]
    print(f"PSNR on the training views at the start and after {STEPS} steps: {scores}")
    assert scores["SIMPLE_RADIAL"][1] > scores["SIMPLE_RADIAL"][0] + 2.0
    assert abs(scores["SIMPLE_RADIAL"][1] - scores["SIMPLE_PINHOLE"][1]) < 1.0, scores
