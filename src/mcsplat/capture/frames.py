"""The input of `process`: the photos of a folder, or the sharpest frames of a video written as numbered JPEGs."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from ..data import images, repeats
from ..errors import DataError

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
# Image formats a folder of photos may hold that SfM's reader (pycolmap's) does not take, or that process does not
# hand to it: named as not read, never skipped in silence.
OTHER_IMAGE_SUFFIXES = (".webp", ".heic", ".heif", ".avif", ".jxl", ".gif", ".bmp", ".tif", ".tiff", ".jp2",
                        ".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".orf", ".rw2")
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
BROKEN, COPY = "cannot be decoded whole", "a byte-identical copy of"  # how two of Photos.left_out's reasons begin


@dataclass
class Photos:
    folder: Path
    names: list[str]  # relative to folder, sorted
    sizes: list[tuple[int, int]]
    # name -> why it is not used: it does not decode whole, it is a copy of another photo, or SfM does not read it
    left_out: dict[str, str] = field(default_factory=dict)


def is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def list_photos(folder: Path, workers: int | None = None) -> Photos:
    """The jpg/png files of `folder` (any names, sub-folders included), each decoded whole; one that does not is
    left out (Photos.left_out says why). A truncated JPEG opens and its header reads, but SfM and the scene's copy
    would get its missing rows as flat grey. So are the byte-identical copies of a photo (one view twice: a copy
    could be a test view of a photo that is trained on) and the images of other formats, each named."""
    files = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file() and not p.name.startswith("."))
    names = [name for name in files if Path(name).suffix.lower() in PHOTO_SUFFIXES]
    others = {name: _not_read(name) for name in files if Path(name).suffix.lower() in OTHER_IMAGE_SUFFIXES}
    if not names:
        what = f"{_count_by_suffix(others)} not read (SfM reads .jpg and .png): convert the photos to .jpg or .png" \
            if others else "put the photos (.jpg or .png) in it"
        raise DataError(f"no images in {folder}: {what}, or give a video file")
    workers = workers or min(8, os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="mcsplat-photos") as pool:
        checked = list(pool.map(lambda name: _decoded_size(folder / name), names))
    broken = {name: reason for name, (size, reason) in zip(names, checked) if size is None}
    if len(broken) == len(names):
        name, reason = next(iter(broken.items()))
        raise DataError(f"none of the {len(names)} images in {folder} can be read ({name}: {reason}); replace them "
                        "and run again")
    whole = [(name, size) for name, (size, _) in zip(names, checked) if size is not None]
    kept, copies = repeats.first_copies([folder / name for name, _ in whole])
    left_out = {**{name: f"{BROKEN} ({reason}): replace it to use it" for name, reason in broken.items()},
                **{whole[copy][0]: f"{COPY} {whole[original][0]}: one view twice" for copy, original in copies.items()},
                **others}
    return Photos(folder, [whole[i][0] for i in kept], [whole[i][1] for i in kept], dict(sorted(left_out.items())))


def _not_read(name: str) -> str:
    return f"a {Path(name).suffix.lower()} file, which SfM does not read: convert it to .jpg or .png to use it"


def _count_by_suffix(names: dict[str, str]) -> str:
    """'1 .webp file is' / '3 .heic and 2 .webp files are'."""
    counts: dict[str, int] = {}
    for name in names:
        counts[Path(name).suffix.lower()] = counts.get(Path(name).suffix.lower(), 0) + 1
    kinds = " and ".join(f"{count} {suffix}" for suffix, count in sorted(counts.items()))
    return f"{kinds} file{'s are' if len(names) > 1 else ' is'}"


def _decoded_size(path: Path) -> tuple[tuple[int, int] | None, str]:
    """(width, height) of the image once decoded to its last byte, or (None, why not). A JPEG is decoded at an
    eighth of its size (Pillow's draft): every byte is still read, in a tenth of the time."""
    try:
        with Image.open(path) as im:
            size = im.size
            im.draft(None, (max(1, size[0] // 8), max(1, size[1] // 8)))
            im.load()
        return size, ""
    except Exception as exc:  # UnidentifiedImageError, OSError (truncated), SyntaxError, ValueError ...
        return None, images._reason(exc)


def sharpness(frame: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image, on a copy at most ~640 px wide: higher is sharper."""
    step = max(1, frame.shape[1] // 640)
    grey = frame[::step, ::step].astype(np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    laplacian = (grey[1:-1, :-2] + grey[1:-1, 2:] + grey[:-2, 1:-1] + grey[2:, 1:-1] - 4.0 * grey[1:-1, 1:-1])
    return float(laplacian.var())


def video_frames(video: Path, out_dir: Path, num_frames: int | None, fps: float | None,
                 progress: bool = True) -> Photos:
    """Split the video into windows (one per wanted frame) and write the sharpest frame of each window.

    num_frames: how many frames to keep (default 200 when fps is not given); fps: frames to keep per second.
    """
    import imageio_ffmpeg
    from tqdm import tqdm

    try:
        reader = imageio_ffmpeg.read_frames(str(video))
        meta = next(reader)
    except Exception as exc:
        reason = " ".join(str(exc).split())[:160] or type(exc).__name__
        raise DataError(f"cannot read video {video} ({reason}); give an mp4/mov file that ffmpeg can decode, or a "
                        "folder of photos") from None
    width, height = meta["size"]
    video_fps = float(meta.get("fps") or 30.0)
    total = int(round(float(meta.get("duration") or 0.0) * video_fps))
    try:
        total = max(total, imageio_ffmpeg.count_frames_and_secs(str(video))[0])
    except Exception:  # counting is only for the window size; the reader below is what matters
        pass
    if fps is not None:
        wanted = max(1, int(round(total / video_fps * fps)))
    else:
        wanted = num_frames or 200
    window = max(1.0, total / wanted) if total else 1.0
    out_dir.mkdir(parents=True, exist_ok=True)
    names, best, best_score, current = [], None, -1.0, 0
    digits = max(5, len(str(wanted)))

    def flush() -> None:
        nonlocal best, best_score
        if best is not None:
            name = f"frame_{len(names) + 1:0{digits}d}.jpg"  # zero-padded: sequential matching follows name order
            Image.fromarray(best).save(out_dir / name, quality=95)
            names.append(name)
        best, best_score = None, -1.0

    count = 0
    try:
        with tqdm(total=total or None, desc="frames", unit="frame", disable=not progress, leave=False) as bar:
            for raw in reader:
                frame = np.frombuffer(raw, dtype=np.uint8).reshape(height, width, 3)
                index = int(count / window)
                if index != current:
                    flush()
                    current = index
                score = sharpness(frame)
                if score > best_score:
                    best, best_score = frame.copy(), score
                count += 1
                bar.update(1)
            flush()
    except Exception as exc:
        if isinstance(exc, DataError):
            raise
        reason = " ".join(str(exc).split())[:160] or type(exc).__name__
        raise DataError(f"cannot decode video {video} after {count} frames ({reason}); re-encode it (e.g. ffmpeg "
                        "-i in.mov out.mp4) or give a folder of photos") from None
    finally:
        reader.close()
    if not names:
        raise DataError(f"video {video} has no frames that can be decoded")
    return Photos(out_dir, names, [(width, height)] * len(names))
