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
from pathlib import Path

from mcsplat.capture.masks import write_scene_masks
from mcsplat.capture.sfm import SfmOptions, describe_cameras, run_sfm
from mcsplat.errors import MCSplatError


def reconstruct(work: Path, folder: Path, names: list[str], sizes: list[tuple[int, int]], from_video: bool,
                options: dict, sift_masks: str | None = None, masks_as_photos: str | None = None) -> dict:
    import pycolmap

    sfm = run_sfm(folder, names, sizes, work,
                  SfmOptions(matcher=options["matcher"], camera_model=options["camera_model"],
                             max_size=options["sfm_max_size"], overlap=options["overlap"], threads=options["threads"],
                             mask_path=sift_masks),
                  from_video, options["progress"])
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
            "camera": describe_cameras(sfm.reconstruction), "masks": masks}


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
