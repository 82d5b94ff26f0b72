"""Training masks: which pixels of each image the loss learns from and the masked metrics score.

A mask is a greyscale image per photo in the scene's masks/ folder (or the folder --masks names), named after the
photo as Brush and nerfstudio name them (`masks/<view name>.png`, the view name being the image's path without its
suffix, or just `<image stem>.png`) or as COLMAP does (`masks/<image file name>.png`). A nonzero pixel is kept and a
zero pixel left out (--invert-masks swaps the two); --masks alpha takes the images' own alpha channel instead, as a
soft weight. Every image must have one: a missing mask is far more often a misnamed file than a wish.

A mask is a weight, so it follows its image by area (resampling.AREA): undistorted with the image's camera, then
area-averaged to the size the image is loaded at, so that a mask pixel lies on its image pixel. Masks stay in memory
as uint8 [H, W] keep weights (255: kept), a third of the images' size.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from PIL import Image

from .. import images
from .kind import Found, Kind
from .resampling import AREA
from ...compute.device import upload
from ...errors import DataError

MASK_FOLDER = "masks"
NOTE_PREFIX = "masks for"  # how the Scene note on masks starts (the console repeats it when a run starts)


@dataclass(frozen=True)
class MaskOptions:
    """Training masks: the pixels the loss leaves out (--masks, --invert-masks)."""

    masks: str = field(default="auto", metadata={"folder_unless": ("auto", "none", "alpha")})
    """Pixels the loss leaves out: 'auto' takes the scene's masks/ folder when it has one (a PNG per image,
    masks/<image name>.png, black: left out), 'none' ignores it, 'alpha' takes the images' alpha channel, or give a
    folder. Evaluation reports masked PSNR / SSIM beside the plain ones."""
    invert_masks: bool = False
    """Masks are white where the pixel is left out (and black where it is kept)."""

    def __post_init__(self) -> None:
        if not self.masks.strip():
            raise DataError(f"--masks {self.masks!r} names no folder: give 'auto', 'none', 'alpha' or the folder "
                            "that holds one mask PNG per image")
        if self.invert_masks and self.masks == "none":
            raise DataError("--invert-masks with --masks none: there are no masks to invert; leave one of them out")

    def per_view_input(self) -> MaskOptions:
        """What a run's feature seam (features.py) loads beside the photos for it: these options."""
        return self

    @property
    def alpha(self) -> bool:
        return self.masks == "alpha"

    def folder(self, root: Path) -> Path | None:
        """The mask folder to read, or None (no masks, or the alpha channel)."""
        if self.masks in ("none", "alpha"):
            return None
        if self.masks == "auto":
            folder = root / MASK_FOLDER
            return folder if folder.is_dir() else None
        folder = Path(self.masks).expanduser()
        if not folder.is_dir():
            raise DataError(f"--masks {self.masks}: no such folder; give the folder that holds one mask PNG per "
                            "image, or --masks none")
        return folder


class MaskKind(Kind):
    name = "mask"
    label = "mask"
    options = MaskOptions
    resampling = AREA
    default = MaskOptions()  # a scene's masks/ folder is used unless --masks says otherwise

    def find(self, options: MaskOptions, scene: Any) -> Found | None:
        views = scene.train + scene.test
        if options.alpha:
            if not scene.alpha:
                raise DataError(f"--masks alpha: the images of {scene.root} have no alpha channel; give a folder of "
                                "masks or --masks none")
            return Found([view.source.photo for view in views], "the images' alpha channel")
        folder = options.folder(scene.root)
        if folder is None:
            if options.invert_masks:
                raise DataError(f"--invert-masks: {scene.root} has no {MASK_FOLDER}/ folder, so there are no masks to "
                                "invert; give the masks' folder with --masks, or leave --invert-masks out")
            return None
        files = [mask_file(folder, view.name, view.source.photo) for view in views]
        missing = [view.name for view, file in zip(views, files) if file is None]
        if missing:
            raise missing_error(folder, missing, len(views))
        return Found(files, str(folder))

    def decode(self, file: Path, view: Any, options: MaskOptions) -> np.ndarray:
        keep = read_keep(file, options.alpha)
        return 255 - keep if options.invert_masks else keep

    def as_float(self, values: torch.Tensor, device: torch.device | str) -> torch.Tensor:
        return upload(values, device).to(torch.float32).div_(255.0)[:, :, None]

    def check(self, values: Sequence[torch.Tensor | None], found: Found, views: Sequence[Any],
              options: MaskOptions) -> None:
        check_something_kept(values, found, [view.name for view in views], options)

    def note(self, values: Sequence[torch.Tensor | None], found: Found, options: MaskOptions) -> str:
        return describe(values, found.where + (", inverted" if options.invert_masks else ""))


