"""The pieces under the loaders: splits, options, radius, image folders and pixel formats (no shared data needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from mcsplat.camera import Camera, intrinsics
from mcsplat.data import View
from mcsplat.data.images import choose_image_dir, load_images
from mcsplat.data.scene import camera_radius, check_options, make_scene, parse_background, split_every
from mcsplat.errors import DataError, MCSplatError


def test_split_every() -> None:
    train, test = split_every(list(range(20)), 8)
    assert test == [0, 8, 16] and train == [i for i in range(20) if i % 8]
    assert split_every([1, 2, 3], 0) == ([1, 2, 3], [])


def test_options_and_background() -> None:
    assert check_options(2, 0) == (2, 0)
    for bad in [(0, 8), (True, 8), (2.0, 8), (1, -1)]:
        with pytest.raises(MCSplatError):
            check_options(*bad)
    assert parse_background(None, (1.0, 1.0, 1.0)) == (1.0, 1.0, 1.0)
    assert parse_background("Black", (1.0, 1.0, 1.0)) == (0.0, 0.0, 0.0)
    assert parse_background("0.5, 0.25,1", (0.0, 0.0, 0.0)) == (0.5, 0.25, 1.0)
    assert parse_background([0, 1, 0], (0.0, 0.0, 0.0)) == (0.0, 1.0, 0.0)
    for bad in ["grey", "1,2", (0.5, 1.5, 0.0), "a,b,c"]:
        with pytest.raises(MCSplatError):
            parse_background(bad, (0.0, 0.0, 0.0))


def camera_at(centre: list[float]) -> Camera:
    w2c = torch.eye(4)
    w2c[:3, 3] = -torch.tensor(centre)  # identity rotation: t = -centre
    return Camera(K=intrinsics(10.0, 10.0, 4.0, 3.0), world_to_camera=w2c, width=8, height=6)


def test_radius_and_scene() -> None:
    cameras = [camera_at([0, 0, 0]), camera_at([2, 0, 0]), camera_at([1, 3, 0])]
    centres = np.array([[0, 0, 0], [2, 0, 0], [1, 3, 0]], dtype=float)
    expected = 1.1 * np.linalg.norm(centres - centres.mean(0), axis=1).max()
    assert camera_radius(cameras) == pytest.approx(expected)
    assert camera_radius([camera_at([5, 5, 5])]) == 1.0  # degenerate: one camera
    image = torch.full((6, 8, 3), 255, dtype=torch.uint8)
    views = [View(camera=c, image=image, name=f"v{i}") for i, c in enumerate(cameras)]
    scene = make_scene(views[1:], views[:1], torch.zeros(0, 3), torch.zeros(0, 3), (1.0, 1.0, 1.0), "colmap",
                       Path("/x"))
    # train cameras only (centres (2,0,0), (1,3,0)); no points -> None
    assert scene.points is None and scene.radius == pytest.approx(1.1 * np.sqrt(2.5))
    text = scene.summary()
    assert "colmap" in text and "2 train, 1 test" in text and "8x6" in text and "white" in text
    assert views[0].image_float().dtype == torch.float32 and views[0].image_float().max() == 1.0
    assert "v0" in repr(views[0]) and "tensor" not in repr(scene)


def test_choose_image_dir(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="no image folder"):
        choose_image_dir(tmp_path, 1)
    (tmp_path / "images_8").mkdir()
    assert choose_image_dir(tmp_path, 1) == (tmp_path / "images_8", 8)  # only a smaller copy: used as is
    (tmp_path / "images_2").mkdir()
    assert choose_image_dir(tmp_path, 4) == (tmp_path / "images_2", 2)  # resized from the closest larger one
    assert choose_image_dir(tmp_path, 8) == (tmp_path / "images_8", 8)
    (tmp_path / "images").mkdir()
    assert choose_image_dir(tmp_path, 4) == (tmp_path / "images", 1)
    assert choose_image_dir(tmp_path, 2) == (tmp_path / "images_2", 2)


def test_pixel_formats(tmp_path: Path) -> None:
    """Grey, grey+alpha, palette with transparency and 16-bit grey all become uint8 RGB (alpha on the background)."""
    rng = np.random.default_rng(0)
    grey = rng.integers(0, 256, (6, 8), dtype=np.uint8)
    alpha = np.where(np.arange(8) < 4, 255, 0).astype(np.uint8)[None].repeat(6, 0)
    Image.fromarray(grey, "L").save(tmp_path / "l.png")
    Image.fromarray(np.stack([grey, alpha], -1), "LA").save(tmp_path / "la.png")
    (grey.astype(np.uint16) * 257).astype(np.uint16).tofile(tmp_path / "raw")
    Image.fromarray(grey.astype(np.uint16) * 257).save(tmp_path / "i16.png")
    palette = Image.fromarray(grey, "L").convert("P")
    palette.info["transparency"] = int(palette.getpixel((0, 0)))
    palette.save(tmp_path / "p.png", transparency=int(palette.getpixel((0, 0))))
    paths = [tmp_path / n for n in ("l.png", "la.png", "i16.png", "p.png")]
    out = load_images(paths, [(8, 6)] * 4, background=(1.0, 0.0, 0.0), workers=2)
    rgb = np.repeat(grey[..., None], 3, -1)
    assert all(t.dtype == torch.uint8 and tuple(t.shape) == (6, 8, 3) for t in out)
    np.testing.assert_array_equal(out[0].numpy(), rgb)
    np.testing.assert_array_equal(out[1].numpy()[:, :4], rgb[:, :4])
    assert (out[1].numpy()[:, 4:] == [255, 0, 0]).all()
    np.testing.assert_array_equal(out[2].numpy(), rgb)
    assert (out[3].numpy()[0, 0] == [255, 0, 0]).all()
    half = load_images(paths[:1], [(4, 3)], background=(0.0, 0.0, 0.0))[0]
    np.testing.assert_allclose(half.numpy()[..., 0], grey.reshape(3, 2, 4, 2).mean((1, 3)), atol=0.5 + 1e-9)
