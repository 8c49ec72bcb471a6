"""BlendSR data generation: the clip contract (pure numpy), the Blender renderer (bpy) and the CLI.

``from gbuffer_export import open_clip`` needs numpy and OpenEXR (colour-science is imported only to convert colours:
``gbuffer_export.colour_spaces``); bpy is imported only by ``gbuffer_export.blender`` and torch only by the
``training`` package.
"""
import importlib

__version__ = "0.1.0"
__all__ = ["open_clip", "Clip", "ClipError", "ClipWriter", "BUFFERS", "DEFAULT_BUFFERS", "Flag", "RenderConfig",
           "validate_clip", "load_spec", "validate_dataset", "__version__"]

#: the package's public names, imported when first used: ``import gbuffer_export.cli`` loads neither numpy nor
#: OpenEXR, so ``blendsr`` sets its Ctrl-C handling before anything slow is imported (``gbuffer_export.cli``).
#: Rendering itself is the bpy layer's: ``gbuffer_export.blender.render.render_clip(RenderConfig(...))``.
_LAZY = {"open_clip": ".clip", "Clip": ".clip", "ClipError": ".clip", "ClipWriter": ".clip",
         "BUFFERS": ".conventions", "DEFAULT_BUFFERS": ".conventions", "Flag": ".conventions",
         "RenderConfig": ".config", "validate_clip": ".validate", "load_spec": ".dataset.spec",
         "validate_dataset": ".dataset.check"}


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
