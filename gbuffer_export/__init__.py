"""BlendSR data generation: the clip contract (pure numpy), the Blender renderer (bpy) and the CLI.

``from gbuffer_export import open_clip`` needs numpy and OpenEXR (colour-science is imported only to convert colours:
``gbuffer_export.colour_spaces``); bpy is imported only by ``gbuffer_export.blender`` and torch only by the
``training`` package.
"""
from .clip import Clip, ClipError, ClipWriter, open_clip
from .conventions import BUFFERS, DEFAULT_BUFFERS, Flag

__version__ = "0.1.0"
__all__ = ["open_clip", "Clip", "ClipError", "ClipWriter", "BUFFERS", "DEFAULT_BUFFERS", "Flag", "__version__"]
