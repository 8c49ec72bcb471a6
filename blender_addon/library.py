"""Finding the BlendSR library (``gbuffer_export``, ``training``) from Blender's Python.

The add-on never imports the library at import time: the extension is its own package inside Blender
(``bl_ext.<repo>.blendsr``) and the library may live elsewhere. ``status(path)`` adds the user's library path
(add-on preferences) to ``sys.path`` when needed, imports ``gbuffer_export`` and says what is missing. No bpy here.
"""
from __future__ import annotations

import glob
import importlib
import importlib.util
import os
import site
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

#: Site directories this add-on added to ``sys.path`` (handed to worker subprocesses too).
ADDED_SITE_DIRS: list[str] = []


@dataclass(frozen=True)
class LibraryStatus:
    """What the add-on can do from this Python: ``ok`` when ``gbuffer_export`` imports; ``torch`` when training's
    inference can run in-process. ``message`` is a one-line reason when not ok; ``hint`` lines say how to fix it."""

    ok: bool
    root: str = ""               # the directory holding the gbuffer_export package
    torch: bool = False
    training: bool = False
    onnxruntime: bool = False    # the preview can run the zip's ONNX graphs without torch
    message: str = ""
    hint: tuple[str, ...] = field(default_factory=tuple)


def site_dirs_for(path: str | os.PathLike) -> list[Path]:
    """Directories to put on ``sys.path`` for a user-given path: a virtual environment's root (with ``pyvenv.cfg``)
    gives its site-packages for this Python's version, a site-packages folder or a source checkout (holding
    ``gbuffer_export/``) is used as is. Empty list when the path does not exist."""
    p = Path(os.path.expanduser(str(path))).resolve()
    if not p.is_dir():
        return []
    if (p / "pyvenv.cfg").is_file():
        ver = f"python{sys.version_info.major}.{sys.version_info.minor}"
        cands = [p / "lib" / ver / "site-packages", p / "Lib" / "site-packages"]
        found = [c for c in cands if c.is_dir()]
        if not found:  # another Python version: take what is there, imports may still work for pure modules
            found = [Path(c) for c in sorted(glob.glob(str(p / "lib" / "python3*" / "site-packages")))]
        return found
    return [p]


def add_library_path(path: str | os.PathLike) -> list[str]:
    """Add the site directories of ``path`` (see ``site_dirs_for``) to ``sys.path``, processing ``.pth`` files
    (editable installs). Returns the directories added now."""
    added = []
    for d in site_dirs_for(path):
        s = str(d)
        if s in sys.path:
            continue
        site.addsitedir(s)
        ADDED_SITE_DIRS.append(s)
        added.append(s)
    return added


def install_hint() -> tuple[str, ...]:
    """Lines telling the user how to make the library importable from this Python."""
    py = sys.executable or "python"
    return (
        "The extension zip of 'make addon' bundles it (reinstall that zip), or",
        "install the BlendSR library into Blender's Python:",
        f'"{py}" -m pip install blendsr    (from a checkout: -m pip install -e PATH)',
        "or set 'Library path' in the add-on preferences to a",
        "virtual environment, its site-packages or a BlendSR checkout.",
    )


_CACHE: dict[str, LibraryStatus] = {}
_CHECKED: dict[str, float] = {}
RECHECK_S = 5.0  # a missing library is looked for again after this many seconds (the user may install it)


def status(path: str = "", refresh: bool = False) -> LibraryStatus:
    """Whether ``gbuffer_export`` imports (after adding ``path``), cached per path; ``refresh`` re-checks."""
    key = str(path or "")
    cached = _CACHE.get(key)
    if cached is not None and not refresh and (cached.ok or time.monotonic() - _CHECKED[key] < RECHECK_S):
        return cached
    if key:
        add_library_path(key)
    importlib.invalidate_caches()
    try:
        gbe = importlib.import_module("gbuffer_export")
    except ImportError as exc:
        where = importlib.util.find_spec("gbuffer_export") if "gbuffer_export" not in str(exc) else None
        msg = (f"BlendSR library found but it cannot be imported ({exc})" if where
               else "BlendSR library (gbuffer_export) is not importable from Blender's Python")
        st = LibraryStatus(False, message=msg, hint=install_hint())
    else:
        root = str(Path(gbe.__file__).resolve().parent.parent)
        st = LibraryStatus(True, root=root, torch=importlib.util.find_spec("torch") is not None,
                           training=importlib.util.find_spec("training") is not None,
                           onnxruntime=importlib.util.find_spec("onnxruntime") is not None)
    _CACHE[key] = st
    _CHECKED[key] = time.monotonic()
    return st


def worker_paths(st: LibraryStatus) -> dict[str, list[str]]:
    """What a worker process must add to ``sys.path`` to import the library as this process does."""
    return {"site_dirs": list(ADDED_SITE_DIRS), "sys_path": [st.root] if st.root else []}


_NOTES: dict[str, str] | None = None


def pretrained_notes() -> dict[str, str]:
    """{'pretrained:NAME': note} for the shipped networks the library marks (``training.pretrained``:
    'below demod-jbu on val', from the JSON beside the weights; json only, no torch); {} while the library is not
    importable (looked for again on the next call)."""
    global _NOTES
    if _NOTES is None:
        try:
            from training import pretrained
        except ImportError:
            return {}
        _NOTES = {pretrained.PREFIX + n: pretrained.below_baseline_note(n) for n in pretrained.PRETRAINED}
    return {k: v for k, v in _NOTES.items() if v}


def marked_items(items, notes: dict[str, str]) -> list[tuple]:
    """``items`` as numbered enum items (number = position, as saved files store them), a shipped network's label
    carrying its note: "NSRD (pretrained, below demod-jbu on val)"."""
    out = []
    for i, (ident, label, desc) in enumerate(items):
        note = notes.get(ident)
        if note:
            label = label[:-1] + f", {note})" if label.endswith(")") else f"{label} ({note})"
            desc = f"{desc}. Scores {note} (training/weights/*.json)"
        out.append((ident, label, desc, i))
    return out
