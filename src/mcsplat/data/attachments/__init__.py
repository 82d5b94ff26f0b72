"""Per-view inputs that lie beside the photos (masks today, depth maps; normal maps next), found and brought to their
views after a loader has run, so that no loader knows of them.

`registry.KINDS` lists the kinds, one module each (masks.py, depth.py); `attach(scene, [MaskOptions(), ...])`
(attach.py) hangs each on its view, where `view.attachment(name, device, size)` gives it at any training resolution.
The recipe for a new kind is in docs/extending.md ("A per-view input").
"""

from .attach import attach
from .depth import DepthOptions
from .kind import Attachment, Found, Kind
from .masks import MaskOptions
from .registry import KINDS, kind_for, kinds_for, with_defaults

__all__ = ["KINDS", "Attachment", "DepthOptions", "Found", "Kind", "MaskOptions", "attach", "kind_for", "kinds_for",
           "with_defaults"]
