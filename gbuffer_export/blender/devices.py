"""Cycles' device probe, done once before a progress bar starts.

Cycles enumerates its GPU back-ends the first time it is asked for devices (a render, the preferences) and logs a
warning for each library it cannot open ("CUEW initialization failed: Error opening the library", "HIPEW ...") on
standard output (descriptor 1; CLOG's) - on a CPU-only machine, in the middle of the first frame's progress bar on
a terminal. ``probe_devices`` asks once, before the bar, with descriptors 1 and 2 captured: the warnings about
absent GPU libraries (expected on a CPU render) are dropped, any other line is printed as it was. Cycles remembers
the result, so later renders print nothing.
"""
from __future__ import annotations

import logging
import re

import bpy

log = logging.getLogger(__name__)

#: Cycles' warnings for a GPU back-end whose library is absent (CUDA, HIP, oneAPI, Metal, OptiX).
ABSENT_GPU_LIBRARY = re.compile(r"\b(CUEW|HIPEW|HIPRTEW|OptiX|oneAPI|Metal)\b.*\b(initialization failed|not found|"
                                r"failed to load|Error opening)", re.IGNORECASE)

_probed = False


def probe_devices() -> list[str]:
    """Enumerate Cycles' devices once per process (fds 1 and 2 captured; absent-GPU-library warnings dropped, other
    lines printed to stderr); returns the device types found (e.g. ['CPU'])."""
    global _probed
    if _probed:
        return []
    _probed = True
    try:
        prefs = bpy.context.preferences.addons["cycles"].preferences
    except (KeyError, AttributeError):
        return []
    from .fds import captured
    with captured() as out:
        devices = prefs.get_devices() or []
    text = out.text
    kept = [ln for ln in text.splitlines() if ln.strip() and not ABSENT_GPU_LIBRARY.search(ln)]
    if kept:
        log.warning("%s", "\n".join(kept))  # what Cycles said besides the absent-GPU-library lines
    types = []
    for group in devices:
        for d in (group if isinstance(group, (list, tuple)) else [group]):
            t = getattr(d, "type", None)
            if t and t not in types:
                types.append(t)
    return types
