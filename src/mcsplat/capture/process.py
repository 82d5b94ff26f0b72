"""Photos or a video in, a scene folder out: SCENE/images + SCENE/sparse/0 (undistorted, PINHOLE).

Everything is built in a hidden folder beside SCENE and moved into place by one rename at the end, so an interrupted
or failed run leaves no half-written scene that `mcsplat train` would load as if it were complete.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import tempfile
import time
import warnings
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tyro

from . import frames
from . import masks as capture_masks
from .child import run_worker, terminate_as_interrupt
from .registration import LeftOut, by_reason
from .sfm import Matcher, describe_cameras
from ..errors import MCSplatError
from ..io.disk import writing_into

MIN_SFM_SIZE = 1000  # long side in pixels under which SIFT starts to fragment the model (the cup at 200x150 did)
SCENE_MARKERS = ("images", "sparse", "transforms.json", "transforms_train.json", "poses_bounds.npy")
MANIFEST = "process.json"  # the summary of the run that made the scene, with the files it wrote
SHOWN_LEFT_OUT = 5  # input photos not used that the summary names (process.json has them all)
# Disk space the work takes, roughly (the undistorted copies and a video's frames; the features' database): what
# the error of a full disk says is needed.
SPACE_PER_INPUT_BYTE, SPACE_PER_IMAGE = 3, 100_000


@dataclass(frozen=True)
class ProcessOptions:
    """How the photos or the video become a scene."""

    matcher: Matcher = "auto"
    """auto: sequential for a video's frames, exhaustive for photos."""
    camera_model: Literal["SIMPLE_RADIAL", "RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE"] = "SIMPLE_RADIAL"
    """Lens model estimated by SfM, one camera shared by all images (SIMPLE_RADIAL: COLMAP's default, steadier than
    OPENCV on few or small images)."""
    sfm_max_size: int = 1600
    """SIFT runs on images shrunk to at most this many pixels on the long side (the scene keeps full size)."""
    num_frames: int | None = None
    """Video: how many frames to keep, the sharpest of each stretch (default 200)."""
    fps: float | None = None
    """Video: frames to keep per second of video, instead of --num-frames."""
    overlap: Annotated[int, tyro.conf.Suppress] = 15  # sequential matching: each frame against this many after it
    threads: int | None = None
    """CPU threads for pycolmap (default: all cores)."""
    overwrite: bool = False
    progress: Annotated[bool, tyro.conf.Suppress] = True
    masks: str | None = None  # a str: the options travel to the SfM worker as JSON
    """Photos only: a folder of masks (<photo name>.png, black: leave out, as `mcsplat train --masks`): SIFT finds no
    features where they leave out (people, sky, the operator), and the scene gets them, undistorted, as masks/."""
    invert_masks: bool = False
    """The masks are white where the photo is to be left out."""
    min_registered: float | None = None
    """Stop, writing no scene, when fewer than this share of the photos register (0.8: four in five); which photos
    were left out and why is printed (and written to process.json) either way."""

    def __post_init__(self) -> None:
        if self.num_frames is not None and self.num_frames < 3 or \
                self.fps is not None and not (self.fps > 0 and math.isfinite(self.fps)):
            raise MCSplatError("--num-frames must be at least 3 and --fps a positive finite number")
        if self.invert_masks and self.masks is None:
            raise MCSplatError("--invert-masks without --masks: there are no masks to invert; give the masks' folder "
                               "with --masks, or leave --invert-masks out")


@dataclass
class ProcessSummary:
    scene: str
    input: str
    registered: int
    images: int
    points: int
    mean_reprojection_error: float
    matcher: str
    models: int
    camera: str
    undistorted_camera: str
    image_sizes: dict[str, int] = field(default_factory=dict)  # "WxH" -> how many input images have that size
    seconds: dict[str, float] = field(default_factory=dict)
    masks: int = 0  # masks written to the scene's masks/ (with --masks)
    # The input photos not used, each with why (frames.Photos.left_out): broken, a copy of another, not read by SfM.
    left_out: dict[str, str] = field(default_factory=dict)
    # The photos SfM did not register, each with its likeliest reason and figures (registration.LeftOut), the
    # sizes of the models not kept, the capture's median figures, and one suggestion for the commonest reason.
    not_registered: list[dict] = field(default_factory=list)
    other_models: list[int] = field(default_factory=list)
    capture_medians: dict[str, float] = field(default_factory=dict)
    suggestion: str = ""

    def lines(self) -> list[str]:
        stages = ", ".join(f"{name} {value:.1f} s" for name, value in self.seconds.items())
        sizes = ", ".join(f"{count} at {size}" for size, count in self.image_sizes.items())
        return [f"registered: {self.registered} of {self.images} images ({self.models} model"
                f"{'s' if self.models != 1 else ''} found, the largest kept; {self.matcher} matching)",
                *([f"sizes:      the images come in {len(self.image_sizes)} sizes ({sizes}): one camera per size"]
                  if len(self.image_sizes) > 1 else []),
                *([f"left out:   {_named_with_reasons(self.left_out, SHOWN_LEFT_OUT)}"] if self.left_out else []),
                *self._not_registered_lines(),
                f"points:     {self.points:,}, mean reprojection error {self.mean_reprojection_error:.2f} px",
                f"camera:     {self.camera} -> {self.undistorted_camera}",
                *([f"masks:      used by SIFT, and undistorted into masks/ ({self.masks}) for training"]
                  if self.masks else []),
                f"time:       {stages} (total {sum(self.seconds.values()):.1f} s)",
                f"wrote:      {self.scene} (images/ + sparse/0/); next: mcsplat train {self.scene}"]

    def _not_registered_lines(self) -> list[str]:
        if not self.not_registered:
            return []
        left_out = [LeftOut(**photo) for photo in self.not_registered]
        models = ", ".join(str(size) for size in self.other_models)
        return [f"not registered: {by_reason(left_out)} (each photo's reason and figures in {MANIFEST})",
                *([f"other models: {len(self.other_models)} ({models} photos), not kept"] if self.other_models
                  else []),
                f"suggestion: {self.suggestion}"]


