"""Where ``blendsr export-dataset`` writes (both formats): the output folder rules, written once.

- ``-o OUT`` names a folder of its own: a file, a symbolic link, a BlendSR clip or dataset folder (or a folder
  inside one), and a folder that holds a source or lies inside one are refused with one line before anything is
  read.
- A non-empty ``OUT`` is refused unless ``mode`` is ``overwrite`` (the export replaces it whole) or ``append``
  (the new sequences or scenes are added after the existing ones; OUT must hold an export of the same format).
- ``--append`` and ``--overwrite`` hold the export's lock, ``OUT/.lock`` (``locks.FolderLock``, the OS's lock,
  released with the process), from before they read what OUT holds (its sequences, its scenes) until their files
  are in place: a second export to OUT waits for it (a note says so), then numbers its sequences after the first's.
- Everything is written into a temporary sibling, ``.OUT.export<PID>``, and moved into place at the end: a new or
  overwritten export appears whole (overwrite: OUT is renamed to ``.OUT.old<PID>``, the sibling to OUT, then the old
  folder removed); an appended one moves its sequence folders in and writes its metadata files last. An export that
  is killed leaves only its sibling (or, between the two renames of an overwrite, the previous export at
  ``.OUT.old<PID>``): the next export to OUT removes the sibling, puts a previous export whose swap was cut short
  back in place, and (append) removes the pieces of a sequence whose metadata was never written and the
  ``.NAME.tmp<PID>`` files of a dead writer.

Pure Python: no bpy, no torch.
"""
from __future__ import annotations

import logging
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..clip import check_no_links
from ..errors import BlendSRError

log = logging.getLogger(__name__)

MODES = ("new", "overwrite", "append")
#: The export's lock file inside OUT (``--append``, ``--overwrite``); not part of the export.
LOCK_NAME = ".lock"
#: ``.NAME.tmp<PID>`` / ``.NAME.tmp<PID>.exr`` written by write_exr, write_png and write_json_atomic
TEMP_FILE = re.compile(r"^\..*\.tmp(\d+)(\.\w+)?$")


class ExportError(BlendSRError):
    """An export request that cannot be done as asked (the output folder, an option): one line, exit code 2."""


@dataclass(frozen=True)
class ExportOptions:
    """How ``export_nss``/``export_rdg`` write. ``mode``: new (OUT absent or empty), overwrite, append;
    ``framerate``: NSS's EmulatedFramerate (frames per second, > 0); ``progress(clip, written)`` after each clip."""
    mode: str = "new"
    framerate: int = 24
    progress: Callable | None = None

    def validate(self) -> None:
        if self.mode not in MODES:
            raise ExportError(f"mode {self.mode!r}: choose one of {', '.join(MODES)}")
        fr = self.framerate
        if isinstance(fr, bool) or not isinstance(fr, int) or not 0 < fr <= 1000:
            raise ExportError(f"framerate {fr!r}: must be a whole number of frames per second in 1..1000")


def pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def _blendsr_folder(p: Path) -> str | None:
    if (p / "dataset.json").is_file():
        return "dataset"
    if (p / "manifest.json").is_file() or (p / "frames").is_dir():
        return "clip"
    return None


def _inside(a: Path, b: Path) -> bool:
    """True when ``a`` is ``b`` or lies inside it (both resolved)."""
    return a == b or b in a.parents


def check_output(out: Path, sources, mode: str) -> None:
    """Refuse an ``-o`` that is a file, a BlendSR clip or dataset (or inside one), or overlaps a source."""
    if out.is_symlink():
        raise ExportError(f"{out}: is a symbolic link; -o names a folder of its own (give the folder it points to)")
    if out.exists() and not out.is_dir():
        raise ExportError(f"{out}: is a file; -o names the folder to write the export to")
    real = out.resolve()
    for p in (real, *real.parents):
        kind = _blendsr_folder(p)
        if kind:
            where = "is" if p == real else f"lies inside {p}, which is"
            raise ExportError(f"{out}: {where} a BlendSR {kind} folder; export into a folder of its own")
    for s in sources:
        src = Path(s).resolve()
        if _inside(real, src) or _inside(src, real):
            raise ExportError(f"{out}: overlaps the source {s}; export into a folder of its own")
    if mode not in MODES:
        raise ExportError(f"mode {mode!r}: choose one of {', '.join(MODES)}")


def clean_stale(out: Path) -> None:
    """Remove what a killed export to ``out`` left beside it (see module doc); restore a previous export whose
    overwrite was cut between its two renames."""
    parent = out.parent if out.parent.exists() else None
    if parent is None:
        return
    pat = re.compile(rf"^\.{re.escape(out.name)}\.(export|old)(\d+)$")
    for p in sorted(parent.iterdir()):
        m = pat.match(p.name)
        if not m or p.is_symlink() or not p.is_dir() or pid_alive(int(m.group(2))):
            continue
        if m.group(1) == "old" and not out.exists():
            log.warning(f"{out}: restoring the previous export from {p.name} (an overwrite was interrupted)")
            os.rename(p, out)
        else:
            log.info(f"{p}: removing what an interrupted export left")
            shutil.rmtree(p)


