"""Training masks (data/attachments/masks.py): found by the image's name, inverted on request, undistorted with their
image, the alpha channel as a mask; the loss leaves masked pixels out; on a real capture with a block painted over every
photo, the block shows in the renders without its mask and not with it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from mcsplat.data import load_scene
from mcsplat.data.attachments.masks import MaskOptions
from mcsplat.errors import DataError
from mcsplat.losses import masked_photometric_loss, photometric_loss
from mcsplat.metrics import masked_psnr, masked_ssim, psnr, ssim_metric

CUP_SIZE = (800, 600)   # the cup's photos; images_4/ holds them at 200x150
BLOCK = (slice(200, 400), slice(280, 520))  # rows, columns at 800x600: multiples of 4, so exact at 200x150
MAGENTA = np.array([255, 0, 255], dtype=np.uint8)


def _block_at(scale: int) -> tuple[slice, slice]:
    return tuple(slice(s.start // scale, s.stop // scale) for s in BLOCK)


def _cup_copy(shared_data: Path, root: Path, paint: bool = False) -> Path:
    """The cup with its 200x150 images only (and, with `paint`, a magenta block over every one of them)."""
    source = shared_data / "colmap_cup"
    shutil.copytree(source / "sparse", root / "sparse", copy_function=shutil.copyfile)
    (root / "images_4").mkdir(parents=True)
    for photo in sorted((source / "images_4").iterdir()):
        if paint:
            pixels = np.array(Image.open(photo).convert("RGB"))
            pixels[_block_at(4)] = MAGENTA
            Image.fromarray(pixels).save(root / "images_4" / photo.name, quality=95)
        else:
            shutil.copyfile(photo, root / "images_4" / photo.name)
    return root


def _write_block_masks(root: Path, colmap_named: int = 0) -> None:
    """masks/<view name>.png at the photos' full size, black over the block; the first `colmap_named` under
    COLMAP's name (<image file name>.png)."""
    (root / "masks").mkdir()
    mask = np.full(CUP_SIZE[::-1], 255, dtype=np.uint8)
    mask[BLOCK] = 0
    for i, photo in enumerate(sorted((root / "images_4").iterdir())):
        name = f"{photo.name}.png" if i < colmap_named else f"{photo.stem}.png"
        Image.fromarray(mask).save(root / "masks" / name)


# ----------------------------------------------------------------------------------------------- loss and metrics
def test_masked_loss_takes_nothing_from_left_out_pixels():
    generator = torch.Generator().manual_seed(0)
    image = torch.rand(40, 50, 3, generator=generator, requires_grad=True)
    target = torch.rand(40, 50, 3, generator=generator)
    keep = torch.ones(40, 50, 1)
    keep[10:30, 5:25] = 0
    loss = masked_photometric_loss(image, target, keep)
    loss.backward()
    assert image.grad[10:30, 5:25].abs().max() == 0  # no gradient through a left-out pixel
    assert image.grad[35:, 30:].abs().min() > 0
    # Whatever the target holds where it is left out, the loss is the same.
    changed = target.clone()
    changed[10:30, 5:25] = 1.0 - changed[10:30, 5:25]
    assert masked_photometric_loss(image, changed, keep).item() == pytest.approx(loss.item(), rel=1e-6)
    # A mask that keeps everything is the plain loss.
    assert masked_photometric_loss(image, target, torch.ones(40, 50, 1)).item() == pytest.approx(
        photometric_loss(image, target).item(), rel=1e-6)


def test_masked_metrics_score_only_kept_pixels():
    generator = torch.Generator().manual_seed(1)
    target = torch.rand(32, 32, 3, generator=generator)
    image = target.clone()
    image[:16] = (target[:16] + 0.1).clamp(0, 1)  # wrong in the top half only
    top_left_out = torch.ones(32, 32, 1)
    top_left_out[:16] = 0
    assert masked_psnr(image, target, top_left_out) == float("inf")
    assert masked_psnr(image, target, torch.ones(32, 32, 1)) == pytest.approx(psnr(image, target), abs=1e-4)
    assert masked_ssim(image, target, torch.ones(32, 32, 1)) == pytest.approx(ssim_metric(image, target), abs=1e-5)
    assert masked_ssim(image, target, top_left_out) > ssim_metric(image, target)


