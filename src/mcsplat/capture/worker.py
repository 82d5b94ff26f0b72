"""The child process of `process`: SfM, then undistortion of the largest model into WORK/scene.

Run as `python -m mcsplat.capture.worker WORK` with WORK/job.json; writes WORK/result.json ({"error": ...} for a
problem the user can fix, {"crash": ...} for any other). A separate process so that Ctrl-C in the parent can stop
pycolmap at any point (child.py).
"""

from __future__ import annotations

import ctypes
import json
import os
import signal
import sys
import time
from dataclasses import asdict
from pathlib import Path

from . import registration
from .masks import write_scene_masks
from .sfm import SfmOptions, describe_cameras, run_sfm, too_few
from ..errors import MCSplatError


def reconstruct(work: Path, folder: Path, names: list[str], sizes: list[tuple[int, int]], from_video: bool,
                options: dict, sift_masks: str | None = None, masks_as_photos: str | None = None) -> dict:
    import pycolmap

    sfm = run_sfm(folder, names, sizes, work,
                  SfmOptions(matcher=options["matcher"], camera_model=options["camera_model"],
                             max_size=options["sfm_max_size"], overlap=options["overlap"], threads=options["threads"],
                             mask_path=sift_masks),
                  from_video, options["progress"])
    start = time.perf_counter()
    report = left_out_report(work, folder, names, sizes, sfm.model_images, options.get("min_registered"),
                             too_few(sfm, len(names)))
    sfm.seconds["report"] = time.perf_counter() - start
    start = time.perf_counter()
    model_dir = work / "model"
    model_dir.mkdir()
    sfm.reconstruction.write_binary(str(model_dir))
    undistorted = work / "undistorted"
    pycolmap.undistort_images(undistorted, model_dir, folder, num_threads=options["threads"] or -1)
    scene = work / "scene"
    (scene / "sparse" / "0").mkdir(parents=True)
    os.replace(undistorted / "images", scene / "images")
    for item in (undistorted / "sparse").iterdir():  # COLMAP writes sparse/*.bin; 3DGS tools expect sparse/0/
        os.replace(item, scene / "sparse" / "0" / item.name)
    masks = 0
    if masks_as_photos is not None:  # the masks through the photos' undistortion, into the scene's masks/
        pycolmap.undistort_images(work / "undistorted_masks", model_dir, masks_as_photos,
                                  num_threads=options["threads"] or -1)
        masks = write_scene_masks(work / "undistorted_masks" / "images", scene / "masks")
    seconds = dict(sfm.seconds, undistortion=time.perf_counter() - start)
    return {"matcher": sfm.matcher, "models": sfm.models, "seconds": seconds,
            "camera": describe_cameras(sfm.reconstruction), "masks": masks, **report}


def left_out_report(work: Path, folder: Path, names: list[str], sizes: list[tuple[int, int]],
                    model_images: list[set[str]], min_registered: float | None, too_few_error: str | None) -> dict:
    """The photos SfM left out with their reasons, the other models' sizes and one suggestion (registration.py);
    one line instead when too few registered for a scene (`too_few_error`) or for `min_registered` (before the
    undistortion's work)."""
    photos = registration.figures_from_database(work / "database.db", folder, names, sizes, model_images)
    left_out, medians = registration.diagnose(photos, model_images[0])
    advice = registration.suggestion(left_out)
    registered = len(model_images[0])
    if too_few_error is not None:
        raise MCSplatError(f"{too_few_error}; left out {registration.by_reason(left_out, shown=2)}")
    if min_registered is not None and registered < min_registered * len(names):
        raise MCSplatError(f"only {registered} of {len(names)} photos registered ({registered / len(names):.0%}, "
                           f"under --min-registered {min_registered:g}): left out "
                           f"{registration.by_reason(left_out, shown=2)}; suggestion: {advice}; no scene was written")
    return {"not_registered": [asdict(photo) for photo in left_out],
            "other_models": [len(model) for model in model_images[1:]], "capture_medians": medians,
            "suggestion": advice}


def end_with_parent(parent: int) -> None:
    """Linux: have the kernel kill this process when its parent dies, however it dies (a parent killed by SIGKILL
    cannot stop it), so that no SfM work goes on for nobody."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # it died before the call above
        os._exit(1)


def main(work: Path) -> None:
    import pycolmap

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C by stopping this process
    job = json.loads((work / "job.json").read_text())
    end_with_parent(job["parent"])
    pycolmap.logging.minloglevel = 1  # COLMAP's per-image INFO lines would bury the progress bars
    try:
        result = reconstruct(work, Path(job["folder"]), job["names"], [tuple(size) for size in job["sizes"]],
                             job["from_video"], job["options"], job.get("sift_masks"), job.get("masks_as_photos"))
    except MCSplatError as error:
        result = {"error": str(error)}
    except Exception as error:  # the parent tells a full disk from the rest (child.py)
        result = {"crash": f"{type(error).__name__}: {' '.join(str(error).split())[:200]}"}
    (work / "result.json").write_text(json.dumps(result))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