def clean_temp_files(root: Path) -> int:
    """Remove ``.NAME.tmp<PID>[.ext]`` files of dead writers under ``root``; returns how many."""
    n = 0
    for dirpath, dirnames, filenames in os.walk(root):
        for f in filenames:
            m = TEMP_FILE.match(f)
            if m and not pid_alive(int(m.group(1))):
                os.unlink(Path(dirpath) / f)
                n += 1
    return n


def _entries(out: Path) -> list[Path]:
    """What OUT holds, its lock file left out."""
    return [p for p in out.iterdir() if p.name != LOCK_NAME] if out.is_dir() else []


def lock_export(out: Path):
    """Hold ``OUT/.lock`` (created with OUT when missing); when another export holds it, log a note and wait for
    it (two appends are serialized, never interleaved). Returns the ``FolderLock``."""
    from ..locks import FolderBusyError, FolderLock
    out.mkdir(parents=True, exist_ok=True)
    busy = "another export to this folder is running"
    try:
        return FolderLock(out, busy, LOCK_NAME)
    except FolderBusyError:
        log.info(f"{out}: {busy}; waiting for it to finish")
        return FolderLock(out, busy, LOCK_NAME, timeout=-1)


class Target:
    """The folder an export writes: ``work`` (the temporary sibling) while it runs, ``commit()`` moves it into
    place. Use as a context manager: entering takes OUT's lock (append, overwrite) and checks OUT again under it
    (``appending``: sequences are numbered inside the block); an exception removes the sibling and leaves OUT as it
    was."""

    def __init__(self, out, sources, mode: str, *, is_export: Callable[[Path], bool], fmt: str):
        self.out, self.mode, self.fmt = Path(os.path.abspath(out)), mode, fmt  # '.', 'a/..': a named folder
        if self.out == Path(self.out.anchor):
            raise ExportError(f"{out}: is the root of the file system; -o names a folder of its own")
        check_output(self.out, sources, mode)
        self.is_export = is_export
        clean_stale(self.out)
        self._check_state()  # before any clip is read; again under the lock
        self.appending = False
        self.lock = None
        self.work = self.out.parent / f".{self.out.name}.export{os.getpid()}"

    def _check_state(self) -> bool:
        """Whether OUT holds something; ExportError when the mode does not allow what it holds."""
        nonempty = bool(_entries(self.out))
        if nonempty and self.mode == "new":
            raise ExportError(f"{self.out}: is not empty; pass --overwrite to replace it or --append to add "
                              "to the export in it")
        if self.mode == "append" and nonempty and not self.is_export(self.out):
            raise ExportError(f"{self.out}: holds no {self.fmt.upper()} export to append to (pass --overwrite to "
                              "replace what is there)")
        return nonempty

    def __enter__(self) -> "Target":
        self.out.parent.mkdir(parents=True, exist_ok=True)
        if self.mode in ("append", "overwrite"):  # an overwrite into a missing OUT too: never beside an append
            self.lock = lock_export(self.out)
        try:
            clean_stale(self.out)
            self._check_state()
            self.appending = self.mode == "append"  # into OUT as it is now (empty: sequences from 0)
            if self.work.exists():
                shutil.rmtree(self.work)
            self.work.mkdir()
        except BaseException:
            self._release()
            raise
        return self

    def _release(self) -> None:
        if self.lock is not None:
            self.lock.close()
            self.lock = None

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if self.work.exists():
                shutil.rmtree(self.work, ignore_errors=True)
        finally:
            self._release()

    def commit(self, last: tuple[str, ...] = ()) -> None:
        """Move the export into place. Append: every file of ``work`` into OUT (``last``: top-level names moved
        after everything else, the metadata that makes a sequence count)."""
        if self.appending:
            self._merge(last)
            return
        if _entries(self.out) and self.mode != "overwrite":
            raise ExportError(f"{self.out}: another export wrote there while this one ran; nothing replaced")
        if self.out.is_dir() and self.mode == "overwrite" and _entries(self.out):
            old = self.out.parent / f".{self.out.name}.old{os.getpid()}"
            os.rename(self.out, old)
            os.rename(self.work, self.out)
            shutil.rmtree(old)
            return
        if self.out.is_dir():
            shutil.rmtree(self.out)  # empty, or only a lock file
        os.rename(self.work, self.out)

    def _merge(self, last: tuple[str, ...]) -> None:
        files = sorted(p for p in self.work.rglob("*") if p.is_file())
        files.sort(key=lambda p: p.relative_to(self.work).parts[0] in last)
        for p in files:
            dest = self.out / p.relative_to(self.work)
            dest.parent.mkdir(parents=True, exist_ok=True)
            check_no_links(self.out, dest.parent)  # never written through a link planted in OUT
            if dest.is_symlink():
                dest.unlink()
            os.replace(p, dest)


__all__ = ["ExportError", "ExportOptions", "LOCK_NAME", "MODES", "Target", "check_output", "clean_stale",
           "clean_temp_files", "lock_export"]
