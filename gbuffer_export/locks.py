"""One writer per folder: an exclusive, non-blocking ``flock`` on a lock file inside it (core: standard library).

Used by the dataset coordinator (``DATASET/.lock``) and by training (``RUN/.lock``); clips have their own
shared/exclusive scheme in ``gbuffer_export.clip.ClipWriter``. The lock is the kernel's: it is released when the
process dies (kill -9 included), so a stale lock file never blocks a later run.
"""
from __future__ import annotations

import fcntl
import os
from pathlib import Path

from .clip import open_nofollow
from .errors import BlendSRError


class FolderBusyError(BlendSRError):
    """Another BlendSR process holds the folder's lock."""


class FolderLock:
    """Hold ``root/name`` exclusively until ``close()`` (or the end of a ``with`` block, or the process).

    ``busy`` is the one-line message raised (``FolderBusyError``) when another process holds it. The lock file is
    opened without following a link (a planted link is refused, never written through)."""

    def __init__(self, root: str | os.PathLike, busy: str, name: str = ".lock"):
        self.root = Path(root)
        self.fd: int | None = open_nofollow(self.root / name, os.O_WRONLY | os.O_CREAT)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self.fd)
            self.fd = None
            raise FolderBusyError(f"{self.root}: {busy}") from None

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def __enter__(self) -> "FolderLock":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