# --------------------------------------------------------------------------------------------------------- loading
def test_masks_are_found_by_name_resized_and_inverted(shared_data, tmp_path):
    root = _cup_copy(shared_data, tmp_path / "cup")
    _write_block_masks(root, colmap_named=3)
    scene = load_scene(root, downscale=4)
    views = scene.train + scene.test
    expected = np.full((150, 200), 255, dtype=np.uint8)
    expected[_block_at(4)] = 0
    for view in views:  # 800x600 masks brought to the 200x150 images, exact at the block's edges
        assert np.array_equal(view.mask.numpy(), expected), view.name
    assert any(f"masks for {len(views)} of {len(views)} images" in note for note in scene.notes)
    inverted = load_scene(root, downscale=4, masks=MaskOptions(invert_masks=True))
    assert np.array_equal(inverted.train[0].mask.numpy(), 255 - expected)
    assert load_scene(root, downscale=4, masks=MaskOptions("none")).train[0].mask is None
    # A folder named on the command line, away from the scene, works the same way.
    elsewhere = tmp_path / "my-masks"
    shutil.move(root / "masks", elsewhere)
    assert load_scene(root, downscale=4).train[0].mask is None  # no masks/ any more: none
    assert np.array_equal(load_scene(root, downscale=4, masks=MaskOptions(str(elsewhere))).test[1].mask.numpy(),
                          expected)


def test_missing_or_misshapen_masks_are_one_line_errors(shared_data, tmp_path):
    root = _cup_copy(shared_data, tmp_path / "cup")
    _write_block_masks(root)
    (root / "masks" / "12.png").unlink()
    with pytest.raises(DataError, match=r"no mask for 1 of the 77 images \(12\).*--masks none"):
        load_scene(root, downscale=4)
    Image.new("L", (100, 100), 255).save(root / "masks" / "12.png")
    with pytest.raises(DataError, match=r"12.png is 100x100 but its image is 200x150"):
        load_scene(root, downscale=4)
    with pytest.raises(DataError, match="no such folder"):
        load_scene(root, downscale=4, masks=MaskOptions(str(tmp_path / "nowhere")))
    with pytest.raises(DataError, match="no alpha channel"):
        load_scene(root, downscale=4, masks=MaskOptions("alpha"))


def test_masks_that_leave_nothing_to_train_on_are_refused(shared_data, tmp_path, capsys):
    """An all-black mask leaves its view nothing to train on or score; all of them leave the run the regularisers
    alone (it trained to a loss of 0.0008 and exited 0). Either is one line that names the masks."""
    from mcsplat.cli import main

    root = _cup_copy(shared_data, tmp_path / "cup")
    _write_block_masks(root)
    black = Image.new("L", CUP_SIZE, 0)
    black.save(root / "masks" / "12.png")
    with pytest.raises(DataError, match=r"mask .*12.png leaves out every pixel of 12\b") as info:
        load_scene(root, downscale=4)
    assert "\n" not in str(info.value)
    for mask in (root / "masks").iterdir():
        black.save(mask)
    with pytest.raises(DataError, match=r"every one of the 77 masks .* leaves out every pixel.*--invert-masks"):
        load_scene(root, downscale=4)
    white = Image.new("L", CUP_SIZE, 255)  # white inverted: black again, and the hint is to drop --invert-masks
    for mask in (root / "masks").iterdir():
        white.save(mask)
    with pytest.raises(DataError, match=r"\(inverted\).*without --invert-masks"):
        load_scene(root, downscale=4, masks=MaskOptions(invert_masks=True))
    run = tmp_path / "run"
    status = main(["train", str(root), "--out", str(run), "--downscale", "4", "--steps", "5", "--quiet",
                   "--invert-masks"])
    error = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and error[-1].startswith("mcsplat: error: every one of the 77 masks"), error
    assert not (run / "checkpoint.pt").exists() and not (run / "metrics.json").exists()


