"""BlendSR's bpy layer: scenes, rendering, camera paths, level cameras. Importing this package imports no bpy; the
public name ``render_clip`` (``gbuffer_export.blender.render``) does, when first used."""
import importlib

__all__ = ["render_clip"]

_LAZY = {"render_clip": ".render"}


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
