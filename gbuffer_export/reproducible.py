"""Same ``blendsr render --threads 1`` command, same EXRs: a fixed address layout and one core for the renderer.

Cycles and Blender order some scene data by memory address (objects and primitives reach the BVH and the sampling
structures in an order that follows pointers: rendering twice in one process is bit-identical, in two processes it
is not). Three things move addresses between two runs of one command, and each was measured to change the radiance
on its own (built-in scene, 64x36, 4 HR / 2 LR spp: 9-49% of HR pixels differ, max abs difference up to 0.75, with
G-buffers equal up to 1 ulp; docs/clip-format.md, "Reproducibility"):

1. address-space layout randomisation (ASLR), new on every process start;
2. Python's string-hash randomisation, which changes set and dict order and so what Python allocates when;
3. threads: Blender's task scheduler and Cycles build the scene on all cores, and which thread allocates what
   first depends on timing.

``prepare_render_process`` removes the three for ``--threads 1``: it pins the process to one core (Blender's task
scheduler then starts one thread), and re-executes the process once with ``personality(ADDR_NO_RANDOMIZE)`` (what
``setarch -R`` does), ``PYTHONHASHSEED=0`` and glibc's default allocator thresholds (``MALLOC_TUNING``). Two runs
of the same command (same arguments, same output path: the path's length shapes the heap too) then give
bit-identical EXRs on an idle machine. This is best effort: Blender keeps helper threads even then, and under CPU
contention their interleaving (and so the radiance's noise realisation) can change; the G-buffers stay equal to
float rounding. With more threads (the default) only 1 and 2 are removed and the radiance still varies.

What stays different in every case: the layout depends on what the process did before a frame, so a frame rendered
by a resumed run or by another ``--shard`` is a different noise realisation of the same image than in one
uninterrupted run (same G-buffers up to 1 ulp, radiance equal in expectation). Where the kernel refuses the
personality change (some container sandboxes) the render runs unchanged. ``BLENDSR_KEEP_ASLR=1`` opts out.
"""
from __future__ import annotations

import ctypes
import os
import sys

ADDR_NO_RANDOMIZE = 0x0040000
#: glibc settings (the Makefile's, for torch) under which even one-core renders differed in every run (0 of 3
#: identical, against 9 of 9 without them): dropped for --threads 1.
MALLOC_TUNING = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
_QUERY = 0xFFFFFFFF


def _personality():
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.personality
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_ulong]
    fn.restype = ctypes.c_int
    return fn


def address_layout_fixed() -> bool | None:
    """True when this process runs without address randomisation; None where that cannot be known."""
    if not sys.platform.startswith("linux"):
        return None
    fn = _personality()
    if fn is None:
        return None
    cur = fn(_QUERY)
    return None if cur == -1 else bool(cur & ADDR_NO_RANDOMIZE)


def reexec_with_fixed_layout(drop_env: tuple[str, ...] = ()) -> bool:
    """Re-execute this process (same interpreter and arguments) with address randomisation off, once. Returns False
    (and does nothing) when it is already off, not Linux, opted out, or the kernel refuses; otherwise it does not
    return. Call it before importing bpy, from a process started for the command (never from a test or library)."""
    if not sys.platform.startswith("linux") or os.environ.get("BLENDSR_KEEP_ASLR") == "1":
        return False
    fn = _personality()
    if fn is None:
        return False
    cur = fn(_QUERY)
    if cur == -1 or cur & ADDR_NO_RANDOMIZE:
        return False
    if fn(cur | ADDR_NO_RANDOMIZE) == -1 or not fn(_QUERY) & ADDR_NO_RANDOMIZE:
        return False
    argv = list(getattr(sys, "orig_argv", [])) or [sys.executable, *sys.argv]
    sys.stdout.flush()
    sys.stderr.flush()
    env = dict(os.environ)
    env.setdefault("PYTHONHASHSEED", "0")  # string hashing (set/dict order) shapes what is allocated where, too
    for k in drop_env:
        env.pop(k, None)
    os.execve(sys.executable, [sys.executable, *argv[1:]], env)
    return True  # not reached


def pin_to_one_core() -> bool:
    """Restrict this process to one of its allowed CPUs (before bpy is imported); False where unsupported."""
    if not hasattr(os, "sched_setaffinity"):
        return False
    try:
        cpus = sorted(os.sched_getaffinity(0))
        if len(cpus) > 1:
            os.sched_setaffinity(0, {cpus[0]})
        return True
    except OSError:
        return False


def prepare_render_process(threads: int) -> None:
    """Called by ``blendsr render`` in its own process before importing bpy (see the module doc)."""
    if os.environ.get("BLENDSR_KEEP_ASLR") == "1":
        return
    if threads == 1:
        pin_to_one_core()
        reexec_with_fixed_layout(drop_env=MALLOC_TUNING)
    else:
        reexec_with_fixed_layout()
