"""BlendSR's error for bad input (numpy core: imports nothing).

Every error that means "the user asked for something that cannot be done" (a bad option, a broken spec, an
unreadable clip, a checkpoint that is not one) subclasses ``BlendSRError``. The CLI (``gbuffer_export/cli.py``)
prints those as one line ``blendsr: error: ...`` with exit code 2; any other exception is a bug in BlendSR and is
reported with its traceback and exit code 70 (``EX_SOFTWARE``). ``BlendSRError`` is a ``ValueError`` so code that
catches ``ValueError`` around a parse keeps working.
"""
from __future__ import annotations


class BlendSRError(ValueError):
    """Bad input: the message is one line naming the file, option or key and what is wrong."""


__all__ = ["BlendSRError"]
