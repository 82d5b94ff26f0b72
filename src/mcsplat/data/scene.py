"""The loaded scene: views (camera + image) split into train and test, SfM points, normalisation radius."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import torch

from ..camera import Camera
from ..compute.device import upload
from .image_store import LazyImage
from ..errors import MCSplatError

if TYPE_CHECKING:
    from .attachments.kind import Attachment

KINDS = ("colmap", "blender", "llff", "idr")

Background = tuple[float, float, float]
NAMED_BACKGROUNDS: dict[str, Background] = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


@dataclass(frozen=True)
class ImageSource:
    """Where a view's pixels came from, for what must line up with them (data/attachments/): the photo as the scene
    holds it, the size the undistortion started from (the distorted camera's; for a pinhole camera the loaded
    size), that undistortion (a data.undistort.Job, or None) and the scene units per unit of the capture (a loader
    that rescales the world says so: IDR's scale_mat)."""

    photo: Path
    before_undistortion: tuple[int, int]
    undistort: object | None = None
    units: float = 1.0


class View:
    """One image with the camera that took it. `image` is uint8 [H, W, 3] on the CPU; convert when used.

    The pixels are either a tensor or a LazyImage (decoded on demand from the scene's ImageStore); `image` returns
    the tensor in both cases, and `prefetch()` asks for it ahead of time. `attachments` holds the per-view inputs
    found beside the photo (data/attachments/: a mask, a depth map), by kind, each at the image's size.
    """

    __slots__ = ("camera", "name", "_image", "source", "attachments")

    def __init__(self, camera: Camera, image: "torch.Tensor | LazyImage", name: str,
                 source: ImageSource | None = None, attachments: "dict[str, Attachment] | None" = None):
        self.camera, self.name, self._image, self.source = camera, name, image, source
        self.attachments = dict(attachments or {})

    @property
    def image(self) -> torch.Tensor:
        return self._image if isinstance(self._image, torch.Tensor) else self._image.get()

    def prefetch(self) -> None:
        if not isinstance(self._image, torch.Tensor):
            self._image.prefetch()

    @property
    def image_file(self) -> Path | None:
        """The file the pixels are decoded from (the undistorted copy in the cache for a distorted camera), or None
        for an image given as a tensor."""
        return None if isinstance(self._image, torch.Tensor) else self._image.path

    def image_float(self, device: torch.device | str = "cpu", size: tuple[int, int] | None = None) -> torch.Tensor:
        """The image as float32 [H, W, 3] in [0, 1] on `device` (the uint8 tensor is moved first, then converted);
        with `size` (width, height) smaller than the image, area-averaged down to it on the device."""
        image = upload(self.image, device).to(torch.float32).div_(255.0)
        if size is None or tuple(size) == (image.shape[1], image.shape[0]):
            return image
        chw = torch.nn.functional.interpolate(image.permute(2, 0, 1)[None], size=(size[1], size[0]), mode="area")
        return chw[0].permute(1, 2, 0).contiguous()

    def attachment(self, kind: str, device: torch.device | str = "cpu", size: tuple[int, int] | None = None
                   ) -> torch.Tensor | None:
        """The view's input of `kind` (a key of data.attachments.KINDS) as float32 [H, W, 1] on `device`, resampled
        to `size` (width, height) as its kind says (a mask by area, as image_float; a depth by nearest), or None
        for a view without one."""
        attached = self.attachments.get(kind)
        if attached is None:
            from .attachments.registry import KINDS

            if kind not in KINDS:  # a misspelt kind would otherwise read as "this view has none"
                raise KeyError(f"no attachment kind {kind!r}: the kinds are {', '.join(KINDS)}")
            return None
        return attached.at(device, size)

    @property
    def mask(self) -> torch.Tensor | None:
        """The uint8 [H, W] keep weight of each pixel in the loss (255 kept, 0 left out), or None."""
        attached = self.attachments.get("mask")
        return None if attached is None else attached.values

    def mask_float(self, device: torch.device | str = "cpu", size: tuple[int, int] | None = None
                   ) -> torch.Tensor | None:
        """The mask as float32 [H, W, 1] keep weights in [0, 1] (area-averaged to `size` as image_float is), or
        None for a view without one."""
        return self.attachment("mask", device, size)

    def camera_at(self, scale: float) -> Camera:
        """The view's camera for its image shrunk to `scale` of its size (at least one pixel a side)."""
        if scale >= 1.0:
            return self.camera
        width, height = self.camera.width, self.camera.height
        return self.camera.scaled(max(1, round(width * scale)), max(1, round(height * scale)))

    def __repr__(self) -> str:
        return f"View(name={self.name!r}, {self.camera.width}x{self.camera.height})"


@dataclass
class Scene:
    """Everything the trainer needs from a scene folder."""

    train: list[View]
    test: list[View]
    points: torch.Tensor | None
    point_colors: torch.Tensor | None
    radius: float
    background: Background
    kind: str
    root: Path
    notes: list[str] = field(default_factory=list)
    """Extra human-readable facts the loader found worth reporting (e.g. which image folder it used)."""
    alpha: bool = False
    """The images carry an alpha channel: a synthetic object on a transparent background (NeRF-Synthetic)."""

    @property
    def centre(self) -> torch.Tensor:
        """[3] float64: the mean of the training cameras' centres, around which `radius` is measured."""
        return camera_centre([view.camera for view in self.train])

    @property
    def train_image_pixels(self) -> int:
        """The median pixel count of the training images (0 without any)."""
        pixels = sorted(v.camera.width * v.camera.height for v in self.train)
        return pixels[len(pixels) // 2] if pixels else 0

    @property
    def object_centric(self) -> bool:
        """Normalised around one object: a synthetic Blender scene in [-1.3, 1.3]^3, or IDR's unit sphere (where
        a random initialisation fills that box rather than a cube of scene radii)."""
        return self.kind == "idr" or (self.kind == "blender" and self.alpha)

    def summary(self, start: str | None = None) -> str:
        """A few human lines: kind, counts, image size, points, radius. `start` says what a scene without points
        starts training from (the loader cannot know: initialization/ decides)."""
        views = self.train + self.test
        sizes = sorted({(v.camera.width, v.camera.height) for v in views})
        if len(sizes) == 1:
            size = f"{sizes[0][0]}x{sizes[0][1]}"
        else:
            size = f"{len(sizes)} sizes, from {sizes[0][0]}x{sizes[0][1]} to {sizes[-1][0]}x{sizes[-1][1]}"
        focal = [v.camera.fx for v in views]
        megabytes = sum(v.camera.width * v.camera.height * 3 for v in views) / 2**20
        points = f"{self.points.shape[0]:,}" if self.points is not None else f"none; {start}" if start else "none"
        lines = [
            f"scene:      {self.root} ({self.kind})",
            f"views:      {len(self.train)} train, {len(self.test)} test",
            f"images:     {size}, focal {min(focal):.1f}-{max(focal):.1f} px, {megabytes:.1f} MiB as uint8",
            f"points:     {points}",
            f"radius:     {self.radius:.4g}",
            f"background: {_format_rgb(self.background)}",
        ]
        lines += [f"note:       {n}" for n in self.notes]
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"Scene(kind={self.kind!r}, root={str(self.root)!r}, train={len(self.train)}, test={len(self.test)}, "
                f"points={None if self.points is None else self.points.shape[0]}, radius={self.radius:.4g})")


def _format_rgb(rgb: Background) -> str:
    for name, value in NAMED_BACKGROUNDS.items():
        if tuple(rgb) == value:
            return name
    return "(" + ", ".join(f"{c:.3g}" for c in rgb) + ")"


def parse_background(background: str | Sequence[float] | None, default: Background) -> Background:
    """`None` -> default; "white" / "black"; or three floats in [0, 1]."""
    if background is None:
        return default
    if isinstance(background, str):
        key = background.strip().lower()
        if key in NAMED_BACKGROUNDS:
            return NAMED_BACKGROUNDS[key]
        parts = key.replace(",", " ").split()
        if len(parts) != 3:
            raise MCSplatError(f"background {background!r} is not understood: use 'white', 'black' or three numbers "
                               "in [0, 1] such as '0.5,0.5,0.5'")
        background = parts
    try:
        rgb = tuple(float(c) for c in background)
    except (TypeError, ValueError):
        raise MCSplatError(f"background {background!r} is not understood: use 'white', 'black' or three numbers in "
                           "[0, 1]") from None
    if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):
        raise MCSplatError(f"background {background!r} must be three numbers in [0, 1] (red, green, blue)")
    return rgb  # type: ignore[return-value]


