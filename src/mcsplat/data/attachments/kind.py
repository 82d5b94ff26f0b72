"""What a kind of per-view input says about itself (`Kind`), and what a view holds of one (`Attachment`).

A kind answers four questions and the seam (attach.py) does the rest: where each view's file is (`find`), what the
file holds as an array at its own size (`decode`), how its values follow a resize and an undistortion
(`resampling`: resampling.AREA or NEAREST) and what one is on the training device (`as_float`). `check` and `note`
are optional: a refusal that needs every view's values at once (a mask that leaves nothing), and the line
Scene.notes gets.

Kinds are duck-typed against views and scenes (a view's `name`, `camera` and `source`; a scene's `root`, `alpha`,
`train` and `test`) so that nothing here imports data/scene.py, which imports the registry to check a name.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Sequence

import numpy as np
import torch

from .resampling import Area, Nearest


@dataclass(frozen=True)
class Found:
    """One file per view (None for a view without one) and where they were looked for (notes and errors say it)."""

    files: list[Path | None]
    where: str


class Kind:
    """One kind of per-view input; a subclass per kind, one instance of it in registry.KINDS."""

    name: ClassVar[str]            # its key: View.attachment(name), registry.KINDS[name]
    label: ClassVar[str]           # how an error names one of its files: "mask", "depth map"
    options: ClassVar[type]        # the dataclass that asks for it (load_scene(attachments=[...]))
    resampling: ClassVar[Area | Nearest]
    default: ClassVar[Any] = None  # the request load_scene makes when none is given (None: only when asked)

    def find(self, options: Any, scene: Any) -> Found | None:
        """Each view's file, or None when the scene has none of this kind (and was not required to)."""
        raise NotImplementedError

    def decode(self, file: Path, view: Any, options: Any) -> np.ndarray:
        """[H, W] values of `file` at its own size, in the scene's terms (a depth in scene units); uint8 for an
        AREA kind. A file that cannot be used is a one-line DataError naming it."""
        raise NotImplementedError

    def as_float(self, values: torch.Tensor, device: torch.device | str) -> torch.Tensor:
        """The stored [H, W] values as float32 [H, W, 1] on `device`."""
        raise NotImplementedError

    def check(self, values: Sequence[torch.Tensor | None], found: Found, views: Sequence[Any], options: Any) -> None:
        """Refuse what only all of the views together show is wrong (nothing by default)."""

    def note(self, values: Sequence[torch.Tensor | None], found: Found, options: Any) -> str | None:
        """The line Scene.notes gets (none by default)."""
        return None


@dataclass(frozen=True)
class Attachment:
    """One view's input of one kind, at its image's size on the CPU, as the kind stores it."""

    kind: Kind
    values: torch.Tensor

    def at(self, device: torch.device | str = "cpu", size: tuple[int, int] | None = None) -> torch.Tensor:
        """float32 [H, W, 1] on `device`; with `size` (width, height), resampled to it by the kind's rule."""
        values = self.kind.as_float(self.values, device)
        if size is None or tuple(size) == (values.shape[1], values.shape[0]):
            return values
        return self.kind.resampling.resize_tensor(values, size)
