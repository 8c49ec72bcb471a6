"""One writer per folder: an exclusive, non-blocking lock on a lock file inside it (core: ``filelock``).

Used by the dataset coordinator (``DATASET/.lock``) and by training (``RUN/.lock``); clips have their own
shared/exclusive scheme in ``gbuffer_export.clip.ClipWriter``. The lock is the operating system's (``flock`` on
Linux and macOS, ``LockFileEx`` on Windows, through ``filelock.FileLock``): it is released when the process dies
(kill -9 included), so a stale lock file never blocks a later run. A process forked from the holder (a training
loader worker) shares the lock while it lives (filelock 4 closes the inherited descriptor in the child; 3.x does
not), so BlendSR's forked workers end with their parent (``die_with_parent``, used by ``training.loader``).
"""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
from pathlib import Path

import filelock

from .clip import UnsafePathError
from .errors import BlendSRError


#: Locks held by this process and not closed: a FolderLock nobody keeps a reference to still holds its folder until
#: ``close()`` or the end of the process (filelock would release it when the object is collected).
_HELD: set = set()


class FolderBusyError(BlendSRError):
    """Another BlendSR process holds the folder's lock."""


class FolderLock:
    """Hold ``root/name`` exclusively until ``close()`` (or the end of a ``with`` block, or the process).

    ``busy`` is the one-line message raised (``FolderBusyError``) when another process (or another ``FolderLock``
    of this process) holds it; ``timeout`` > 0 waits that many seconds for it first, -1 waits until it is free. A
    symbolic link planted at the lock file's place is refused (UnsafePathError), never written through."""

    def __init__(self, root: str | os.PathLike, busy: str, name: str = ".lock", timeout: float = 0):
        self.root = Path(root)
        path = self.root / name
        if path.is_symlink():
            raise UnsafePathError(f"{path}: is a symbolic link; refused")
        self._lock: filelock.BaseFileLock | None = filelock.FileLock(
            path, timeout=timeout, thread_local=False, is_singleton=False)
        try:
            self._lock.acquire()
        except filelock.Timeout:
            self._lock = None
            raise FolderBusyError(f"{self.root}: {busy}") from None
        except OSError as exc:
            self._lock = None
            if path.is_symlink():  # planted between the check and the open (filelock opens with O_NOFOLLOW)
                raise UnsafePathError(f"{path}: is a symbolic link; refused") from None
            raise
        _HELD.add(self)

    @property
    def held(self) -> bool:
        return self._lock is not None

    def close(self) -> None:
        if self._lock is not None:
            lock, self._lock = self._lock, None
            _HELD.discard(self)
            lock.release(force=True)

    def __enter__(self) -> "FolderLock":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: How often a child without the kernel's parent-death signal checks that its parent is alive (seconds).
PARENT_POLL_S = 0.2


def die_with_parent(parent: int) -> str:
    """Make this (forked) process end when ``parent`` does, so that it never outlives the process that holds a
    folder's lock (a loader worker of a killed trainer). Linux: ``prctl(PR_SET_PDEATHSIG, SIGKILL)``, immediate;
    elsewhere (or when prctl is unavailable) a daemon thread that exits the process within PARENT_POLL_S of the
    parent's death. Returns the mechanism used ("pdeathsig" or "watch")."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(1, int(signal.SIGKILL), 0, 0, 0) == 0:  # 1: PR_SET_PDEATHSIG
                if os.getppid() != parent:  # the parent died before the signal was armed
                    os._exit(1)
                return "pdeathsig"
        except (OSError, AttributeError):
            pass

    def watch():
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    if os.getppid() != parent:
        os._exit(1)
    threading.Thread(target=watch, name="blendsr-parent-watch", daemon=True).start()
    return "watch"