def check_options(downscale: object, test_every: object) -> tuple[int, int]:
    """Validate the integer options of load_scene; returns them as ints."""
    if isinstance(downscale, bool) or not isinstance(downscale, int) or downscale < 1:
        raise MCSplatError(f"downscale must be an integer >= 1 (1 = full resolution), got {downscale!r}")
    if isinstance(test_every, bool) or not isinstance(test_every, int) or test_every < 0:
        raise MCSplatError(f"test_every must be an integer >= 0 (0 = no test views), got {test_every!r}")
    return downscale, test_every


def split_every(items: list, test_every: int) -> tuple[list, list]:
    """Every `test_every`-th item (index 0, N, 2N, ...) goes to test, the rest to train (the 3DGS `llffhold`)."""
    if test_every <= 0:
        return list(items), []
    train = [x for i, x in enumerate(items) if i % test_every != 0]
    test = [x for i, x in enumerate(items) if i % test_every == 0]
    return train, test


def camera_centre(cameras: Sequence[Camera]) -> torch.Tensor:
    """[3] float64: the mean of the cameras' centres (the origin when there are none)."""
    if not cameras:
        return torch.zeros(3, dtype=torch.float64)
    return torch.stack([c.center.to(torch.float64) for c in cameras]).mean(dim=0)


def camera_radius(cameras: Sequence[Camera]) -> float:
    """1.1 x the largest distance from a camera centre to the mean centre (3DGS `getNerfppNorm`)."""
    if not cameras:
        return 1.0
    centres = torch.stack([c.center.to(torch.float64) for c in cameras])
    distance = (centres - camera_centre(cameras)).norm(dim=1).max().item()
    # A single camera (or all at one spot) would give 0, which breaks every scale derived from it.
    return 1.1 * distance if distance > 0 else 1.0


def make_scene(train: list[View], test: list[View], points: torch.Tensor | None, colors: torch.Tensor | None,
               background: Background, kind: str, root: Path, notes: list[str] | None = None,
               alpha: bool = False) -> Scene:
    assert kind in KINDS
    if points is not None and points.shape[0] == 0:
        points, colors = None, None
    return Scene(train=train, test=test, points=points, point_colors=colors,
                 radius=camera_radius([v.camera for v in train]), background=background, kind=kind,
                 root=root, notes=list(notes or []), alpha=alpha)
