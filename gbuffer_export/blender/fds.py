"""Blender's own output on file descriptors 1 and 2 (render logs, importer chatter, GPU-library warnings), captured
in one place. ``BLENDSR_VERBOSE=1`` lets it through as it is."""
from __future__ import annotations

import contextlib
import os
import sys
import tempfile


class Captured:
    """What a ``captured`` block's descriptors received (``text``, filled when the block ends; '' when verbose)."""
    text: str = ""


@contextlib.contextmanager
def captured(fds: tuple[int, ...] = (1, 2)):
    """Redirect ``fds`` into a temporary file for the block; yields a ``Captured`` whose ``text`` holds what they
    received once the block ends (the caller logs, filters or drops it)."""
    out = Captured()
    if os.environ.get("BLENDSR_VERBOSE"):
        yield out
        return
    sys.stdout.flush()
    sys.stderr.flush()
    saved = {fd: os.dup(fd) for fd in fds}
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        for fd in saved:
            os.dup2(tmp.fileno(), fd)
        try:
            yield out
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            for fd, keep in saved.items():
                os.dup2(keep, fd)
                os.close(keep)
            tmp.seek(0)
            out.text = tmp.read().decode(errors="replace")
