"""The child process of `process`: SfM, then undistortion of the largest model into WORK/scene.

Run as `python -m mcsplat.capture.worker WORK` with WORK/job.json; writes WORK/result.json ({"error": ...} for a
problem the user can fix). A separate process so that Ctrl-C in the parent can stop pycolmap at any point.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path

from mcsplat.capture.sfm import SfmOptions, describe_cameras, run_sfm
from mcsplat.errors import MCSplatError


def reconstruct(work: Path, folder: Path, names: list[str], sizes: list[tuple[int, int]], from_video: bool,
                options: dict) -> dict:
    import pycolmap

    sfm = run_sfm(folder, names, sizes, work,
                  SfmOptions(matcher=options["matcher"], camera_model=options["camera_model"],
                             max_size=options["sfm_max_size"], overlap=options["overlap"], threads=options["threads"]),
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
    seconds = dict(sfm.seconds, undistortion=time.perf_counter() - start)
    return {"matcher": sfm.matcher, "models": sfm.models, "seconds": seconds,
            "camera": describe_cameras(sfm.reconstruction)}


def main(work: Path) -> None:
    import pycolmap

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C by stopping this process
    pycolmap.logging.minloglevel = 1  # COLMAP's per-image INFO lines would bury the progress bars
    job = json.loads((work / "job.json").read_text())
    try:
        result = reconstruct(work, Path(job["folder"]), job["names"], [tuple(size) for size in job["sizes"]],
                             job["from_video"], job["options"])
    except MCSplatError as error:
        result = {"error": str(error)}
    (work / "result.json").write_text(json.dumps(result))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
