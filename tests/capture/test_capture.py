"""`mcsplat process`: the real cup photos (resized to 400x300) and a video made from the real bird photos.

One SfM reconstruction of the cup is shared by the tests that need it (module fixture, 2 threads, about 20 s).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image, ImageFilter

from mcsplat.capture import ProcessOptions, process
from mcsplat.capture.frames import sharpness
from mcsplat.data import load_scene
from mcsplat.errors import MCSplatError

SMALL = (400, 300)


@pytest.fixture(scope="module")
def cup_photos(tmp_path_factory) -> Path:
    source = Path(__file__).resolve().parents[3] / "shared" / "data" / "colmap_cup" / "images"
    if not source.is_dir():
        pytest.skip(f"real datasets not found at {source}")
    folder = tmp_path_factory.mktemp("cup_photos")
    for path in source.glob("*.jpg"):
        Image.open(path).resize(SMALL, Image.Resampling.BOX).save(folder / path.name, quality=95)
    return folder


@pytest.fixture(scope="module")
def cup_scene(cup_photos, tmp_path_factory):
    out = tmp_path_factory.mktemp("processed") / "cup"
    start = time.perf_counter()
    with pytest.warns(UserWarning, match="400 px on the long side"):
        summary = process(cup_photos, out, ProcessOptions(threads=2, progress=False))
    print(f"cup at 400x300: {summary.registered}/{summary.images} registered, {summary.points} points, "
          f"{time.perf_counter() - start:.1f} s {summary.seconds}")
    return out, summary


def test_cup_photos_register_and_agree_with_the_cup_model(cup_scene, shared_data):
    out, summary = cup_scene
    assert summary.images == 77 and summary.registered >= 70
    assert summary.matcher == "exhaustive" and summary.points > 1000 and summary.mean_reprojection_error < 1.5
    ours = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert {camera.model.name for camera in ours.cameras.values()} == {"PINHOLE"}
    reference = pycolmap.Reconstruction(str(shared_data / "colmap_cup" / "sparse" / "0"))
    comparison = pycolmap.compare_reconstructions(ours, reference, alignment_error="proj_center")
    rotation = [error.rotation_error_deg for error in comparison["errors"]]
    print(f"median rotation error {np.median(rotation):.2f} deg over {len(rotation)} images")
    assert len(rotation) >= 70 and np.median(rotation) < 3.0


def test_processed_scene_loads_and_nothing_is_left_beside_it(cup_scene, cup_photos):
    out, summary = cup_scene
    scene = load_scene(out)
    assert scene.kind == "colmap" and len(scene.train) + len(scene.test) == summary.registered
    assert scene.points is not None and scene.points.shape[0] == summary.points
    assert sorted(p.name for p in out.parent.iterdir()) == ["cup"]  # no partial work folder
    assert len(list(cup_photos.iterdir())) == 77  # the input folder is untouched


def test_an_existing_scene_is_not_overwritten(cup_scene, cup_photos):
    out, _ = cup_scene
    before = sorted(p.name for p in (out / "images").iterdir())
    with pytest.raises(MCSplatError, match="already holds a scene.*--overwrite"):
        process(cup_photos, out, ProcessOptions(threads=2, progress=False))
    assert sorted(p.name for p in (out / "images").iterdir()) == before


def test_bad_inputs_get_one_line_errors(tmp_path, cup_photos):
    empty = tmp_path / "empty"
    empty.mkdir()
    cases = [(tmp_path / "missing", tmp_path / "a", "does not exist"),
             (empty, tmp_path / "b", "no images in"),
             (cup_photos, cup_photos / "scene", "inside the input folder")]
    broken = tmp_path / "broken"  # a broken photo is left out (see below): here every one is
    broken.mkdir()
    (broken / "1.jpg").write_bytes((cup_photos / "1.jpg").read_bytes()[:5000])
    (broken / "12.jpg").write_bytes(b"not a jpeg")
    cases.append((broken, tmp_path / "c", r"none of the 2 images in .* can be read \(1.jpg: image file is truncated"))
    bad_video = tmp_path / "clip.mp4"
    bad_video.write_bytes(b"\x00" * 1000)
    cases.append((bad_video, tmp_path / "d", "cannot read video"))
    two = tmp_path / "two"
    two.mkdir()
    for name in ("1.jpg", "10.jpg"):
        (two / name).write_bytes((cup_photos / name).read_bytes())
    cases.append((two, tmp_path / "e", "at least 3"))
    for source, out, expected in cases:
        with pytest.raises(MCSplatError, match=expected) as info:
            with pytest.warns(UserWarning) if source == two else _nothing():
                process(source, out, ProcessOptions(threads=2, progress=False))
        assert "\n" not in str(info.value)
        assert not out.exists()
    assert len(list(cup_photos.iterdir())) == 77


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *args):
        return False


def copy_photos(cup_photos: Path, folder: Path, count: int) -> Path:
    folder.mkdir(parents=True)
    for path in sorted(cup_photos.glob("*.jpg"))[:count]:
        (folder / path.name).write_bytes(path.read_bytes())
    return folder


def test_an_input_inside_the_output_is_refused_and_kept(cup_photos, tmp_path):
    """`process SCENE/images --out SCENE --overwrite` would replace the folder that holds the photos."""
    scene = tmp_path / "scene"
    photos = copy_photos(cup_photos, scene / "images", 2)
    (scene / "sparse").mkdir()
    for source in (photos, scene):
        with pytest.raises(MCSplatError, match="is inside (--out|the input folder)") as info:
            process(source, scene, ProcessOptions(threads=1, progress=False, overwrite=True))
        assert "\n" not in str(info.value)
    assert sorted(p.name for p in photos.iterdir()) == sorted(p.name for p in cup_photos.glob("*.jpg"))[:2]


def test_overwrite_replaces_only_what_process_wrote(cup_photos, tmp_path):
    """A scene is replaced only while it holds nothing but the files its process.json lists."""
    two = copy_photos(cup_photos, tmp_path / "two", 2)  # fails ("at least 3") after the check of --out
    scene = tmp_path / "scene"
    copy_photos(cup_photos, scene / "images", 3)
    (scene / "sparse" / "0").mkdir(parents=True)
    (scene / "sparse" / "0" / "cameras.bin").write_bytes(b"made elsewhere")
    options = ProcessOptions(threads=1, progress=False, overwrite=True)
    with pytest.raises(MCSplatError, match="did not make"):
        process(two, scene, options)
    listed = sorted(str(p.relative_to(scene)) for p in scene.rglob("*") if p.is_file())
    (scene / "process.json").write_text(json.dumps({"files": listed + ["process.json"]}))
    (scene / "notes.txt").write_text("mine")
    with pytest.raises(MCSplatError, match=r"did not write \(notes.txt\)"):
        process(two, scene, options)
    (scene / "notes.txt").unlink()
    with pytest.raises(MCSplatError, match="at least 3"), pytest.warns(UserWarning):
        process(two, scene, options)  # past the check: the scene would have been replaced
    assert len(list((scene / "images").iterdir())) == 3, "a failed run replaces nothing"


def processes_mentioning(text: str) -> list[int]:
    """The pids of the processes whose command line contains `text` (the worker names its work folder)."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and text.encode() in (entry / "cmdline").read_bytes():
                found.append(int(entry.name))
        except OSError:
            continue
    return found


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_signal_leaves_no_scene_and_no_worker(cup_photos, tmp_path, sig):
    """SIGINT (Ctrl-C) or SIGTERM (kill, timeout, docker) once feature extraction has started: exit status 2, a
    one-line message, the SfM worker stopped, and nothing on disk."""
    out = tmp_path / "scene"
    command = [sys.executable, "-m", "mcsplat.cli", "process", str(cup_photos), "--out", str(out), "--threads", "1"]
    # SIGINT as a terminal delivers it (a parent started in the background may have left it ignored).
    child = subprocess.Popen(command, stderr=subprocess.PIPE,
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    seen = b""
    try:
        deadline = time.monotonic() + 120
        while b"features:" not in seen and time.monotonic() < deadline:
            chunk = os.read(child.stderr.fileno(), 4096)
            if not chunk:
                break
            seen += chunk
        assert b"features:" in seen, seen[-2000:]
        time.sleep(1.0)
        assert processes_mentioning(str(tmp_path / ".scene.partial-")), "the SfM worker runs"
        child.send_signal(sig)
        stderr = (seen + child.communicate(timeout=60)[1]).decode(errors="replace")
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert child.returncode == 2, stderr[-3000:]
    assert "mcsplat: error: interrupted: no scene was written" in stderr
    deadline = time.monotonic() + 10  # the worker is stopped (and waited for) before the parent exits
    while processes_mentioning(str(tmp_path / ".scene.partial-")) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert processes_mentioning(str(tmp_path / ".scene.partial-")) == [], "the SfM worker was left running"
    assert list(tmp_path.iterdir()) == []


def test_video_path_keeps_the_sharp_frames_and_registers_them(shared_data, tmp_path):
    """A video of 24 real bird photos, each followed by a blurred copy: the sharp one of each pair is kept."""
    import imageio.v2 as imageio

    names = sorted((shared_data / "colmap_bird" / "images").glob("*.jpg"))[:24]
    video = tmp_path / "bird.mp4"
    with imageio.get_writer(video, format="FFMPEG", fps=10, codec="libx264", quality=9, macro_block_size=1) as writer:
        for path in names:
            photo = Image.open(path).convert("RGB")
            writer.append_data(np.asarray(photo))
            writer.append_data(np.asarray(photo.filter(ImageFilter.GaussianBlur(4))))
    out = tmp_path / "scene"
    with pytest.warns(UserWarning, match="960 px on the long side"):
        summary = process(video, out, ProcessOptions(num_frames=24, threads=2, progress=False))
    frames = sorted((out / "images").iterdir())
    assert summary.matcher == "sequential" and summary.images == 24
    assert summary.registered >= 22, summary
    assert frames[0].name == "frame_00001.jpg"
    # Every kept frame is a sharp one: as sharp as the original photo, not the blurred copy (both measured on the
    # undistorted output, which resamples slightly).
    originals = [sharpness(np.asarray(Image.open(p).convert("RGB"))) for p in names]
    blurred = [sharpness(np.asarray(Image.open(p).convert("RGB").filter(ImageFilter.GaussianBlur(4)))) for p in names]
    kept = [sharpness(np.asarray(Image.open(p).convert("RGB"))) for p in frames]
    threshold = 3 * max(blurred)
    assert min(originals) > threshold and min(kept) > threshold, (min(kept), threshold)


def test_photos_of_two_sizes_get_a_camera_each_and_all_register(cup_photos, tmp_path):
    """pycolmap's single camera silently skips the images of any other size than the first."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for i, path in enumerate(sorted(cup_photos.glob("*.jpg"))[:24]):
        image = Image.open(path)
        (image if i % 2 else image.resize((360, 270), Image.Resampling.BOX)).save(photos / path.name, quality=95)
    out = tmp_path / "scene"
    with pytest.warns(UserWarning):
        summary = process(photos, out, ProcessOptions(threads=2, progress=False))
    assert summary.images == 24 and summary.registered >= 20, summary
    assert summary.image_sizes == {"400x300": 12, "360x270": 12}
    assert any(line.startswith("sizes:") and "one camera per size" in line for line in summary.lines())
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    sizes = {model.cameras[image.camera_id].width for image in model.images.values()}
    assert len(model.cameras) == 2 and len(sizes) == 2, "both sizes registered, each under its own camera"
    assert len(load_scene(out).train) > 0


def _left_share(model, masks: Path | None = None) -> tuple[float, float]:
    """Of the observations with a 3D point: the share in the left 40% of their image, and (with the scene's
    masks/) the share on a pixel the image's mask leaves out."""
    left = observed = dropped = 0
    for image in model.images.values():
        width = model.cameras[image.camera_id].width
        keep = None if masks is None else np.asarray(Image.open(masks / f"{Path(image.name).stem}.png"))
        for point in image.points2D:
            if not point.has_point3D():
                continue
            x, y = point.xy
            observed += 1
            left += x < 0.4 * width
            if keep is not None:
                dropped += keep[min(int(y), keep.shape[0] - 1), min(int(x), keep.shape[1] - 1)] == 0
    return left / observed, dropped / observed


def test_masks_keep_sift_off_what_they_leave_out_and_come_with_the_scene(cup_photos, cup_scene, tmp_path):
    """Masks that leave out the left 40% of every photo (inverted: white there): no tie point of the model lies
    there (without the masks a good share does), and the scene gets the masks, undistorted, as masks/."""
    masks = tmp_path / "masks"
    masks.mkdir()
    leave_out = np.zeros(SMALL[::-1], dtype=np.uint8)
    leave_out[:, : int(0.4 * SMALL[0])] = 255
    for path in cup_photos.glob("*.jpg"):
        Image.fromarray(leave_out).save(masks / f"{path.stem}.png")
    out = tmp_path / "scene"
    with pytest.warns(UserWarning):
        summary = process(cup_photos, out, ProcessOptions(threads=2, progress=False, masks=str(masks),
                                                          invert_masks=True))
    assert summary.registered >= 40 and summary.masks == summary.registered, summary
    assert any(line.startswith("masks:") for line in summary.lines())
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    left, dropped = _left_share(model, out / "masks")
    unmasked_left, _ = _left_share(pycolmap.Reconstruction(str(cup_scene[0] / "sparse" / "0")))
    print(f"tie points in the left 40%: {left:.1%} with the masks, {unmasked_left:.1%} without")
    assert unmasked_left > 0.15 and left < 0.02 and dropped < 0.01
    scene = load_scene(out)
    assert all(view.mask is not None and view.mask.shape == view.image.shape[:2] for view in scene.train)
    assert 0.3 < (scene.train[0].mask == 0).float().mean() < 0.5  # the left 40%, through the undistortion
    assert sorted(p.name for p in masks.iterdir()) == sorted(f"{p.stem}.png" for p in cup_photos.glob("*.jpg"))


def test_a_photo_that_does_not_decode_whole_is_left_out_and_named(cup_photos, tmp_path):
    """A truncated JPEG opens and its header reads (Pillow's verify() passes it), but two thirds of its rows are
    flat grey: it is left out before SfM, with a warning that names it, and the scene has no copy of it. So are a
    byte-identical copy of a photo (it would be one view twice: a test view that is trained on) and a .webp photo
    (SfM's reader does not decode it), each with its own reason (issue 58)."""
    photos = copy_photos(cup_photos, tmp_path / "photos", 16)
    broken = sorted(photos.iterdir())[5]
    broken.write_bytes(broken.read_bytes()[: broken.stat().st_size // 3])
    original = sorted(photos.iterdir())[0]
    (photos / "zz_copy.jpg").write_bytes(original.read_bytes())
    Image.open(sorted(photos.iterdir())[1]).save(photos / "webp_photo.webp")
    out = tmp_path / "scene"
    with pytest.warns(UserWarning) as warned:
        summary = process(photos, out, ProcessOptions(threads=2, progress=False))
    left_out = [str(w.message) for w in warned if broken.name in str(w.message)]
    assert left_out and "left out" in left_out[0] and "truncated" in left_out[0], [str(w.message) for w in warned]
    assert "zz_copy.jpg" in left_out[0] and "webp_photo.webp" in left_out[0], left_out[0]
    assert summary.images == 15 and sorted(summary.left_out) == [broken.name, "webp_photo.webp", "zz_copy.jpg"]
    assert f"a byte-identical copy of {original.name}" in summary.left_out["zz_copy.jpg"]
    assert ".webp" in summary.left_out["webp_photo.webp"] and "convert" in summary.left_out["webp_photo.webp"]
    line = next(line for line in summary.lines() if line.startswith("left out:"))
    assert all(name in line for name in summary.left_out), line
    written = json.loads((out / "process.json").read_text())
    assert written["left_out"] == summary.left_out
    for name in summary.left_out:
        assert name not in {p.name for p in (out / "images").iterdir()} and name not in written["files"]


def test_copies_and_other_formats_are_left_out_of_the_photos_and_named(cup_photos, tmp_path):
    """list_photos: the first of byte-identical photos is kept (in name order, sub-folders too), each copy named
    with its original; a photo in another image format is named, never silently skipped; a folder of only those
    says so in its error."""
    from mcsplat.capture.frames import list_photos

    photos = copy_photos(cup_photos, tmp_path / "photos", 4)
    first, second = sorted(p.name for p in photos.iterdir())[:2]
    (photos / "sub").mkdir()
    (photos / "sub" / "again.jpg").write_bytes((photos / second).read_bytes())
    (photos / "z.jpg").write_bytes((photos / first).read_bytes())
    Image.open(photos / first).save(photos / "phone.webp")
    Image.open(photos / first).save(photos / "scan.tif")
    (photos / "notes.txt").write_text("not a photo")
    listed = list_photos(photos)
    assert listed.names == sorted(p.name for p in cup_photos.glob("*.jpg"))[:4]
    assert sorted(listed.left_out) == ["phone.webp", "scan.tif", "sub/again.jpg", "z.jpg"], listed.left_out
    assert listed.left_out["z.jpg"].startswith(f"a byte-identical copy of {first}")
    assert listed.left_out["sub/again.jpg"].startswith(f"a byte-identical copy of {second}")
    assert "convert it to .jpg or .png" in listed.left_out["phone.webp"]
    only_webp = tmp_path / "only_webp"
    only_webp.mkdir()
    Image.open(photos / first).save(only_webp / "a.webp")
    with pytest.raises(MCSplatError, match=r"no images in .*: 1 \.webp file is not read") as info:
        list_photos(only_webp)
    assert "\n" not in str(info.value) and "convert" in str(info.value)


def test_a_flat_frame_is_featureless_not_blurred(cup_photos, tmp_path):
    """A flat grey frame has no sharpness, but it is not blurred: it has nothing to see. It gets its own reason and
    advice; a blurred photo is still blurred, a dark copy still badly exposed (its contrast is the photo's)."""
    from mcsplat.capture.registration import PhotoFigures, by_reason, diagnose, measure, suggestion

    cup = sorted(cup_photos.glob("*.jpg"))
    Image.new("RGB", SMALL, (128, 128, 128)).save(tmp_path / "grey.jpg", quality=95)
    Image.open(cup[6]).filter(ImageFilter.GaussianBlur(6)).save(tmp_path / "blurred.jpg", quality=95)
    dark = (np.asarray(Image.open(cup[7])).astype(np.float32) * 0.06).astype(np.uint8)
    Image.fromarray(dark).save(tmp_path / "dark.jpg", quality=95)

    def figures(path: Path, features: int, matches: int) -> PhotoFigures:
        sharp, bright, contrast = measure(path)
        return PhotoFigures(path.name, features, matches, matches, sharp, bright, camera="400x300",
                            contrast=contrast)

    photos = [figures(path, 400, 80) for path in cup[:6]] + [
        figures(tmp_path / name, 0, 0) for name in ("grey.jpg", "blurred.jpg", "dark.jpg")]
    left_out, medians = diagnose(photos, {path.name for path in cup[:6]})
    reasons = {photo.name: photo for photo in left_out}
    assert reasons["grey.jpg"].reason == "featureless", reasons["grey.jpg"]
    assert "blur" not in reasons["grey.jpg"].other_causes and "contrast" in reasons["grey.jpg"].detail
    assert reasons["blurred.jpg"].reason == "blur" and reasons["dark.jpg"].reason == "exposure"
    assert "featureless" not in reasons["blurred.jpg"].other_causes + reasons["dark.jpg"].other_causes
    assert by_reason([reasons["grey.jpg"]]) == "1 featureless (grey.jpg)"
    advice = suggestion([reasons["grey.jpg"]])
    assert "hold the camera still" not in advice and "lens cap" in advice, advice


def _full_masks(photos: Path, folder: Path) -> Path:
    folder.mkdir()
    for path in photos.glob("*.jpg"):
        Image.new("L", SMALL, 255).save(folder / f"{path.stem}.png")
    return folder


def test_a_broken_or_missing_mask_is_one_line_that_names_it(cup_photos, tmp_path, capsys):
    """A truncated PNG or a text file among the masks: one line naming the file (as `train` gives), no scene; a
    missing mask: a hint that `process` takes (it has no `--masks none`: leave --masks out)."""
    from mcsplat.cli import main

    photos = copy_photos(cup_photos, tmp_path / "photos", 3)
    masks = _full_masks(photos, tmp_path / "masks")
    first, second, _ = sorted(masks.iterdir())
    whole = first.read_bytes()
    first.write_bytes(whole[: len(whole) // 2])
    second.write_text("not a mask\n")
    out = tmp_path / "scene"
    for damaged in (first, second):
        with pytest.warns(UserWarning), pytest.raises(MCSplatError, match=f"cannot decode mask {damaged}") as info:
            process(photos, out, ProcessOptions(threads=1, progress=False, masks=str(masks)))
        assert "\n" not in str(info.value) and "replace the file" in str(info.value)
        assert not out.exists()
        first.write_bytes(whole)
    second.unlink()
    status = main(["process", str(photos), "--out", str(out), "--masks", str(masks), "--threads", "1"])
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert status == 2 and error.startswith("mcsplat: error:") and f"({second.stem}.jpg)" in error, error
    assert "--masks none" not in error and "leave --masks out" in error
    assert not out.exists()


@pytest.fixture(scope="module")
def mixed_photos(cup_photos, shared_data, tmp_path_factory) -> Path:
    """20 cup photos, and mixed in: 2 blurred copies of others, 2 noise images, 1 nearly black copy and 12 photos
    of something else (the bird capture, resized to the cup's size: one camera, so only the content differs)."""
    folder = tmp_path_factory.mktemp("mixed")
    cup = sorted(cup_photos.glob("*.jpg"))
    for path in cup[:20]:
        (folder / path.name).write_bytes(path.read_bytes())
    for path in cup[20:22]:
        Image.open(path).filter(ImageFilter.GaussianBlur(6)).save(folder / f"blurred_{path.name}", quality=95)
    noise = np.random.default_rng(0).integers(0, 256, (2, SMALL[1], SMALL[0], 3), dtype=np.uint8)
    for i, pixels in enumerate(noise):
        Image.fromarray(pixels).save(folder / f"noise_{i}.png")
    dark = (np.asarray(Image.open(cup[22])).astype(np.float32) * 0.06).astype(np.uint8)
    Image.fromarray(dark).save(folder / f"dark_{cup[22].name}", quality=95)
    for path in sorted((shared_data / "colmap_bird" / "images").glob("*.jpg"))[:12]:
        Image.open(path).resize(SMALL, Image.Resampling.BOX).save(folder / f"bird_{path.name}", quality=95)
    return folder


def test_photos_that_do_not_register_are_named_with_their_reasons(mixed_photos, tmp_path):
    """Each mixed-in photo is named with its likeliest reason, in the summary, its lines and process.json; the
    bird photos' own model is reported with its size; the suggestion is the one for the commonest reason."""
    out = tmp_path / "scene"
    with pytest.warns(UserWarning):
        summary = process(mixed_photos, out, ProcessOptions(threads=2, progress=False))
    assert summary.images == 37 and summary.registered >= 15, summary
    reasons = {photo["name"]: photo for photo in summary.not_registered}
    print({name: photo["detail"] for name, photo in reasons.items()})
    assert summary.registered + len(reasons) == summary.images
    registered = {p.name for p in (out / "images").iterdir()}
    assert not registered & set(reasons), "a photo both registered and reported left out"
    expected = {"blurred_": "blur", "noise_": "overlap", "dark_": "exposure", "bird_": "separate model"}
    for prefix, reason in expected.items():
        mixed_in = [p.name for p in mixed_photos.iterdir() if p.name.startswith(prefix)]
        assert mixed_in and all(reasons[name]["reason"] == reason for name in mixed_in), (prefix, reasons)
    assert "too dark" in reasons[next(n for n in reasons if n.startswith("dark_"))]["detail"]
    blurred = reasons[next(n for n in reasons if n.startswith("blurred_"))]
    assert blurred["figures"]["sharpness"] < 0.05 * summary.capture_medians["sharpness"]
    assert all(reasons[name]["figures"]["best_matches_any"] < 15 for name in reasons if name.startswith("noise_"))
    assert summary.other_models == [12], summary  # the bird photos registered among themselves, in a model not kept
    # The cup photos left out are real ones (the first 20 by name do not all overlap): each has a reason too.
    assert all(photo["detail"] for photo in summary.not_registered)
    assert summary.suggestion.startswith("take more photos between the parts")  # 12 of them: the commonest
    lines = summary.lines()
    line = next(line for line in lines if line.startswith("not registered:"))
    assert "12 in a separate model (bird_" in line and "2 blurred (blurred_" in line and "badly exposed (dark_" in line
    assert "other models: 1 (12 photos), not kept" in lines and f"suggestion: {summary.suggestion}" in lines
    written = json.loads((out / "process.json").read_text())
    assert written["not_registered"] == summary.not_registered and written["other_models"] == [12]


def test_min_registered_stops_with_one_line_and_no_scene(mixed_photos, tmp_path, capsys):
    from mcsplat.cli import main

    out = tmp_path / "scene"
    status = main(["process", str(mixed_photos), "--out", str(out), "--threads", "2", "--min-registered", "0.8"])
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert status == 2 and error.startswith("mcsplat: error: only ") and "of 37 photos registered" in error, error
    assert "under --min-registered 0.8" in error and "12 in a separate model" in error and "no scene" in error
    assert not out.exists() and list(tmp_path.iterdir()) == []
    for share in ("0", "1.5"):
        with pytest.raises(MCSplatError, match=f"--min-registered {share}: give the share"):
            process(mixed_photos, out, ProcessOptions(min_registered=float(share), progress=False))


def test_each_cause_is_judged_against_the_registered_photos():
    """The causes SfM's run above does not produce: another camera, a photo that matched but found no pose, one that
    matches only left-out photos; and the figures are held against the registered photos, not the whole capture."""
    from mcsplat.capture.registration import PhotoFigures, by_reason, diagnose, suggestion

    def photo(name, **figures):
        values = dict(features=300, best_matches=80, best_matches_any=80, sharpness=200.0, brightness=120.0,
                      camera="Apple iPhone 15 4032x3024", contrast=0.5)
        return PhotoFigures(name, **{**values, **figures})

    photos = [photo(f"{i}.jpg") for i in range(6)] + [
        photo("zoomed.jpg", camera="Apple iPhone 15 1920x1080", best_matches=5),
        photo("stuck.jpg", best_matches=40),
        photo("elsewhere.jpg", best_matches=3, best_matches_any=60),
        *[photo(f"soft{i}.jpg", sharpness=40.0, best_matches=0) for i in range(2)]]
    registered = {f"{i}.jpg" for i in range(6)}
    left_out, medians = diagnose(photos, registered)
    reasons = {p.name: p for p in left_out}
    assert medians["sharpness"] == 200.0  # the two soft photos do not pull the median down
    assert reasons["zoomed.jpg"].reason == "camera" and reasons["zoomed.jpg"].other_causes == ["overlap"]
    assert "1920x1080, most photos Apple iPhone 15 4032x3024" in reasons["zoomed.jpg"].detail
    assert reasons["stuck.jpg"].reason == "pose" and "40 verified matches" in reasons["stuck.jpg"].detail
    assert reasons["elsewhere.jpg"].reason == "overlap" and "something else" in reasons["elsewhere.jpg"].detail
    assert [reasons[f"soft{i}.jpg"].reason for i in range(2)] == ["blur", "blur"]
    assert suggestion(left_out).startswith("hold the camera still")  # blur: 2 of the 5
    assert by_reason(left_out, shown=1) == ("2 blurred (soft0.jpg and 1 more); 1 from another camera (zoomed.jpg); "
                                            "1 with no pose (stuck.jpg); 1 with no overlap (elsewhere.jpg)")
    assert suggestion([]) == "" and diagnose(photos, set(p.name for p in photos))[0] == []


def test_a_model_is_counted_once_with_the_images_no_larger_model_holds():
    from mcsplat.capture.sfm import distinct_models

    models = [{"a", "b", "c", "d"}, {"x", "y", "z"}, {"a", "b"}, {"c", "w"}]
    assert distinct_models(models) == [{"a", "b", "c", "d"}, {"x", "y", "z"}, {"w"}]
    assert distinct_models([]) == []


def test_too_few_registered_names_the_photos_and_their_reasons(cup_photos, tmp_path):
    """Noise images and two blurred cup photos: no model (or one under 3 images); the one-line error says why."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for i, pixels in enumerate(np.random.default_rng(1).integers(0, 256, (3, SMALL[1], SMALL[0], 3), dtype=np.uint8)):
        Image.fromarray(pixels).save(photos / f"noise_{i}.png")
    for path in sorted(cup_photos.glob("*.jpg"))[:2]:
        Image.open(path).filter(ImageFilter.GaussianBlur(6)).save(photos / f"blurred_{path.name}", quality=95)
    with pytest.warns(UserWarning), pytest.raises(MCSplatError, match="registered only 0 of 5 images") as info:
        process(photos, tmp_path / "scene", ProcessOptions(threads=2, progress=False))
    message = str(info.value)
    assert "\n" not in message and "left out 3 with no overlap (noise_0.png, noise_1.png and 1 more)" in message
    assert "2 blurred (blurred_1.jpg, blurred_10.jpg)" in message, message
    assert not (tmp_path / "scene").exists()
