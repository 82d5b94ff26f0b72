"""Scene loading: `load_scene(path)` reads a COLMAP, Blender/NeRF or LLFF folder into a `Scene` of `View`s."""

from .load import detect_kind, load_scene
from .scene import Scene, View

__all__ = ["Scene", "View", "detect_kind", "load_scene"]