def process(source: str | os.PathLike, out: str | os.PathLike, options: ProcessOptions | None = None
            ) -> ProcessSummary:
    options = options or ProcessOptions()
    source, out = Path(source).expanduser().resolve(), Path(out).expanduser().resolve()
    if not source.exists():
        raise MCSplatError(f"input {source} does not exist: give a folder of photos or a video file")
    from_video = frames.is_video(source)
    if not from_video and not source.is_dir():
        raise MCSplatError(f"input {source} is neither a folder of photos nor a video "
                           f"({', '.join(frames.VIDEO_SUFFIXES)})")
    if source.is_dir() and (out == source or out.is_relative_to(source)):
        raise MCSplatError(f"--out {out} is inside the input folder {source}; write the scene somewhere else")
    if source.is_relative_to(out):  # --overwrite would replace the folder that holds the input
        raise MCSplatError(f"the input {source} is inside --out {out}; write the scene to another folder")
    if options.min_registered is not None and not 0 < options.min_registered <= 1:
        raise MCSplatError(f"--min-registered {options.min_registered:g}: give the share of the photos that must "
                           "register, above 0 and at most 1 (0.8: four in five)")
    _check_output(out, options.overwrite)
    if from_video and options.masks is not None:
        raise MCSplatError("--masks needs a folder of photos (the frames taken from a video have no masks named "
                           "after them); extract the frames first, or leave --masks out")
    photos = None if from_video else frames.list_photos(source)  # fail on a bad input before any work
    if photos is not None and photos.left_out:
        warnings.warn(_left_out_warning(photos.left_out), stacklevel=2)
    needed = _space_needed(source, photos, options)
    with writing_into(out.parent, needed):
        out.parent.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, [])  # as it is now: _move_into_place blocks the signals
    import pycolmap  # noqa: F401  (before our handlers: importing it installs glog's, which dumps a stack on SIGTERM)

    with terminate_as_interrupt():
        try:
            with writing_into(out.parent, needed):
                return _process(source, out, work, photos, from_video, options, needed)
        except KeyboardInterrupt:  # while reading the video (the SfM child handles its own)
            raise MCSplatError("interrupted: no scene was written (the partial work is removed)") from None
        finally:
            shutil.rmtree(work, ignore_errors=True)
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # a signal held back during the move arrives now


def _left_out_warning(left_out: dict[str, str]) -> str:
    return (f"left out {len(left_out)} image{'s' if len(left_out) > 1 else ''} of the input: "
            f"{_named_with_reasons(left_out, 3)}")


def _named_with_reasons(left_out: dict[str, str], shown: int) -> str:
    """'a.jpg (why); b.webp (why) and 2 more (all in process.json)'."""
    named = "; ".join(f"{name} ({reason})" for name, reason in list(left_out.items())[:shown])
    return named + (f" and {len(left_out) - shown} more (all in {MANIFEST})" if len(left_out) > shown else "")


def _space_needed(source: Path, photos: frames.Photos | None, options: ProcessOptions) -> int:
    if photos is None:  # a video: its kept frames come to about its own size
        return SPACE_PER_INPUT_BYTE * source.stat().st_size + SPACE_PER_IMAGE * (options.num_frames or 200)
    return (SPACE_PER_INPUT_BYTE * sum((photos.folder / name).stat().st_size for name in photos.names)
            + SPACE_PER_IMAGE * len(photos.names))


