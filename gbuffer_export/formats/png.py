"""Minimal 8-bit RGB PNG writer and reader (zlib + struct, no imaging library), for the RDG layout's Image files."""
from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np

from ..clip import write_bytes_atomic


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def write_png(path: str | os.PathLike, rgb8: np.ndarray) -> None:
    """Write an H x W x 3 uint8 array as an 8-bit RGB PNG (atomically: temporary name, then rename)."""
    a = np.ascontiguousarray(np.asarray(rgb8, np.uint8))
    h, w, c = a.shape
    assert c == 3
    raw = b"".join(b"\x00" + a[i].tobytes() for i in range(h))  # filter type 0 per row
    data = (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + _chunk(b"IDAT", zlib.compress(raw, 6)) + _chunk(b"IEND", b""))
    write_bytes_atomic(path, data)  # a full disk names the file


def read_png(path: str | os.PathLike) -> np.ndarray:
    """Read a PNG written by ``write_png`` (8-bit RGB, filter type 0) as H x W x 3 uint8."""
    b = Path(path).read_bytes()
    pos, idat, w, h = 8, b"", 0, 0
    while pos < len(b):
        n = struct.unpack(">I", b[pos:pos + 4])[0]
        kind, data = b[pos + 4:pos + 8], b[pos + 8:pos + 8 + n]
        if kind == b"IHDR":
            w, h = struct.unpack(">II", data[:8])
        elif kind == b"IDAT":
            idat += data
        pos += 12 + n
    raw = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(h, 1 + 3 * w)
    if np.any(raw[:, 0]):
        raise ValueError(f"{path}: only PNG filter type 0 is read here")
    return raw[:, 1:].reshape(h, w, 3).copy()
