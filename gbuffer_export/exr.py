"""EXR reading and atomic writing with the OpenEXR 3 Python bindings (pure numpy layer)."""
from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path

import numpy as np
import OpenEXR

from .errors import BlendSRError

HALF_MAX = 65504.0


class ExrError(BlendSRError):
    """A file that is not a readable EXR, or lacks what the caller asked for. The message names the file."""


def write_exr(path: str | os.PathLike, channels: dict[str, np.ndarray], *, half: bool = False,
              compression: str = "ZIP_COMPRESSION", attributes: dict | None = None) -> None:
    """Write single-part EXR ``path`` atomically (temporary file in the same folder, then rename).

    ``channels`` maps channel names to H x W arrays: float arrays are stored as float32 (or half when
    ``half`` is set and every finite value fits), uint32 arrays as UINT.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    out = {}
    for name, arr in channels.items():
        a = np.asarray(arr)
        if a.ndim != 2:
            raise ValueError(f"{path}: channel {name!r} must be 2-D, got shape {a.shape}")
        if a.dtype.kind in "ui":
            a = a.astype(np.uint32)
        elif half and np.all(np.abs(a[np.isfinite(a)]) <= HALF_MAX):
            a = a.astype(np.float16)
        else:
            a = a.astype(np.float32)
        out[name] = np.ascontiguousarray(a)
    header = {"compression": getattr(OpenEXR, compression), "type": OpenEXR.scanlineimage}
    if attributes:
        header.update(attributes)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")
    with contextlib.suppress(FileNotFoundError):
        os.unlink(tmp)  # a leftover (or a planted link) of the same name is never written through
    try:
        with OpenEXR.File(header, out) as f:
            f.write(str(tmp))
        os.replace(tmp, path)
    except RuntimeError as exc:  # OpenEXR's write errors: a full disk names the file, as an OSError would
        raise write_error(path, exc) from None
    finally:
        if tmp.exists():
            tmp.unlink()


def write_error(path: Path, exc: RuntimeError) -> Exception:
    """OpenEXR's RuntimeError of a failed write as the error to raise: an OSError naming ``path`` when its message
    is a filesystem fault the user can fix (``errors.FILESYSTEM_ERRNOS``: a full disk, a quota), else ExrError."""
    from .errors import FILESYSTEM_ERRNOS, first_line
    text = first_line(exc)
    for eno in FILESYSTEM_ERRNOS:
        if os.strerror(eno).lower() in text.lower():
            return OSError(eno, os.strerror(eno), str(path))
    return ExrError(f"{path}: could not write the EXR ({text})")


def read_exr_channels(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """All channels of every part of ``path`` as H x W arrays, keyed by their full channel names."""
    path = Path(path)
    if not path.is_file():
        raise ExrError(f"{path}: file not found")
    try:
        # A truncated file gives zero parts and a warning printed on sys.stdout instead of an exception.
        with contextlib.redirect_stdout(io.StringIO()), OpenEXR.File(str(path), separate_channels=True) as f:
            if not f.parts or any(ch.pixels is None for part in f.parts for ch in part.channels.values()):
                raise ExrError(f"{path}: truncated or corrupt EXR (no readable pixel data)")
            out = {}
            for part in f.parts:
                for name, ch in part.channels.items():
                    out[name] = np.array(ch.pixels)
            return out
    except ExrError:
        raise
    except Exception as exc:  # OpenEXR raises plain exceptions on truncated or foreign files
        raise ExrError(f"{path}: not a readable EXR ({exc})") from None


def read_exr(path: str | os.PathLike, channels: tuple[str, ...]) -> np.ndarray:
    """Read ``channels`` of ``path`` into one H x W x C array (float32, or uint32 for UINT channels)."""
    data = read_exr_channels(path)
    missing = [c for c in channels if c not in data]
    if missing:
        raise ExrError(f"{Path(path)}: missing channel(s) {', '.join(missing)} (has {', '.join(sorted(data))})")
    arrs = [data[c] for c in channels]
    if all(a.dtype.kind == "u" for a in arrs):
        return np.stack(arrs, axis=-1).astype(np.uint32)
    return np.stack([a.astype(np.float32) for a in arrs], axis=-1)


def exr_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an EXR from its header only."""
    try:
        with OpenEXR.File(str(path), header_only=True) as f:
            (x0, y0), (x1, y1) = f.header()["dataWindow"]
            return int(x1 - x0 + 1), int(y1 - y0 + 1)
    except Exception as exc:
        raise ExrError(f"{Path(path)}: not a readable EXR ({exc})") from None