def _check_output(out: Path, overwrite: bool) -> None:
    if not out.exists():
        return
    if not out.is_dir():
        raise MCSplatError(f"--out {out} is a file; give a folder for the scene")
    entries = [p.name for p in out.iterdir()]
    if not entries:
        return
    holds_scene = any(name in SCENE_MARKERS for name in entries)
    if holds_scene and not overwrite:
        raise MCSplatError(f"--out {out} already holds a scene; choose another folder or add --overwrite to "
                           "replace it")
    if not holds_scene:
        raise MCSplatError(f"--out {out} is not empty and holds no scene ({', '.join(sorted(entries)[:3])} ...); "
                           "give a new or empty folder")
    if not (out / MANIFEST).is_file():
        raise MCSplatError(f"--overwrite: {out} holds a scene that mcsplat process did not make (it has no "
                           f"{MANIFEST}), and --overwrite replaces only those; choose another folder")
    foreign = files_not_written_by_process(out)
    if foreign:
        raise MCSplatError(f"--overwrite: {out} holds files that mcsplat process did not write "
                           f"({', '.join(foreign[:3])}{' ...' if len(foreign) > 3 else ''}), which replacing it would "
                           "delete; move them out of it, or choose another folder")


def files_in(folder: Path) -> list[str]:
    """Every file below `folder`, as sorted paths relative to it."""
    return sorted(str(path.relative_to(folder)) for path in folder.rglob("*") if not path.is_dir())


def files_not_written_by_process(scene: Path) -> list[str]:
    """The files of `scene` that its MANIFEST does not list (all of them for a scene that process did not make)."""
    try:
        written = set(json.loads((scene / MANIFEST).read_text()).get("files", []))
    except (OSError, ValueError, AttributeError):
        written = set()
    return [name for name in files_in(scene) if name not in written]


def _process(source: Path, out: Path, work: Path, photos, from_video: bool, options: ProcessOptions,
             space_needed: int) -> ProcessSummary:
    import pycolmap

    seconds: dict[str, float] = {}
    if from_video:
        start = time.perf_counter()
        photos = frames.video_frames(source, work / "frames", options.num_frames, options.fps, options.progress)
        seconds["frames"] = time.perf_counter() - start
    long_side = min(max(size) for size in photos.sizes)
    if long_side < MIN_SFM_SIZE:
        warnings.warn(f"some images are only {long_side} px on the long side; SIFT works best at "
                      f"{MIN_SFM_SIZE}-{options.sfm_max_size} px and may register fewer images", stacklevel=3)
    if len(photos.names) < 3:
        raise MCSplatError(f"{len(photos.names)} image(s) in {source}: structure from motion needs at least 3 "
                           "overlapping views (20 or more for a good scene)")
    job = {"folder": str(photos.folder), "names": photos.names, "sizes": photos.sizes, "from_video": from_video,
           "options": asdict(options)}
    if options.masks is not None:
        sift, as_photos = capture_masks.prepare(Path(options.masks).expanduser(), photos.folder, photos.names,
                                                photos.sizes, options.invert_masks, work)
        job.update(sift_masks=str(sift), masks_as_photos=str(as_photos))
    result = run_worker(work, job, space_needed)
    seconds.update(result["seconds"])

    scene = work / "scene"
    model = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    summary = ProcessSummary(
        scene=str(out), input=str(source), registered=model.num_reg_images(), images=len(photos.names),
        points=model.num_points3D(), mean_reprojection_error=float(model.compute_mean_reprojection_error()),
        matcher=result["matcher"], models=result["models"], camera=result["camera"],
        undistorted_camera=describe_cameras(model), image_sizes=_count_sizes(photos.sizes),
        seconds={k: round(v, 2) for k, v in seconds.items()}, masks=result.get("masks", 0),
        left_out=dict(photos.left_out), not_registered=result["not_registered"],
        other_models=result["other_models"], capture_medians=result["capture_medians"],
        suggestion=result["suggestion"])
    # The summary, and the list of the files written: --overwrite replaces the scene only while that is all it holds.
    files = sorted(files_in(scene) + [MANIFEST])
    (scene / MANIFEST).write_text(json.dumps({**asdict(summary), "files": files}, indent=2) + "\n")
    _move_into_place(scene, out, work)
    return summary


def _count_sizes(sizes: list[tuple[int, int]]) -> dict[str, int]:
    """"WxH" -> how many images have that size, the most common first."""
    return dict(Counter(f"{width}x{height}" for width, height in sizes).most_common())


def _move_into_place(scene: Path, out: Path, work: Path) -> None:
    """One rename makes the scene appear complete; an old scene (--overwrite) is moved aside first, then removed.

    No signal may stop it between the two renames (the old scene aside, the new one not yet in place, both in the
    work folder that is removed next): they are held back until process() has finished."""
    signal.pthread_sigmask(signal.SIG_BLOCK, [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
    if out.exists() and not any(out.iterdir()):
        out.rmdir()
    old = None
    if out.exists():
        old = work / "replaced"
        os.replace(out, old)
    os.replace(scene, out)
