"""load_scene: find the format of a scene folder and hand it to its loader."""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Sequence

from . import blender, colmap, idr, llff
from .attachments import MaskOptions, attach, with_defaults
from .scene import NAMED_BACKGROUNDS, Scene, check_options, parse_background
from ..errors import DataError

LOOKED_FOR = ("sparse/0/ or sparse/ with cameras, images, points3D .bin/.txt (COLMAP), transforms_train.json or "
              "transforms.json (Blender/NeRF), poses_bounds.npy (LLFF), cameras.npz (IDR, NeuS, MonoSDF)")


def detect_kind(root: Path) -> str:
    """"colmap", "blender", "llff" or "idr" (in that order of priority); DataError if the folder holds none."""
    if colmap.find_model(root) is not None:
        return "colmap"
    if blender.is_blender(root):
        return "blender"
    if llff.is_llff(root):
        return "llff"
    if idr.is_idr(root):
        return "idr"
    partial = colmap.incomplete_model(root)
    raise DataError(f"no scene found in {root}: looked for {LOOKED_FOR}" + (f"; {partial}" if partial else ""))


def load_scene(path: str | os.PathLike, downscale: int = 1, background: str | Sequence[float] | None = None,
               test_every: int = 8, masks: MaskOptions | None = None, attachments: Sequence[object] = ()) -> Scene:
    """Load a COLMAP, Blender/NeRF, LLFF or IDR (cameras.npz) scene folder (auto-detected).

    downscale: load images at 1/N resolution (images_N/ when the folder has it, else resized); K follows.
    background: "white", "black" or an RGB triple in [0, 1]; default white when the images have an alpha channel
        (NeRF-Synthetic's convention), black otherwise. Images with an alpha channel are composited on it.
    test_every: every N-th view (sorted by name, starting with the first) is a test view; 0 = none. Blender scenes
        with transforms_test.json (or _val) keep their own split.
    masks: where the training masks come from (data/attachments/masks.py); default: the scene's masks/ folder when
        it has one.
    attachments: the options of the other per-view inputs to find beside the photos (data/attachments/), such as
        DepthOptions(); a kind the scene has no files of is left out (a mask may be asked for here too).
    Raises mcsplat.errors.DataError (one line: the file and what is wrong) for any problem with the data.
    """
    downscale, test_every = check_options(downscale, test_every)
    # Checked before the data is read: a request for no kind, or two for one, is the caller's mistake, not the data's.
    requests = with_defaults([*([masks] if masks is not None else []), *attachments])
    root = Path(path).expanduser()
    if not root.exists():
        raise DataError(f"scene folder {root} does not exist")
    if not root.is_dir():
        raise DataError(f"{root} is not a folder; give the scene folder (the one that holds sparse/, "
                        "transforms_*.json or poses_bounds.npy)")
    kind = detect_kind(root)
    rgb = None if background is None else parse_background(background, NAMED_BACKGROUNDS["black"])
    loader = {"colmap": colmap.load_colmap, "blender": blender.load_blender, "llff": llff.load_llff,
              "idr": idr.load_idr}[kind]
    try:
        scene = loader(root, downscale, rgb, test_every)
        attach(scene, requests)  # after the loader, which knows nothing of them
    except DataError:
        raise
    except (OSError, ValueError, KeyError, IndexError, TypeError, struct.error) as exc:
        # A case the checks above did not foresee: still one line, with the cause chained for debugging.
        reason = " ".join(str(exc).split())[:200]
        raise DataError(f"cannot load the {kind} scene in {root}: {type(exc).__name__}: {reason}") from exc
    scene.root = root.resolve()
    return scene