def test_a_mask_is_undistorted_with_its_image(shared_data, tmp_path, monkeypatch):
    """ngp_fruit's OPENCV camera: a mask made from the photo's own bright pixels still lies on them once both are
    undistorted."""
    monkeypatch.setenv("MCSPLAT_CACHE", str(tmp_path / "cache"))
    source = shared_data / "ngp_fruit"
    root = tmp_path / "fruit"
    meta = json.loads((source / "transforms.json").read_text())
    meta["frames"] = meta["frames"][:3]
    (root / "masks").mkdir(parents=True)
    (root / "newfruit_small").mkdir()
    for frame in meta["frames"]:
        photo = source / frame["file_path"]
        shutil.copyfile(photo, root / "newfruit_small" / photo.name)
        grey = np.asarray(Image.open(photo).convert("L"))
        Image.fromarray(np.where(grey > np.median(grey), 255, 0).astype(np.uint8)).save(
            root / "masks" / f"{photo.stem}.png")
    (root / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(root, test_every=0)
    assert any("undistorted" in note for note in scene.notes)
    for view in scene.train:
        original = np.asarray(Image.open(root / "newfruit_small" / f"{Path(view.name).name}.jpg").convert("L"))
        grey = view.image.to(torch.float32).mul(torch.tensor([0.299, 0.587, 0.114])).sum(-1).numpy()
        bright = grey > np.median(original)
        agree = ((view.mask.numpy() > 127) == bright).mean()
        assert view.mask.shape == view.image.shape[:2]
        assert agree > 0.95, f"{view.name}: the mask agrees with its undistorted image on {agree:.1%} of pixels"


def test_alpha_channel_as_mask(mini_demo):
    scene = load_scene(mini_demo, masks=MaskOptions("alpha"))
    view = scene.train[0]
    alpha = np.asarray(Image.open(mini_demo / "train" / f"{Path(view.name).name}.png").convert("RGBA"))[:, :, 3]
    width, height = view.camera.width, view.camera.height
    if alpha.shape != (height, width):
        alpha = np.asarray(Image.fromarray(alpha).resize((width, height), Image.Resampling.BOX))
    assert np.abs(view.mask.numpy().astype(int) - alpha.astype(int)).max() <= 1
    assert 0 < (view.mask.numpy() == 0).mean() < 1  # the transparent surroundings are left out, the object kept


# ------------------------------------------------------------------------------------------- training, end to end
def _magenta_in_block(run: Path) -> float:
    """How magenta the block region of the training renders is: mean (R + B) / 2 - G (the paint: 1)."""
    from mcsplat.run import trained as trained_run
    from mcsplat.render import render

    trained = trained_run.load(run, torch.device("cpu"))
    scores = []
    for view in trained.scene.train[::8]:
        with torch.no_grad():
            region = render(trained.model, view.camera, trained.background, trained.sh_degree).rgb[_block_at(4)]
        scores.append(float(((region[..., 0] + region[..., 2]) / 2 - region[..., 1]).mean()))
    return float(np.mean(scores))


def test_a_block_painted_over_every_photo_is_not_learned_with_its_mask(shared_data, tmp_path):
    from mcsplat.config import config_of
    from mcsplat.strategy.mcmc import MCMCConfig
    from mcsplat.train import train

    root = _cup_copy(shared_data, tmp_path / "cup", paint=True)
    _write_block_masks(root)
    magenta = {}
    for masks in ("auto", "none"):
        run = tmp_path / f"run-{masks}"
        metrics = train(config_of(data=root, out=run, downscale=4, steps=400, masks=masks, quiet=True,
                                    lpips_net="alex", save_every=0, save_renders=False,
                                    mcmc=MCMCConfig(cap_max=15000)))
        magenta[masks] = _magenta_in_block(run)
        assert ("masked_psnr" in metrics) == (masks == "auto")
    assert magenta["auto"] < 0.1, magenta  # the scene behind the block, seen from the other views
    assert magenta["none"] > 0.15, magenta  # the paint, learned as floaters in front of every camera


def test_mask_options_that_name_no_masks_are_one_line_errors(mini_demo, tmp_path, capsys):
    """--masks '' names no folder (not the current one); --invert-masks with no masks to invert is refused."""
    from mcsplat.cli import main

    cases = [(["info", str(mini_demo), "--masks", ""], "--masks ''"),
             (["info", str(mini_demo), "--invert-masks"], "--invert-masks"),
             (["info", str(mini_demo), "--masks", "none", "--invert-masks"], "--invert-masks"),
             (["train", str(mini_demo), "--out", str(tmp_path / "run"), "--invert-masks", "--steps", "5", "--quiet"],
              "--invert-masks"),
             (["process", str(tmp_path / "photos"), "--out", str(tmp_path / "scene"), "--invert-masks"],
              "--invert-masks")]
    for argv, expected in cases:
        capsys.readouterr()
        assert main(argv) == 2, argv
        error = capsys.readouterr().err
        assert error.startswith("mcsplat: error:") and expected in error and error.count("\n") == 1, (argv, error)
        assert "has no mask for" not in error, error
    assert not (tmp_path / "run" / "checkpoint.pt").exists() and not (tmp_path / "scene").exists()
