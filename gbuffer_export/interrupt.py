"""Ctrl-C (SIGINT) for renders: stop between Cycles passes instead of inside them (pure Python, no bpy).

Python's own SIGINT handler raises KeyboardInterrupt wherever the main thread happens to run Python code. Inside a
render that is Cycles' render callback, where bpy prints the exception and renders on; while ``import bpy`` runs it
is Blender's start-up, which prints it and may crash at exit. ``stop_on_sigint`` replaces the handler with one that
only counts the press; ``check_interrupt`` (called after every Cycles pass, after the scene is loaded and between
frames) then raises KeyboardInterrupt where the render can stop cleanly: the frame in flight is dropped, finished
frames stay, and the CLI prints its resume line with exit code 130. A second Ctrl-C exits at once (exit 130; the
clip stays as consistent as after kill -9). The handler is installed in the main thread only (elsewhere
``signal.signal`` is not allowed) and is re-entrant: nested uses share the outermost one.
"""
from __future__ import annotations

import contextlib
import os
import signal
import threading

_STATE = {"depth": 0, "presses": 0}


def _on_sigint(signum, frame) -> None:
    _STATE["presses"] += 1
    if _STATE["presses"] > 1:
        os.write(2, b"\nblendsr: interrupted again; stopping now (rerun the same command to resume)\n")
        os._exit(130)
    os.write(2, b"\nblendsr: interrupted; stopping after the render pass in progress (Ctrl-C again to stop at "
                b"once)\n")


@contextlib.contextmanager
def stop_on_sigint():
    """Within the block, Ctrl-C is counted instead of raised (see the module doc); the previous handler comes back
    afterwards (a press after the last ``check_interrupt`` of a finished render is dropped: the work is done)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if _STATE["depth"]:
        _STATE["depth"] += 1
        try:
            yield
        finally:
            _STATE["depth"] -= 1
        return
    previous = signal.signal(signal.SIGINT, _on_sigint)
    _STATE.update(depth=1, presses=0)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _STATE.update(depth=0, presses=0)


def check_interrupt() -> None:
    """KeyboardInterrupt when Ctrl-C was pressed inside ``stop_on_sigint``."""
    if _STATE["presses"]:
        raise KeyboardInterrupt


__all__ = ["stop_on_sigint", "check_interrupt"]
