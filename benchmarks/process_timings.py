"""`mcsplat process` at full resolution on the shared real captures: seconds per stage, registered images, and
agreement with the capture's own COLMAP model. One JSON line per input.

    .venv/bin/python benchmarks/process_timings.py                     # cup photos (77 x 800x600) and bird video
    .venv/bin/python benchmarks/process_timings.py --inputs cup --threads 2

cup: the 77 photos as they are (800x600), exhaustive matching. bird: the 184 phone photos (544x960) written to an
mp4 at 30 fps (a 6 s "phone video", libx264), then the video path: frame selection, sequential matching.
The rotation / centre errors come from pycolmap.compare_reconstructions against the shared sparse/0 model
(alignment by camera centres); the centre error is in the reference model's units.
"""

from __future__ import annotations

import json
import os
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro

from _common import DATA_ROOT


@dataclass(frozen=True)
class Options:
    """`mcsplat process` at full resolution on the shared real captures."""

    inputs: tuple[Literal["cup", "bird"], ...] = ("cup", "bird")
    """cup: the photos; bird: the photos written to a video."""
    threads: int | None = None
    """pycolmap threads (default: all cores)."""
    keep: Path | None = None
    """Write the scenes under this folder and keep them."""


def bird_video(folder: Path) -> Path:
    import imageio.v2 as imageio
    import numpy as np
    from PIL import Image

    video = folder / "bird.mp4"
    with imageio.get_writer(video, format="FFMPEG", fps=30, codec="libx264", quality=9, macro_block_size=1) as out:
        for path in sorted((DATA_ROOT / "colmap_bird" / "images").glob("*.jpg")):
            out.append_data(np.asarray(Image.open(path).convert("RGB")))
    return video


def main() -> None:
    args = tyro.cli(Options, description=__doc__)

    import pycolmap

    from mcsplat.capture import ProcessOptions, process

    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        for name in args.inputs:
            source = DATA_ROOT / "colmap_cup" / "images" if name == "cup" else bird_video(Path(tmp))
            out = root / f"{name}_scene"
            start = time.perf_counter()
            summary = process(source, out, ProcessOptions(threads=args.threads, overwrite=True, progress=False))
            wall = time.perf_counter() - start
            reference = pycolmap.Reconstruction(str(DATA_ROOT / f"colmap_{name}" / "sparse" / "0"))
            ours = pycolmap.Reconstruction(str(out / "sparse" / "0"))
            if name == "bird":  # frames are renamed frame_00001.jpg ...: map them back to 001.jpg ...
                for image in ours.images.values():
                    image.name = f"{int(image.name.split('_')[1].split('.')[0]):03d}.jpg"
            errors = pycolmap.compare_reconstructions(ours, reference, alignment_error="proj_center")
            rotation = [e.rotation_error_deg for e in errors["errors"]] if errors else []
            centre = [e.proj_center_error for e in errors["errors"]] if errors else []
            print(json.dumps({
                "input": name, "registered": summary.registered, "images": summary.images,
                "points": summary.points, "mean_reprojection_error_px": round(summary.mean_reprojection_error, 3),
                "matcher": summary.matcher, "camera": summary.camera, "undistorted": summary.undistorted_camera,
                "seconds": summary.seconds, "wall_seconds": round(wall, 1), "threads": args.threads or os.cpu_count(),
                "compared_images": len(rotation),
                "median_rotation_error_deg": round(statistics.median(rotation), 3) if rotation else None,
                "max_rotation_error_deg": round(max(rotation), 3) if rotation else None,
                "median_centre_error": round(statistics.median(centre), 4) if centre else None}), flush=True)


if __name__ == "__main__":
    main()
