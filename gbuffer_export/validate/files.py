"""Checks of the buffer files: every buffer of a checked frame exists at both levels and is a readable EXR with
the level's size, the channels of ``BUFFERS`` and the right sample type (flags uint32, others float)."""
from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import OpenEXR

from ..clip import UnsafePathError, buffer_path, check_no_links
from ..conventions import BUFFERS
from .report import WARNING, Collector


class ExrProblem(Exception):
    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


def read_exr_all(path: Path, header_only: bool = False) -> tuple[tuple[int, int], dict[str, np.ndarray | str]]:
    """((width, height), {channel: H x W array}) of a single-part EXR; with ``header_only`` the values are the
    channel type names instead of pixels. The OpenEXR bindings return no parts (not an exception) when the pixel
    data is truncated, so that case is detected here."""
    try:
        with OpenEXR.File(str(path), header_only=True) as f:
            hdr = f.header()
            (x0, y0), (x1, y1) = hdr["dataWindow"]
            size = (int(x1 - x0 + 1), int(y1 - y0 + 1))
            names = [c.name for c in hdr["channels"]]
    except Exception as exc:  # the bindings raise plain exceptions on foreign or cut headers
        raise ExrProblem("truncated-exr", f"not a readable EXR ({str(exc).splitlines()[0] if str(exc) else exc})")
    if header_only:
        return size, {n: "" for n in names}
    said = io.StringIO()  # the bindings print (to sys.stdout) why pixel data could not be read
    try:
        with contextlib.redirect_stdout(said), OpenEXR.File(str(path), separate_channels=True) as f:
            chans = {name: np.asarray(ch.pixels) for name, ch in f.parts[0].channels.items()} if f.parts else {}
    except Exception as exc:
        raise ExrProblem("truncated-exr", f"not a readable EXR ({str(exc).splitlines()[0] if str(exc) else exc})")
    if names and not chans:
        why = said.getvalue().strip().splitlines()
        raise ExrProblem("truncated-exr", f"truncated EXR: header lists {', '.join(names)} but the pixel data "
                                           f"cannot be read{' (' + why[-1] + ')' if why else ''}")
    return size, chans



def read_level(c: Collector, frame: int, lvl: str, h: dict, header_only: bool) -> dict[str, np.ndarray]:
    """Check the files of one frame and level; return the readable, well-formed buffers (H x W x C)."""
    w, hh = h["sizes"][lvl]
    out: dict[str, np.ndarray] = {}
    for name in h["buffers"]:
        spec = BUFFERS[name]
        key = f"{lvl}/{name}"
        path = buffer_path(c.root, frame, lvl, name)
        try:
            check_no_links(c.root, path)
        except UnsafePathError as exc:
            c.add("unsafe-link", str(exc), frame=frame, key=key)
            continue
        if not path.is_file():
            c.add("missing-buffer", f"{path}: missing", frame=frame, key=key)
            continue
        try:
            size, chans = read_exr_all(path, header_only)
        except ExrProblem as exc:
            c.add(exc.code, f"{path}: {exc}", frame=frame, key=key)
            continue
        c.stats["files_header_only" if header_only else "files_read"] += 1
        good = True
        if size != (w, hh):
            c.add("bad-size", f"{path}: {size[0]}x{size[1]} px, level {lvl} is {w}x{hh}", frame=frame,
                     key=key, width=size[0], height=size[1])
            good = False
        missing = [c for c in spec.channels if c not in chans]
        if missing:
            c.add("bad-channels", f"{path}: lacks channel(s) {', '.join(missing)} (has "
                                     f"{', '.join(sorted(chans)) or 'none'}; {name} needs "
                                     f"{', '.join(spec.channels)})", frame=frame, key=key)
            good = False
        extra = sorted(c for c in chans if c not in spec.channels)
        if extra:
            c.add("extra-channels", f"{path}: unexpected channel(s) {', '.join(extra)}", frame=frame,
                     key=key, severity=WARNING)
        if header_only or not good:
            continue
        arrs = [chans[c] for c in spec.channels]
        kinds = {a.dtype.kind for a in arrs}
        if spec.dtype == "uint32":
            if any(a.dtype != np.uint32 for a in arrs):
                c.add("bad-dtype", f"{path}: {name} stored as {arrs[0].dtype}, must be uint32", frame=frame,
                         key=key)
                continue
            out[name] = np.stack(arrs, axis=-1)
        else:
            if kinds != {"f"}:
                c.add("bad-dtype", f"{path}: {name} stored as {arrs[0].dtype}, must be float (half or "
                                      "float32)", frame=frame, key=key)
                continue
            if name == "radiance" and any(a.dtype != np.float32 for a in arrs):
                c.add("bad-dtype", f"{path}: radiance stored as {arrs[0].dtype}, must be float32 (half overflows "
                                   "at 65504)", frame=frame, key=key)
                continue
            out[name] = np.stack([a.astype(np.float32, copy=False) for a in arrs], axis=-1)
    return out
