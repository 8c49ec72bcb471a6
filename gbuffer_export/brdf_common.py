"""What the split-sum table (``brdf``) and the BRDF model (``brdf_model``) share (pure numpy): the Hammersley point
set and the on-disk cache of generated tables. A module of its own so that neither of the two imports the other's
internals (``brdf`` dispatches to ``brdf_model``; ``brdf_model`` needs only these)."""
from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def radical_inverse_base2(i: np.ndarray) -> np.ndarray:
    """Van der Corput radical inverse in base 2 of non-negative integers < 2^32 (float64 in [0, 1))."""
    x = np.asarray(i, dtype=np.uint64).astype(np.uint32)
    x = (x << np.uint32(16)) | (x >> np.uint32(16))
    x = ((x & np.uint32(0x55555555)) << np.uint32(1)) | ((x & np.uint32(0xAAAAAAAA)) >> np.uint32(1))
    x = ((x & np.uint32(0x33333333)) << np.uint32(2)) | ((x & np.uint32(0xCCCCCCCC)) >> np.uint32(2))
    x = ((x & np.uint32(0x0F0F0F0F)) << np.uint32(4)) | ((x & np.uint32(0xF0F0F0F0)) >> np.uint32(4))
    x = ((x & np.uint32(0x00FF00FF)) << np.uint32(8)) | ((x & np.uint32(0xFF00FF00)) >> np.uint32(8))
    return x.astype(np.float64) / 4294967296.0


def hammersley(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The n-point Hammersley set (i / n, radical_inverse_2(i)), i = 0..n-1, as two float64 arrays."""
    i = np.arange(n)
    return i / n, radical_inverse_base2(i)


def cache_dir() -> Path:
    """$BLENDSR_CACHE, else $XDG_CACHE_HOME/blendsr, else ~/.cache/blendsr."""
    env = os.environ.get("BLENDSR_CACHE")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "blendsr"


def load_or_generate_file(path: Path, read, generate, write, unreadable: tuple[type[Exception], ...]):
    """``read(path)`` when it succeeds; otherwise ``generate()``, written with ``write(path, value)`` (atomic in the
    callers) and returned. A file ``read`` rejects with ``unreadable`` (torn or foreign) is regenerated and replaced;
    a read-only cache only loses the write."""
    if path.is_file():
        try:
            return read(path)
        except unreadable:
            pass
    log.info("computing %s (cached for later runs)", path.name)
    value = generate()
    try:
        write(path, value)
    except OSError as exc:
        log.debug("%s: not cached (%s)", path, exc.strerror or exc)
    return value
