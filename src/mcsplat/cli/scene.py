"""`mcsplat info` and `mcsplat process`: a scene folder read, or made from photos or a video."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from ..capture import ProcessOptions
from ..data.attachments.masks import MaskOptions


@dataclass
class Info:
    """Load a scene folder and print a summary: format, train/test views, image size, SfM points, radius."""

    data: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DATA")]
    """Scene folder: COLMAP (sparse/0 + images/), Blender/NeRF (transforms_*.json) or LLFF (poses_bounds.npy)."""
    downscale: int = 1
    """Load images at 1/N resolution (uses images_N/ when the folder has it)."""
    test_every: int = 8
    """Every N-th view (sorted by name) is held out for testing; 0 = none. Blender test splits are kept as they are."""
    background: Annotated[str, tyro.conf.arg(metavar="COLOR")] = "auto"
    """'white', 'black' or 'r,g,b' in [0, 1]; 'auto' = white when the images have an alpha channel, else black."""
    training_masks: Annotated[MaskOptions, tyro.conf.OmitArgPrefixes] = field(default_factory=MaskOptions)

    def run_command(self) -> int:
        from ..data import load_scene
        from ..initialization import start_without_points

        background = None if self.background.strip().lower() == "auto" else self.background
        scene = load_scene(self.data, downscale=self.downscale, background=background, test_every=self.test_every,
                           masks=self.training_masks)
        print(scene.summary(start=start_without_points(scene)))
        return 0


@dataclass
class Process:
    """Photos or a video to a scene folder that `mcsplat train` loads: pycolmap SIFT features, matching, incremental
    mapping, then undistortion to SCENE/images + SCENE/sparse/0 (PINHOLE). No COLMAP binary needed."""

    input: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="INPUT")]
    """A folder of photos (jpg/png, any names) or a video file (mp4/mov)."""
    out: Path
    """The scene folder to write (created; an existing scene is only replaced with --overwrite)."""
    process: Annotated[ProcessOptions, tyro.conf.OmitArgPrefixes] = field(default_factory=ProcessOptions)

    def run_command(self) -> int:
        from ..capture import process

        print("\n".join(process(self.input, self.out, self.process).lines()))
        return 0