def mask_file(folder: Path, view_name: str, image: Path) -> Path | None:
    """The mask of the image `image` (view `view_name`) in `folder`, under any of the accepted names."""
    candidates = [folder / f"{view_name}.png", folder / f"{image.name}.png", folder / f"{image.stem}.png",
                  folder / image.name]
    candidates += [folder / f"{view_name}{suffix}" for suffix in images.IMAGE_SUFFIXES]
    return next((path for path in candidates if path.is_file()), None)


def missing_error(folder: Path, missing: Sequence[str], total: int, without: str = "give --masks none"
                  ) -> DataError:
    """The error for images without a mask; `without` says how the command goes on without masks."""
    shown = ", ".join(missing[:3]) + (f" and {len(missing) - 3} more" if len(missing) > 3 else "")
    return DataError(f"{folder} has no mask for {len(missing)} of the {total} images ({shown}); add "
                     f"{folder.name}/<image name>.png for each (white: keep, black: leave out), or {without}")


def check_something_kept(keep: Sequence[torch.Tensor | None], found: Found, names: Sequence[str],
                         options: MaskOptions) -> None:
    """Refuse masks that leave out every pixel of their image (as loaded): such a view has nothing to train on or
    to score, and when every view is one, a run would train on its regularisers alone and end as if it had worked."""
    empty = [i for i, mask in enumerate(keep) if mask is not None and not bool(mask.any())]
    if not empty:
        return
    invert = options.invert_masks
    if len(empty) == len(keep):
        fix = ("--invert-masks made them black: run without --invert-masks" if invert else
               "if yours are black where the image is to be kept, add --invert-masks")
        raise DataError(f"every one of the {len(keep)} masks from {found.where}{' (inverted)' if invert else ''} "
                        f"leaves out every pixel of its image, so nothing is left to train on; a mask keeps its white "
                        f"pixels and leaves out the black ones: {fix}")
    first = found.files[empty[0]]
    label = f"the alpha channel of {first}" if options.alpha else f"mask {first}"
    more = f" (and {len(empty) - 1} more: {', '.join(names[i] for i in empty[1:4])}" \
           f"{' ...' if len(empty) > 4 else ''})" if len(empty) > 1 else ""
    raise DataError(f"{label} leaves out every pixel of {names[empty[0]]}{more}, so nothing of that view is left to "
                    "train on or to score; give it a mask that keeps part of it (white: keep), or give --masks none")


def read_keep(source: Path, alpha: bool = False) -> np.ndarray:
    """The keep weights [H, W] of a mask file (nonzero kept) or of an image's alpha channel: uint8, 255 kept; a
    file that is missing or does not decode whole is a one-line DataError naming it."""
    try:
        with Image.open(source) as im:
            if alpha:
                return np.array(im.convert("RGBA"))[:, :, 3]
            return np.where(np.asarray(im.convert("L")) > 0, 255, 0).astype(np.uint8)
    except FileNotFoundError:
        raise DataError(f"mask file is missing: {source}") from None
    except Exception as exc:
        raise DataError(f"cannot decode mask {source}: {images._reason(exc)}; replace the file") from None


def describe(masks: Sequence[torch.Tensor | None], source: str) -> str:
    """The line Scene.notes gets: how many views have a mask and what share of their pixels is left out."""
    present = [mask for mask in masks if mask is not None]
    left_out = sum(float((255 - mask.to(torch.float32)).sum()) for mask in present) / 255.0
    pixels = sum(mask.numel() for mask in present)
    share = 100 * left_out / max(pixels, 1)
    return f"{NOTE_PREFIX} {len(present)} of {len(masks)} images from {source}: {share:.1f}% of their pixels left out"


KIND = MaskKind()
