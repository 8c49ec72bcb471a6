"""BlendSR's error for bad input, and which exceptions are bad input (core: standard library only).

Every error that means "the user asked for something that cannot be done" (a bad option, a broken spec, an
unreadable clip, a checkpoint that is not one) subclasses ``BlendSRError``. The CLI (``gbuffer_export/cli.py``)
prints those as one line ``blendsr: error: ...`` with exit code 2; any other exception is a bug in BlendSR and is
reported with its traceback and exit code 70 (``EX_SOFTWARE``). ``BlendSRError`` is a ``ValueError`` so code that
catches ``ValueError`` around a parse keeps working.
"""
from __future__ import annotations

import errno
import json


class BlendSRError(ValueError):
    """Bad input: the message is one line naming the file, option or key and what is wrong."""


#: Exit code of an internal error (a bug in BlendSR), sysexits.h's EX_SOFTWARE.
EXIT_INTERNAL = 70

#: Filesystem faults the user can fix (errno -> what the one-line error says).
FILESYSTEM_ERRNOS = {
    errno.EROFS: "read-only file system",
    errno.ENOSPC: "no space left on device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EFBIG: "file too large",
}

def first_line(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc).strip() else type(exc).__name__


def filesystem_message(exc: BaseException) -> str | None:
    """'PATH: read-only file system' for a filesystem fault the user can fix (see FILESYSTEM_ERRNOS), else None.
    Looks through ``__cause__``/``__context__`` so a fault re-raised by a library is still recognised, but not
    through a context the raiser suppressed (``raise ... from None``: its own message already says what is wrong and
    names the file)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in FILESYSTEM_ERRNOS:
            what = FILESYSTEM_ERRNOS[exc.errno]
            return f"{exc.filename}: {what}" if exc.filename is not None else what
        exc = exc.__cause__ or (None if exc.__suppress_context__ else exc.__context__)
    return None


def with_path(exc: OSError, path) -> OSError:
    """``exc`` as an OSError naming ``path`` when it names no file (a failed ``write`` or ``flush`` on a full disk
    names none), so that the one-line error says which file; ``exc`` itself otherwise."""
    if exc.filename is None and exc.errno is not None:
        named = OSError(exc.errno, exc.strerror, str(path))
        named.__cause__ = exc
        return named
    return exc


def bad_input_line(exc: BaseException) -> str | None:
    """The one-line message of an exception that is the user's to fix, or None for a bug."""
    fs = filesystem_message(exc)
    if fs is not None:
        return fs
    if isinstance(exc, (BlendSRError, FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError)):
        return first_line(exc)
    if isinstance(exc, (json.JSONDecodeError, UnicodeDecodeError)) or type(exc).__name__ == "TOMLDecodeError":
        return f"{type(exc).__name__}: {first_line(exc)}"
    return None


__all__ = ["BlendSRError", "EXIT_INTERNAL", "FILESYSTEM_ERRNOS", "bad_input_line", "filesystem_message",
           "first_line", "with_path"]
