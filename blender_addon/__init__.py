"""BlendSR add-on (Blender 4.2+ extension): export super-resolution datasets and preview upscaling from a panel.

A thin UI over the BlendSR library: exports call ``gbuffer_export.blender.render.render_clip`` in a worker process,
the preview calls ``training.inference.loading``. Importing this package has no side effects and imports neither bpy nor
the library; ``register()`` loads the submodules. See docs/addon.md.
"""
from __future__ import annotations

import importlib

#: Submodules with register()/unregister(), in registration order.
SUBMODULES = ("props", "prefs", "operators", "dataset_ops", "panels")


def _submodules():
    return [importlib.import_module(f"{__name__}.{name}") for name in SUBMODULES]


class WheelError(RuntimeError):
    """A wheel the extension carries is not a readable wheel (a corrupt or truncated download): one line naming it."""


def wheel_problem(wheel) -> str:
    """'' when ``wheel`` (a path or a file object) opens as a zip holding its ``*.dist-info/RECORD`` (cheap: the
    central directory only; the build also checks every member's CRC), else what is wrong, in a few words."""
    import zipfile
    try:
        with zipfile.ZipFile(wheel) as z:
            if not any(n.endswith(".dist-info/RECORD") for n in z.namelist()):
                return "no .dist-info/RECORD inside"
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        return f"not a readable zip ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
    return ""


def check_wheels(folder=None) -> None:
    """WheelError naming the first wheel of the extension's ``wheels/`` (``folder``) that is not readable, so that
    enabling says which file to replace instead of failing later on an import (Blender installs the wheels)."""
    from pathlib import Path
    folder = Path(folder) if folder is not None else Path(__file__).resolve().parent / "wheels"
    for w in sorted(folder.glob("*.whl")) if folder.is_dir() else ():
        why = wheel_problem(w)
        if why:
            raise WheelError(f"BlendSR: the bundled wheel {w.name} is corrupt ({why}); reinstall the add-on from a "
                             "fresh download of its zip")


def register() -> None:
    check_wheels()
    for mod in _submodules():
        mod.register()


def unregister() -> None:
    for mod in reversed(_submodules()):
        mod.unregister()
