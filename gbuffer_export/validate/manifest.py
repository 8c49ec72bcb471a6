"""Checks of the clip as a whole: the manifest (JSON, schema, version, header keys, level sizes, buffer names)
and its frames (every planned frame finished, ``frames/`` records merged, no files of unfinished frames, no
leftover temporary files)."""
from __future__ import annotations

import json
import re
from pathlib import Path

from ..clip import FRAMES_DIR, MANIFEST, ClipError, frame_name, header_identity, load_manifest
from ..colour_spaces import DEFAULT_WORKING_SPACE, WORKING_SPACES
from ..conventions import BUFFERS, LEVELS, SCHEMA, SCHEMA_VERSION, is_level_name, level_name
from .report import WARNING, Collector, as_int, json_safe

_HEADER_KEYS = ("scale", "levels", "frames", "buffers", "blender_version", "blendsr_version", "scene", "render",
                "frame_data")
_TEMP_RE = re.compile(r"^\..+\.tmp\d+")


def check_manifest(c: Collector) -> dict | None:
    """The manifest as a dict, or None when it is missing, unreadable or refused by the clip reader."""
    mpath = c.root / MANIFEST
    if mpath.is_symlink():
        c.add("unsafe-link", f"{mpath}: is a symbolic link; BlendSR reads nothing through links inside a clip")
        return None
    if not mpath.is_file():
        c.add("manifest-missing", f"{mpath}: no manifest (not a BlendSR clip, or no frame finished yet)")
        return None
    try:
        manifest = json.loads(mpath.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        c.add("manifest-invalid", f"{mpath}: not valid JSON ({exc})")
        return None
    if not isinstance(manifest, dict) or manifest.get("schema") != SCHEMA:
        c.add("manifest-invalid", f"{mpath}: not a BlendSR clip manifest (schema is not {SCHEMA!r})")
        return None
    version = manifest.get("schema_version")
    if as_int(version) is None:
        c.add("manifest-invalid", f"{mpath}: schema_version {version!r} is not an integer")
        return None
    if version > SCHEMA_VERSION:
        c.add("schema-newer", f"{mpath}: schema_version {version} is newer than this blendsr reads "
                                 f"({SCHEMA_VERSION}); upgrade blendsr", version=version)
        return None
    missing = [k for k in _HEADER_KEYS if k not in manifest]
    if missing:
        c.add("manifest-incomplete", f"{mpath}: manifest lacks {', '.join(repr(k) for k in missing)}",
                 missing=missing)
    try:  # the reader's own contract: anything it refuses is a finding too
        load_manifest(c.root)
    except ClipError as exc:
        if not missing:
            c.add("manifest-invalid", str(exc).splitlines()[0])
        return None
    check_identity(c, manifest)
    return manifest


def check_identity(c: Collector, m: dict) -> None:
    """``manifest-identity``: the stored ``identity`` is the hash of the header the clip was rendered with
    (``clip.header_identity``: every key but ``VOLATILE_KEYS``, an auto exposure's request but not its metering);
    a deleted, nulled or edited ``exposure`` (or any other covered field) changes it."""
    mpath = c.root / MANIFEST
    stored = m.get("identity")
    try:
        expect = header_identity(m)
    except (TypeError, ValueError) as exc:
        c.add("manifest-identity", f"{mpath}: the header cannot be hashed ({exc})", key="identity")
        return
    if stored is None:
        c.add("manifest-identity", f"{mpath}: manifest lacks its 'identity' (the hash of its header); a clip "
              "whose identity was removed cannot prove its header is the one it was rendered with", key="identity")
    elif stored != expect:
        c.add("manifest-identity", f"{mpath}: identity {stored!r} is not the hash of the header ({expect!r}): a "
              "field the identity covers (exposure, render, scene, levels, buffers, frames, ...) was edited, "
              "added or removed after rendering", key="identity", stored=stored, expected=expect)


def check_header(c: Collector, m: dict) -> dict | None:
    """Parse scale, level sizes, buffers and planned frames; None when file checks cannot proceed."""
    mpath = c.root / MANIFEST
    fatal = False
    scale = m.get("scale")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not scale >= 1:
        c.add("manifest-invalid", f"{mpath}: scale {m.get('scale')!r} is not a number >= 1")
        fatal = True
    space = m.get("scene_linear", DEFAULT_WORKING_SPACE)
    if space not in WORKING_SPACES:  # the clip reads as stored, but training cannot convert it to its space
        c.add("manifest-colour-space", f"{mpath}: scene_linear {space!r} is not a working space training converts "
                                       f"({', '.join(WORKING_SPACES)})", severity=WARNING)
    sizes, scales, levels_ok = _check_levels(c, mpath, m.get("levels"), scale)
    fatal = fatal or not levels_ok
    if not fatal:
        _check_level_scales(c, mpath, sizes, scales, scale)
    buffers = _check_buffers(c, mpath, m.get("buffers"))
    fatal = fatal or buffers is None
    planned = m.get("frames")
    if not isinstance(planned, list) or any(as_int(f) is None for f in planned):
        c.add("manifest-invalid", f"{mpath}: frames is not a list of integers")
        planned = []
    planned = [as_int(f) for f in planned]
    fd = m.get("frame_data")
    if not isinstance(fd, dict) or any(not str(k).lstrip("-").isdigit() or not isinstance(v, dict)
                                       for k, v in fd.items()):
        c.add("manifest-invalid", f"{mpath}: frame_data is not an object of frame number -> record")
        fatal = True
    if fatal:
        return None
    return {"scale": scale, "scales": scales, "sizes": sizes, "buffers": buffers, "planned": planned,
            "frame_data": {int(k): v for k, v in fd.items()}}


def _check_levels(c: Collector, mpath, levels, scale) -> tuple[dict[str, tuple[int, int]], dict[str, float], bool]:
    """Each level's size and scale (``hr``'s is 1; version 1's ``lr`` takes the clip's ``scale``), and whether all
    were readable (False: file checks cannot proceed)."""
    sizes: dict[str, tuple[int, int]] = {}
    scales: dict[str, float] = {"hr": 1.0}
    ok = True
    if not isinstance(levels, dict):
        c.add("manifest-invalid", f"{mpath}: levels is not an object")
        ok, levels = False, {}
    for lvl in (*LEVELS, *(k for k in levels if k not in LEVELS)):
        v = levels.get(lvl)
        if not is_level_name(lvl):
            c.add("manifest-invalid", f"{mpath}: level name {lvl!r} is not hr, lr or lr_x<scale>", key=lvl)
            ok = False
            continue
        if not isinstance(v, dict) or "width" not in v or "height" not in v:
            c.add("manifest-incomplete", f"{mpath}: levels lacks {lvl!r} with width and height", key=lvl)
            ok = False
            continue
        w, h = as_int(v["width"]), as_int(v["height"])
        if w is None or h is None or w < 1 or h < 1:
            c.add("manifest-invalid", f"{mpath}: level {lvl} size {v['width']!r}x{v['height']!r} "
                                         "is not positive integers", key=lvl)
            ok = False
            continue
        sizes[lvl] = (w, h)
        if lvl == "hr":
            continue
        ls = v.get("scale", scale if lvl == "lr" else None)  # version 1: lr is at the top-level scale
        if isinstance(ls, bool) or not isinstance(ls, (int, float)) or not ls >= 1:
            c.add("manifest-invalid", f"{mpath}: level {lvl} scale {ls!r} is not a number >= 1", key=lvl)
            ok = False
            continue
        scales[lvl] = float(ls)
    return sizes, scales, ok


def _check_level_scales(c: Collector, mpath, sizes: dict, scales: dict, scale) -> None:
    """Each LR level against the clip: lr at the clip's scale, the others named by their scale, sizes that fit."""
    for lvl, ls in scales.items():
        if lvl == "hr":
            continue
        if lvl == "lr" and ls != float(scale):
            c.add("manifest-inconsistent", f"{mpath}: level lr has scale {ls:g} but the clip's scale is "
                                           f"{scale:g}", key=lvl)
        elif lvl != "lr" and level_name(ls, scales["lr"]) != lvl:
            c.add("manifest-inconsistent", f"{mpath}: level {lvl} has scale {ls:g}; its name must be "
                                           f"{level_name(ls, scales['lr'])!r}", key=lvl)
        (wh, hh), (wl, hl) = sizes["hr"], sizes[lvl]
        if abs(wl * ls - wh) > 1e-6 * wh or abs(hl * ls - hh) > 1e-6 * hh:
            c.add("manifest-inconsistent", f"{mpath}: hr size {wh}x{hh} != {lvl} size {wl}x{hl} x scale {ls:g}",
                  key=lvl)


def _check_buffers(c: Collector, mpath, raw_buffers) -> list[str] | None:
    """The known buffers the manifest lists (unknown ones and a missing radiance reported); None: not a list."""
    if not isinstance(raw_buffers, list):
        c.add("manifest-invalid", f"{mpath}: buffers is not a list")
        return None
    unknown = [b for b in raw_buffers if b not in BUFFERS]
    if unknown:
        c.add("manifest-inconsistent", f"{mpath}: unknown buffer(s) {unknown}; known: {', '.join(BUFFERS)}")
    buffers = [b for b in raw_buffers if b in BUFFERS]
    if "radiance" not in buffers:
        c.add("manifest-inconsistent", f"{mpath}: buffers lack 'radiance'")
    return buffers


def check_frames(c: Collector, h: dict) -> list[int]:
    """Completeness of the clip as a whole; returns the finished frames (ascending)."""
    fd = h["frame_data"]
    finished = sorted(fd)
    planned = h["planned"]
    c.stats["frames_planned"] = len(planned)
    c.stats["frames_finished"] = len(finished)
    if not finished:
        c.add("no-frames", f"{c.root}: no finished frame ({len(planned)} planned)")
    missing = [f for f in planned if f not in fd]
    for f in missing:
        c.add("missing-frame", f"planned frame {f} has no record (not rendered yet, or the clip is "
                                  "half-written)", frame=f)
    pset = set(planned)
    for f in finished:
        if f not in pset:
            c.add("unplanned-frame", f"finished frame {f} is not among the {len(planned)} planned frames",
                     frame=f, severity=WARNING)
    for tp in sorted(c.root.glob(".render-*")):  # the renderer's scratch folders (render.py removes its own)
        c.add("leftover-temp", f"{tp}: scratch folder of an interrupted render (the next render of this clip "
                               "removes it)", severity=WARNING)
    rdir = c.root / FRAMES_DIR
    on_disk = _check_frame_records(c, rdir, fd)
    for f in finished:
        if f not in on_disk:
            c.add("missing-record", f"{rdir / (frame_name(f) + '.json')}: missing; the manifest lists "
                                       f"frame {f} but a later merge would drop it", frame=f)
    _check_orphan_buffers(c, fd)
    return finished


def _check_frame_records(c: Collector, rdir: Path, fd: dict) -> set[int]:
    """The records under ``frames/`` against the manifest's; returns the frames with a readable record."""
    on_disk: set[int] = set()
    if rdir.is_symlink():
        c.add("unsafe-link", f"{rdir}: is a symbolic link; its records are not read")
        return on_disk
    if not rdir.is_dir():
        return on_disk
    for rp in sorted(rdir.iterdir()):
        if rp.is_symlink():
            c.add("unsafe-link", f"{rp}: is a symbolic link; not read")
            continue
        if _TEMP_RE.match(rp.name):
            c.add("leftover-temp", f"{rp}: temporary file of an interrupted write", severity=WARNING)
            continue
        if rp.suffix != ".json" or not rp.stem.lstrip("-").isdigit():
            continue
        f = int(rp.stem)
        try:
            rec = json.loads(rp.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            c.add("incomplete-frame", f"{rp}: torn record (not valid JSON)", frame=f)
            continue
        on_disk.add(f)
        if f not in fd:
            c.add("manifest-stale", f"{rp}: frame {f} is recorded in {FRAMES_DIR}/ but not in the "
                                       "manifest (manifest not merged)", frame=f)
        elif json_safe(rec) != json_safe(fd[f]):
            c.add("manifest-stale", f"{rp}: record differs from the manifest's record of frame {f}", frame=f)
    return on_disk


def _check_orphan_buffers(c: Collector, fd: dict) -> None:
    """Buffer files of frames that are not finished, and temporary files, under every level folder."""
    orphans: dict[int, list[str]] = {}
    for ldir in sorted(p for p in c.root.iterdir() if p.is_dir() and is_level_name(p.name)):
        lvl = ldir.name
        if ldir.is_symlink():
            continue  # read_level reports the link at every buffer under it
        for bdir in sorted(p for p in ldir.iterdir() if p.is_dir() and not p.is_symlink()):
            for fp in bdir.iterdir():
                if _TEMP_RE.match(fp.name):
                    c.add("leftover-temp", f"{fp}: temporary file of an interrupted write", severity=WARNING,
                             key=f"{lvl}/{bdir.name}")
                    continue
                if fp.suffix != ".exr" or not fp.stem.lstrip("-").isdigit():
                    continue
                f = int(fp.stem)
                if f not in fd:
                    orphans.setdefault(f, []).append(f"{lvl}/{bdir.name}")
    for f in sorted(orphans):
        keys = orphans[f]
        c.add("incomplete-frame", f"{len(keys)} buffer file(s) of frame {f} exist ({', '.join(keys[:4])}"
                                     f"{', ...' if len(keys) > 4 else ''}) but the frame is not finished",
                 frame=f, files=len(keys))
