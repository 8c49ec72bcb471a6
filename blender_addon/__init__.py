"""BlendSR add-on (Blender 4.2+ extension): export super-resolution datasets and preview upscaling from a panel.

A thin UI over the BlendSR library: exports call ``gbuffer_export.blender.render.render_clip`` in a worker process,
the preview calls ``training.inference``. Importing this package has no side effects and imports neither bpy nor
the library; ``register()`` loads the submodules. See docs/addon.md.
"""
from __future__ import annotations

import importlib

#: Submodules with register()/unregister(), in registration order.
SUBMODULES = ("props", "prefs", "operators", "dataset_ops", "panels")


def _submodules():
    return [importlib.import_module(f"{__name__}.{name}") for name in SUBMODULES]


def register() -> None:
    for mod in _submodules():
        mod.register()


def unregister() -> None:
    for mod in reversed(_submodules()):
        mod.unregister()
