"""Clip validation (``blendsr validate``): is a clip on disk complete, readable and consistent with the conventions?

Pure numpy + json + OpenEXR (no bpy, no torch). ``validate_clip(path)`` never raises for a broken clip: every
problem becomes a ``Finding`` with a stable ``code`` (see ``CODES``), a severity and a one-line message naming the
file, frame, buffer and the numbers measured. It raises ``ClipError`` only when ``path`` is not a directory.

Checks, in order:
    manifest   loads (JSON, schema, version), header keys, level sizes (hr = lr * scale), buffer names;
    frames     every planned frame finished; ``frames/`` records merged into the manifest; no buffer files or torn
               records of unfinished frames (a half-written clip never passes); leftover temporary files;
    records    per frame and level: cameras (4x4 rigid), intrinsics (positive focal), jitter in [-0.5, 0.5] px,
               spp, seed, seconds; hr and lr describe the same camera (lr intrinsics = hr / scale);
    files      every buffer of every checked frame at both levels exists, is a readable EXR with the level's size,
               the channels of ``BUFFERS`` and the right sample type (flags uint32);
    values     finite; depth > 0 on surfaces and +inf exactly on background; unit normals on surfaces, zero on
               background; fbeta in [0, fbeta_max] on surfaces and 1 on background; material buffers in [0, 1];
               emission >= 0; only known flag bits;
    motion     stored motion against ``reprojection_motion`` from the stored depth and cameras on static surface
               pixels (neither MOVING nor ALPHA: an alpha-blended pixel's Vector pass averages the layers its samples
               stopped at, its depth is sample 0's), and against the rotation-only motion on background pixels (fractions within tolerance);
               ``motion_next`` the same way towards the next camera (``gbuffer_export.forward_motion``).
"""
from __future__ import annotations

import contextlib
import io
import json
import math
import re
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import OpenEXR

from .clip import FRAMES_DIR, MANIFEST, ClipError, buffer_path, frame_name, load_manifest
from .conventions import BUFFERS, LEVELS, SCHEMA, SCHEMA_VERSION, Flag, reprojection_motion
from .demod import RADIANCE_CAP
from .forward_motion import CODES as _FORWARD_MOTION_CODES, check_motion_next

ERROR = "error"
WARNING = "warning"

#: Every finding code, with what it means. Codes are stable identifiers: scripts may match on them.
CODES: dict[str, str] = {
    # manifest and frames
    "manifest-missing": "CLIP/manifest.json does not exist",
    "manifest-invalid": "manifest is not valid JSON, not a BlendSR manifest, or a header value has the wrong type",
    "schema-newer": "manifest schema_version is newer than this blendsr reads",
    "manifest-incomplete": "a required header key is missing",
    "manifest-inconsistent": "header values contradict each other (hr size != lr size * scale, unknown buffer)",
    "no-frames": "the clip has no finished frame",
    "missing-frame": "a planned frame has no record (not rendered, or the clip is half-written)",
    "unplanned-frame": "a finished frame is not among the planned frames",
    "manifest-stale": "a frames/ record is absent from the manifest or differs from it (manifest not merged)",
    "missing-record": "a frame of the manifest has no frames/ record (a later merge would drop it)",
    "incomplete-frame": "buffer files or a torn record of a frame that is not finished",
    "leftover-temp": "a temporary file of an interrupted write",
    # frame records
    "record-incomplete": "a frame record lacks a level or a key",
    "bad-camera": "a camera matrix or intrinsics is malformed (shape, non-finite, not rigid, focal <= 0)",
    "jitter-range": "jitter is not two finite numbers in [-0.5, 0.5] px",
    "bad-record": "spp, seed or seconds has the wrong type or value",
    "level-mismatch": "hr and lr records describe different cameras (lr intrinsics != hr intrinsics / scale)",
    # files
    "missing-buffer": "a buffer file of a finished frame does not exist",
    "truncated-exr": "a buffer file is not a readable EXR (truncated or foreign)",
    "bad-size": "a buffer file does not have its level's width x height",
    "bad-channels": "a buffer file lacks channels that BUFFERS requires",
    "extra-channels": "a buffer file has channels beyond those BUFFERS lists",
    "bad-dtype": "a buffer file has the wrong sample type (flags must be uint32, others float)",
    # values
    "non-finite": "NaN or Inf in a buffer (Inf allowed only in depth on background)",
    "implausible-value": "radiance or emission beyond +-RADIANCE_CAP (1e9), which no scene produces (warning)",
    "depth-range": "depth <= 0 on a surface pixel",
    "depth-inf-on-surface": "depth is +inf where flags do not mark background (or not finite where no flags)",
    "depth-finite-on-background": "depth is finite where flags mark background (Blender's 1e10 not converted?)",
    "non-unit-normal": "too many surface normals are not unit length (ALPHA-flagged pixels: a warning)",
    "normal-on-background": "normals are not zero on background pixels",
    "fbeta-range": "fbeta outside [0, fbeta_max] on surface pixels",
    "fbeta-background": "fbeta is not 1 on background pixels",
    "value-range": "a material buffer outside its range (albedo/roughness/metallic/specular [0,1], emission >= 0)",
    "flags-range": "flags hold unknown bits",
    # motion
    "motion-reprojection": "stored motion disagrees with reprojection from depth and cameras on static surfaces",
    "background-motion": "background motion is not the camera's rotation-only motion",
    **_FORWARD_MOTION_CODES,  # motion_next (gbuffer_export.forward_motion)
}

_KNOWN_FLAG_BITS = 0
for _f in Flag:
    _KNOWN_FLAG_BITS |= int(_f)
_HEADER_KEYS = ("scale", "levels", "frames", "buffers", "blender_version", "blendsr_version", "scene", "render",
                "frame_data")
_RECORD_KEYS = ("world_from_camera", "prev_world_from_camera", "intrinsics", "prev_intrinsics", "jitter", "spp",
                "seed", "seconds")
_TEMP_RE = re.compile(r"^\..+\.tmp\d+")


@dataclass(frozen=True)
class ValidationOptions:
    """Tolerances of the value and motion checks.

    motion_tol_px: hr motion tolerance, pixels of the hr level (|stored - reprojected| <= tol counts as agreeing).
    lr_motion_tol_px: lr tolerance in pixels of the lr level; None uses ``motion_tol_px`` (each level's motion is
        checked against that level's own point-sampled depth, so the error sources are per pixel of the level).
    motion_min_fraction: least fraction of static surface pixels that must agree (edges may disagree).
    background_min_fraction: least fraction of background pixels that must carry the rotation-only motion.
    normal_tol / normal_min_fraction: | |n| - 1 | < normal_tol on at least this fraction of surface pixels.
    fbeta_max: upper end of the plausible fbeta range on surfaces; fbeta_max_outside: fraction of surface pixels
        allowed outside [0, fbeta_max] before it is an error (any pixel outside is a warning).
    range_eps: slack of the [0, 1] and >= 0 range checks (float rounding).
    background_eps: tolerance of "zero normal" and "fbeta == 1" on background pixels.
    min_pixels: fewer pixels than this in a motion class gives no finding (fraction too noisy).
    """

    motion_tol_px: float = 0.05
    lr_motion_tol_px: float | None = None
    motion_min_fraction: float = 0.8
    background_min_fraction: float = 0.9
    normal_tol: float = 1e-2
    normal_min_fraction: float = 0.99
    fbeta_max: float = 1.05
    fbeta_max_outside: float = 1e-3
    range_eps: float = 1e-4
    background_eps: float = 1e-3
    min_pixels: int = 8

    def __post_init__(self):
        for name in ("motion_tol_px", "normal_tol", "fbeta_max", "range_eps", "background_eps"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"validation option {name}={v!r}: must be a positive number")
        if self.lr_motion_tol_px is not None and not (math.isfinite(self.lr_motion_tol_px)
                                                      and self.lr_motion_tol_px > 0):
            raise ValueError(f"validation option lr_motion_tol_px={self.lr_motion_tol_px!r}: must be positive")
        for name in ("motion_min_fraction", "background_min_fraction", "normal_min_fraction", "fbeta_max_outside"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v <= 1.0):
                raise ValueError(f"validation option {name}={v!r}: must be a fraction in [0, 1]")
        if not (isinstance(self.min_pixels, int) and self.min_pixels >= 1):
            raise ValueError(f"validation option min_pixels={self.min_pixels!r}: must be an integer >= 1")

    def tol_px(self, level: str) -> float:
        """Motion tolerance of ``level`` in pixels of that level."""
        if level == "lr" and self.lr_motion_tol_px is not None:
            return float(self.lr_motion_tol_px)
        return float(self.motion_tol_px)


@dataclass
class Finding:
    """One problem. ``key`` is '<level>/<buffer>' (or '<level>' for camera records); ``details`` holds the
    measured numbers (counts, fractions, pixels) behind the message."""

    code: str
    severity: str
    message: str
    frame: int | None = None
    key: str | None = None
    details: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        if self.code not in CODES:
            raise ValueError(f"unknown finding code {self.code!r}")
        if self.severity not in (ERROR, WARNING):
            raise ValueError(f"unknown severity {self.severity!r}")

    def line(self) -> str:
        """'ERROR frame 12 hr/normal: message' (frame and key omitted when absent)."""
        where = []
        if self.frame is not None:
            where.append(f"frame {self.frame}")
        if self.key:
            where.append(self.key)
        prefix = " ".join(where) if where else "clip"
        return f"{self.severity.upper()} {prefix}: {self.message} [{self.code}]"

    def to_dict(self) -> dict:
        return _json_safe(asdict(self))


@dataclass
class ValidationReport:
    """Result of ``validate_clip``: the findings and summary statistics (counts, timings, motion agreement)."""

    path: str
    findings: list[Finding]
    stats: dict[str, Any]

    @property
    def errors(self) -> list[Finding]:
        return [f for f in self.findings if f.severity == ERROR]

    @property
    def warnings(self) -> list[Finding]:
        return [f for f in self.findings if f.severity == WARNING]

    @property
    def ok(self) -> bool:
        """True when no finding is an error (warnings allowed)."""
        return not self.errors

    def codes(self, severity: str | None = None) -> set[str]:
        return {f.code for f in self.findings if severity is None or f.severity == severity}

    def summary_line(self) -> str:
        s = self.stats
        verdict = "OK" if self.ok else "FAILED"
        parts = [f"{verdict}: {self.path}", f"{len(self.errors)} error(s), {len(self.warnings)} warning(s)",
                 f"{s.get('frames_checked', 0)}/{s.get('frames_finished', 0)} finished frames checked "
                 f"({s.get('frames_planned', 0)} planned)"]
        for lvl in LEVELS:
            m = s.get("levels", {}).get(lvl, {}).get("motion", {})
            if m.get("static_fraction_min") is not None:
                parts.append(f"{lvl} motion agrees on >= {100 * m['static_fraction_min']:.1f}% of static pixels "
                             f"(worst median {m['static_median_px_max']:.3g} px)")
        parts.append(f"{s.get('seconds', 0.0):.2f} s")
        return "; ".join(parts)

    def to_dict(self) -> dict:
        return _json_safe({"path": self.path, "ok": self.ok, "errors": len(self.errors),
                           "warnings": len(self.warnings), "findings": [f.to_dict() for f in self.findings],
                           "stats": self.stats})


def _json_safe(obj):
    """Replace NaN/Inf by None and numpy scalars by Python ones, recursively (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


# ----------------------------------------------------------------------------------------------------------------
# EXR reading that tells truncation apart from missing channels
# ----------------------------------------------------------------------------------------------------------------

class _ExrProblem(Exception):
    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


def _read_exr_all(path: Path, header_only: bool = False) -> tuple[tuple[int, int], dict[str, np.ndarray | str]]:
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
        raise _ExrProblem("truncated-exr", f"not a readable EXR ({str(exc).splitlines()[0] if str(exc) else exc})")
    if header_only:
        return size, {n: "" for n in names}
    said = io.StringIO()  # the bindings print (to sys.stdout) why pixel data could not be read
    try:
        with contextlib.redirect_stdout(said), OpenEXR.File(str(path), separate_channels=True) as f:
            chans = {name: np.asarray(ch.pixels) for name, ch in f.parts[0].channels.items()} if f.parts else {}
    except Exception as exc:
        raise _ExrProblem("truncated-exr", f"not a readable EXR ({str(exc).splitlines()[0] if str(exc) else exc})")
    if names and not chans:
        why = said.getvalue().strip().splitlines()
        raise _ExrProblem("truncated-exr", f"truncated EXR: header lists {', '.join(names)} but the pixel data "
                                           f"cannot be read{' (' + why[-1] + ')' if why else ''}")
    return size, chans


# ----------------------------------------------------------------------------------------------------------------
# The validator
# ----------------------------------------------------------------------------------------------------------------

def _as_int(v) -> int | None:
    if isinstance(v, bool):
        return None
    if isinstance(v, int):
        return v
    if isinstance(v, float) and v.is_integer():
        return int(v)
    return None


def _fmt_frac(x: float) -> str:
    return f"{100.0 * x:.3g}%"


class _Validator:
    def __init__(self, root: Path, options: ValidationOptions):
        self.root = root
        self.opt = options
        self.findings: list[Finding] = []
        self.stats: dict[str, Any] = {"frames_planned": 0, "frames_finished": 0, "frames_checked": 0,
                                      "frames_value_checked": 0, "files_read": 0, "files_header_only": 0,
                                      "options": asdict(options), "levels": {}, "per_frame": {}}
        self.level_acc: dict[str, dict[str, list]] = {}

    # -------------------------------------------------------------------------------------------------- findings
    def add(self, code: str, message: str, *, frame: int | None = None, key: str | None = None,
            severity: str = ERROR, **details) -> None:
        self.findings.append(Finding(code, severity, message, frame, key, details))

    # -------------------------------------------------------------------------------------------------- manifest
    def load_manifest(self) -> dict | None:
        mpath = self.root / MANIFEST
        if not mpath.is_file():
            self.add("manifest-missing", f"{mpath}: no manifest (not a BlendSR clip, or no frame finished yet)")
            return None
        try:
            manifest = json.loads(mpath.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            self.add("manifest-invalid", f"{mpath}: not valid JSON ({exc})")
            return None
        if not isinstance(manifest, dict) or manifest.get("schema") != SCHEMA:
            self.add("manifest-invalid", f"{mpath}: not a BlendSR clip manifest (schema is not {SCHEMA!r})")
            return None
        version = manifest.get("schema_version")
        if _as_int(version) is None:
            self.add("manifest-invalid", f"{mpath}: schema_version {version!r} is not an integer")
            return None
        if version > SCHEMA_VERSION:
            self.add("schema-newer", f"{mpath}: schema_version {version} is newer than this blendsr reads "
                                     f"({SCHEMA_VERSION}); upgrade blendsr", version=version)
            return None
        missing = [k for k in _HEADER_KEYS if k not in manifest]
        if missing:
            self.add("manifest-incomplete", f"{mpath}: manifest lacks {', '.join(repr(k) for k in missing)}",
                     missing=missing)
        try:  # the reader's own contract: anything it refuses is a finding too
            load_manifest(self.root)
        except ClipError as exc:
            if not missing:
                self.add("manifest-invalid", str(exc).splitlines()[0])
            return None
        return manifest

    def check_header(self, m: dict) -> dict | None:
        """Parse scale, level sizes, buffers and planned frames; None when file checks cannot proceed."""
        mpath = self.root / MANIFEST
        fatal = False
        scale = _as_int(m.get("scale"))
        if scale is None or scale < 1:
            self.add("manifest-invalid", f"{mpath}: scale {m.get('scale')!r} is not a positive integer")
            fatal = True
        sizes: dict[str, tuple[int, int]] = {}
        levels = m.get("levels")
        if not isinstance(levels, dict):
            self.add("manifest-invalid", f"{mpath}: levels is not an object")
            fatal = True
            levels = {}
        for lvl in LEVELS:
            v = levels.get(lvl)
            if not isinstance(v, dict) or "width" not in v or "height" not in v:
                self.add("manifest-incomplete", f"{mpath}: levels lacks {lvl!r} with width and height", key=lvl)
                fatal = True
                continue
            w, h = _as_int(v["width"]), _as_int(v["height"])
            if w is None or h is None or w < 1 or h < 1:
                self.add("manifest-invalid", f"{mpath}: level {lvl} size {v['width']!r}x{v['height']!r} "
                                             "is not positive integers", key=lvl)
                fatal = True
                continue
            sizes[lvl] = (w, h)
        if not fatal and (sizes["hr"][0] != sizes["lr"][0] * scale or sizes["hr"][1] != sizes["lr"][1] * scale):
            self.add("manifest-inconsistent",
                     f"{mpath}: hr size {sizes['hr'][0]}x{sizes['hr'][1]} != lr size "
                     f"{sizes['lr'][0]}x{sizes['lr'][1]} x scale {scale}")
        raw_buffers = m.get("buffers")
        buffers: list[str] = []
        if not isinstance(raw_buffers, list):
            self.add("manifest-invalid", f"{mpath}: buffers is not a list")
            fatal = True
        else:
            unknown = [b for b in raw_buffers if b not in BUFFERS]
            if unknown:
                self.add("manifest-inconsistent", f"{mpath}: unknown buffer(s) {unknown}; known: {', '.join(BUFFERS)}")
            buffers = [b for b in raw_buffers if b in BUFFERS]
            if "radiance" not in buffers:
                self.add("manifest-inconsistent", f"{mpath}: buffers lack 'radiance'")
        planned = m.get("frames")
        if not isinstance(planned, list) or any(_as_int(f) is None for f in planned):
            self.add("manifest-invalid", f"{mpath}: frames is not a list of integers")
            planned = []
        planned = [_as_int(f) for f in planned]
        fd = m.get("frame_data")
        if not isinstance(fd, dict) or any(not str(k).lstrip("-").isdigit() or not isinstance(v, dict)
                                           for k, v in fd.items()):
            self.add("manifest-invalid", f"{mpath}: frame_data is not an object of frame number -> record")
            fatal = True
        if fatal:
            return None
        return {"scale": scale, "sizes": sizes, "buffers": buffers, "planned": planned,
                "frame_data": {int(k): v for k, v in fd.items()}}

    # ---------------------------------------------------------------------------------------------------- frames
    def check_frames(self, h: dict) -> list[int]:
        """Completeness of the clip as a whole; returns the finished frames (ascending)."""
        fd = h["frame_data"]
        finished = sorted(fd)
        planned = h["planned"]
        self.stats["frames_planned"] = len(planned)
        self.stats["frames_finished"] = len(finished)
        if not finished:
            self.add("no-frames", f"{self.root}: no finished frame ({len(planned)} planned)")
        missing = [f for f in planned if f not in fd]
        for f in missing:
            self.add("missing-frame", f"planned frame {f} has no record (not rendered yet, or the clip is "
                                      "half-written)", frame=f)
        pset = set(planned)
        for f in finished:
            if f not in pset:
                self.add("unplanned-frame", f"finished frame {f} is not among the {len(planned)} planned frames",
                         frame=f, severity=WARNING)
        # frames/ records against the manifest
        rdir = self.root / FRAMES_DIR
        on_disk: set[int] = set()
        if rdir.is_dir():
            for rp in sorted(rdir.iterdir()):
                if _TEMP_RE.match(rp.name):
                    self.add("leftover-temp", f"{rp}: temporary file of an interrupted write", severity=WARNING)
                    continue
                if rp.suffix != ".json" or not rp.stem.lstrip("-").isdigit():
                    continue
                f = int(rp.stem)
                try:
                    rec = json.loads(rp.read_text())
                except (json.JSONDecodeError, UnicodeDecodeError):
                    self.add("incomplete-frame", f"{rp}: torn record (not valid JSON)", frame=f)
                    continue
                on_disk.add(f)
                if f not in fd:
                    self.add("manifest-stale", f"{rp}: frame {f} is recorded in {FRAMES_DIR}/ but not in the "
                                               "manifest (manifest not merged)", frame=f)
                elif _json_safe(rec) != _json_safe(fd[f]):
                    self.add("manifest-stale", f"{rp}: record differs from the manifest's record of frame {f}",
                             frame=f)
        for f in finished:
            if f not in on_disk:
                self.add("missing-record", f"{rdir / (frame_name(f) + '.json')}: missing; the manifest lists "
                                           f"frame {f} but a later merge would drop it", frame=f)
        # buffer files of frames that are not finished; temporary files
        orphans: dict[int, list[str]] = {}
        for lvl in LEVELS:
            ldir = self.root / lvl
            if not ldir.is_dir():
                continue
            for bdir in sorted(p for p in ldir.iterdir() if p.is_dir()):
                for fp in bdir.iterdir():
                    if _TEMP_RE.match(fp.name):
                        self.add("leftover-temp", f"{fp}: temporary file of an interrupted write", severity=WARNING,
                                 key=f"{lvl}/{bdir.name}")
                        continue
                    if fp.suffix != ".exr" or not fp.stem.lstrip("-").isdigit():
                        continue
                    f = int(fp.stem)
                    if f not in fd:
                        orphans.setdefault(f, []).append(f"{lvl}/{bdir.name}")
        for f in sorted(orphans):
            keys = orphans[f]
            self.add("incomplete-frame", f"{len(keys)} buffer file(s) of frame {f} exist ({', '.join(keys[:4])}"
                                         f"{', ...' if len(keys) > 4 else ''}) but the frame is not finished",
                     frame=f, files=len(keys))
        return finished

    # --------------------------------------------------------------------------------------------------- records
    def check_record(self, frame: int, rec: dict, h: dict) -> dict[str, dict] | None:
        """Cameras of both levels as arrays, or None where a level's record is unusable."""
        cams: dict[str, dict] = {}
        for lvl in LEVELS:
            r = rec.get(lvl)
            if not isinstance(r, dict):
                self.add("record-incomplete", f"record lacks level {lvl!r}", frame=frame, key=lvl)
                continue
            missing = [k for k in _RECORD_KEYS if k not in r]
            if missing:
                self.add("record-incomplete", f"record lacks {', '.join(missing)}", frame=frame, key=lvl,
                         missing=missing)
            cam = {}
            ok = True
            for name in ("world_from_camera", "prev_world_from_camera"):
                if name not in r:
                    ok = False
                    continue
                try:
                    a = np.asarray(r[name], dtype=np.float64)
                except (TypeError, ValueError):
                    a = np.zeros(0)
                if a.shape != (4, 4) or not np.all(np.isfinite(a)):
                    self.add("bad-camera", f"{name} is not a finite 4x4 matrix (shape {a.shape})", frame=frame,
                             key=lvl)
                    ok = False
                    continue
                rot = a[:3, :3]
                rig = float(np.max(np.abs(rot.T @ rot - np.eye(3))))
                if not np.allclose(a[3], (0, 0, 0, 1), atol=1e-6) or rig > 1e-4:
                    self.add("bad-camera", f"{name} is not rigid (|R^T R - I| max {rig:.2g}, bottom row "
                                           f"{a[3].tolist()})", frame=frame, key=lvl)
                    ok = False
                    continue
                cam[name] = a
            for name in ("intrinsics", "prev_intrinsics"):
                if name not in r:
                    ok = False
                    continue
                try:
                    k = np.asarray(r[name], dtype=np.float64)
                except (TypeError, ValueError):
                    k = np.zeros(0)
                if k.shape != (4,) or not np.all(np.isfinite(k)) or k[0] <= 0 or k[1] <= 0:
                    self.add("bad-camera", f"{name} {r[name]!r} is not (fx, fy, cx, cy) with positive focal",
                             frame=frame, key=lvl)
                    ok = False
                    continue
                cam[name] = k
            if "jitter" in r:
                try:
                    j = np.asarray(r["jitter"], dtype=np.float64)
                except (TypeError, ValueError):
                    j = np.zeros(0)
                if j.shape != (2,) or not np.all(np.isfinite(j)) or np.any(np.abs(j) > 0.5 + 1e-9):
                    self.add("jitter-range", f"jitter {r['jitter']!r} is not two numbers in [-0.5, 0.5] px",
                             frame=frame, key=lvl)
                else:
                    cam["jitter"] = (float(j[0]), float(j[1]))
            if "spp" in r and (_as_int(r["spp"]) is None or _as_int(r["spp"]) < 1):
                self.add("bad-record", f"spp {r['spp']!r} is not a positive integer", frame=frame, key=lvl)
            if "seed" in r and _as_int(r["seed"]) is None:
                self.add("bad-record", f"seed {r['seed']!r} is not an integer", frame=frame, key=lvl)
            if "seconds" in r and not (isinstance(r["seconds"], dict) or r["seconds"] is None
                                       or (isinstance(r["seconds"], (int, float))
                                           and not isinstance(r["seconds"], bool))):
                self.add("bad-record", f"seconds {r['seconds']!r} is not a number or an object of timings",
                         frame=frame, key=lvl)
            if ok:
                cams[lvl] = cam
        if "hr" in cams and "lr" in cams:
            a, b = cams["hr"], cams["lr"]
            for name in ("world_from_camera", "prev_world_from_camera"):
                d = float(np.max(np.abs(a[name] - b[name])))
                if d > 1e-9 * max(1.0, float(np.max(np.abs(a[name])))):
                    self.add("level-mismatch", f"hr and lr {name} differ (max |diff| {d:.3g})", frame=frame,
                             key="lr", max_diff=d)
            s = h["scale"]
            for name in ("intrinsics", "prev_intrinsics"):
                expect = a[name] / s
                d = float(np.max(np.abs(b[name] - expect)))
                if d > 1e-6 * float(np.max(np.abs(expect))):
                    self.add("level-mismatch", f"lr {name} {b[name].tolist()} != hr {name} / {s} = "
                                               f"{expect.tolist()} (max |diff| {d:.3g} px)", frame=frame, key="lr",
                             max_diff=d)
        return cams

    # ----------------------------------------------------------------------------------------------------- files
    def read_level(self, frame: int, lvl: str, h: dict, header_only: bool) -> dict[str, np.ndarray]:
        """Check the files of one frame and level; return the readable, well-formed buffers (H x W x C)."""
        w, hh = h["sizes"][lvl]
        out: dict[str, np.ndarray] = {}
        for name in h["buffers"]:
            spec = BUFFERS[name]
            key = f"{lvl}/{name}"
            path = buffer_path(self.root, frame, lvl, name)
            if not path.is_file():
                self.add("missing-buffer", f"{path}: missing", frame=frame, key=key)
                continue
            try:
                size, chans = _read_exr_all(path, header_only)
            except _ExrProblem as exc:
                self.add(exc.code, f"{path}: {exc}", frame=frame, key=key)
                continue
            self.stats["files_header_only" if header_only else "files_read"] += 1
            good = True
            if size != (w, hh):
                self.add("bad-size", f"{path}: {size[0]}x{size[1]} px, level {lvl} is {w}x{hh}", frame=frame,
                         key=key, width=size[0], height=size[1])
                good = False
            missing = [c for c in spec.channels if c not in chans]
            if missing:
                self.add("bad-channels", f"{path}: lacks channel(s) {', '.join(missing)} (has "
                                         f"{', '.join(sorted(chans)) or 'none'}; {name} needs "
                                         f"{', '.join(spec.channels)})", frame=frame, key=key)
                good = False
            extra = sorted(c for c in chans if c not in spec.channels)
            if extra:
                self.add("extra-channels", f"{path}: unexpected channel(s) {', '.join(extra)}", frame=frame,
                         key=key, severity=WARNING)
            if header_only or not good:
                continue
            arrs = [chans[c] for c in spec.channels]
            kinds = {a.dtype.kind for a in arrs}
            if spec.dtype == "uint32":
                if any(a.dtype != np.uint32 for a in arrs):
                    self.add("bad-dtype", f"{path}: {name} stored as {arrs[0].dtype}, must be uint32", frame=frame,
                             key=key)
                    continue
                out[name] = np.stack(arrs, axis=-1)
            else:
                if kinds != {"f"}:
                    self.add("bad-dtype", f"{path}: {name} stored as {arrs[0].dtype}, must be float (half or "
                                          "float32)", frame=frame, key=key)
                    continue
                out[name] = np.stack([a.astype(np.float32, copy=False) for a in arrs], axis=-1)
        return out

    # ---------------------------------------------------------------------------------------------------- values
    def check_values(self, frame: int, lvl: str, b: dict[str, np.ndarray]) -> np.ndarray | None:
        """Value checks of one frame and level; returns the surface mask (H x W bool) or None when unknown."""
        o = self.opt
        surface = None
        flags = b.get("flags")
        if flags is not None:
            fl = flags[..., 0]
            unknown = (fl & np.uint32(~_KNOWN_FLAG_BITS & 0xFFFFFFFF)) != 0
            if unknown.any():
                bits = int(np.bitwise_or.reduce(fl[unknown] & np.uint32(~_KNOWN_FLAG_BITS & 0xFFFFFFFF)))
                self.add("flags-range", f"{int(unknown.sum())} pixel(s) carry unknown flag bits 0x{bits:x}",
                         frame=frame, key=f"{lvl}/flags", pixels=int(unknown.sum()), bits=bits)
            surface = (fl & np.uint32(Flag.BACKGROUND)) == 0
        depth = b.get("depth")
        if depth is not None:
            d = depth[..., 0]
            nan = np.isnan(d) | (d == -np.inf)
            if nan.any():
                self.add("non-finite", f"{int(nan.sum())} pixel(s) of depth are NaN or -inf", frame=frame,
                         key=f"{lvl}/depth", pixels=int(nan.sum()))
            inf = d == np.inf
            fin = np.isfinite(d)
            if surface is not None:
                bad = inf & surface
                if bad.any():
                    self.add("depth-inf-on-surface", f"depth is +inf on {int(bad.sum())} pixel(s) that flags mark "
                                                     f"as surface (of {int(surface.sum())})", frame=frame,
                             key=f"{lvl}/depth", pixels=int(bad.sum()))
                bad = fin & ~surface
                if bad.any():
                    self.add("depth-finite-on-background",
                             f"depth is finite on {int(bad.sum())} background pixel(s) (max {float(d[bad].max()):.4g}"
                             "; background must be +inf)", frame=frame, key=f"{lvl}/depth", pixels=int(bad.sum()))
            else:
                surface = fin
            bad = fin & (d <= 0)
            if bad.any():
                self.add("depth-range", f"depth <= 0 on {int(bad.sum())} pixel(s) (min {float(d[bad].min()):.4g})",
                         frame=frame, key=f"{lvl}/depth", pixels=int(bad.sum()))
        for name, arr in b.items():
            if name in ("depth", "flags"):
                continue
            nf = ~np.isfinite(arr)
            if nf.any():
                px = nf.any(axis=-1)
                n_nan = int(np.isnan(arr).any(axis=-1).sum())
                n_inf = int(np.isinf(arr).any(axis=-1).sum())
                self.add("non-finite", f"{int(px.sum())} of {px.size} pixel(s) non-finite ({n_nan} NaN, {n_inf} "
                                       "Inf)", frame=frame, key=f"{lvl}/{name}", pixels=int(px.sum()),
                         nan=n_nan, inf=n_inf)
            if name in ("radiance", "emission"):
                with np.errstate(invalid="ignore"):
                    huge = (np.abs(arr) > RADIANCE_CAP).any(axis=-1)
                if huge.any():
                    self.add("implausible-value", f"{int(huge.sum())} pixel(s) with |value| > {RADIANCE_CAP:.0e}, "
                                                  f"which no scene produces (max {float(np.nanmax(np.abs(arr[huge]))):.4g}"
                                                  "; training treats them as non-finite: data.nonfinite)",
                             frame=frame, key=f"{lvl}/{name}", severity=WARNING, pixels=int(huge.sum()))
        normal = b.get("normal")
        if normal is not None:
            length = np.linalg.norm(normal.astype(np.float64), axis=-1)
            surf = surface if surface is not None else length > 0.5
            if flags is not None:
                # Alpha-blended or cut-out surfaces: Cycles writes depth and indices from the first sample and
                # accumulates the normal only over samples whose hit passes the alpha threshold, so a flagged
                # pixel's normal may be short or zero. Counted apart, as a warning.
                alpha = surf & ((flags[..., 0] & np.uint32(Flag.ALPHA)) != 0)
                short = alpha & ~(np.abs(length - 1.0) < o.normal_tol)
                if short.any():
                    self.add("non-unit-normal", f"{int(short.sum())} of {int(alpha.sum())} ALPHA-flagged pixel(s) "
                                                "have non-unit normals (partial coverage; excluded from the unit-length check)",
                             frame=frame, key=f"{lvl}/normal", severity=WARNING, pixels=int(short.sum()),
                             alpha_pixels=int(alpha.sum()))
                surf = surf & ~alpha
            n_surf = int(surf.sum())
            if n_surf:
                off = ~(np.abs(length[surf] - 1.0) < o.normal_tol)  # NaN counts as off
                frac_ok = 1.0 - float(off.mean())
                if frac_ok < o.normal_min_fraction:
                    self.add("non-unit-normal",
                             f"{_fmt_frac(1 - frac_ok)} of {n_surf} surface pixels have | |n| - 1 | >= "
                             f"{o.normal_tol:g} (need <= {_fmt_frac(1 - o.normal_min_fraction)}; |n| median "
                             f"{float(np.nanmedian(length[surf])):.4g})", frame=frame, key=f"{lvl}/normal",
                             fraction_off=1 - frac_ok, pixels=int(off.sum()))
            if surface is not None:
                bg = ~surface
                bad = bg & ~(length <= o.background_eps)
                if bad.any():
                    self.add("normal-on-background", f"normal is not zero on {int(bad.sum())} of {int(bg.sum())} "
                                                     "background pixel(s)", frame=frame, key=f"{lvl}/normal",
                             pixels=int(bad.sum()))
        fbeta = b.get("fbeta")
        if fbeta is not None:
            surf = surface if surface is not None else np.ones(fbeta.shape[:2], bool)
            n_surf = int(surf.sum())
            if n_surf:
                v = fbeta[surf]
                outside = ~((v >= 0.0) & (v <= o.fbeta_max)).all(axis=-1)
                frac = float(outside.mean())
                if frac > 0:
                    sev = ERROR if frac > o.fbeta_max_outside else WARNING
                    self.add("fbeta-range", f"fbeta outside [0, {o.fbeta_max:g}] on {_fmt_frac(frac)} of {n_surf} "
                                            f"surface pixels (range {float(np.nanmin(v)):.4g}.."
                                            f"{float(np.nanmax(v)):.4g}; error above "
                                            f"{_fmt_frac(o.fbeta_max_outside)})", frame=frame,
                             key=f"{lvl}/fbeta", severity=sev, fraction=frac, pixels=int(outside.sum()))
            if surface is not None:
                bg = ~surface
                bad = bg & ~(np.abs(fbeta - 1.0) <= o.background_eps).all(axis=-1)
                if bad.any():
                    self.add("fbeta-background", f"fbeta is not 1 on {int(bad.sum())} of {int(bg.sum())} background "
                                                 "pixel(s)", frame=frame, key=f"{lvl}/fbeta", pixels=int(bad.sum()))
        eps = o.range_eps
        for name, lo, hi in (("albedo", 0.0, 1.0), ("roughness", 0.0, 1.0), ("metallic", 0.0, 1.0),
                             ("specular", 0.0, 1.0), ("emission", 0.0, None)):
            arr = b.get(name)
            if arr is None:
                continue
            finite = np.isfinite(arr)
            below = (finite & (arr < lo - eps)).any(axis=-1)
            above = (finite & (arr > hi + eps)).any(axis=-1) if hi is not None else np.zeros_like(below)
            if below.any() or above.any():
                rng = f"[{lo:g}, {hi:g}]" if hi is not None else f">= {lo:g}"
                vals = arr[finite]
                # albedo above 1 can come from an HDR texture driving Base Color: suspicious, not impossible
                sev = WARNING if (name == "albedo" and not below.any()) else ERROR
                self.add("value-range", f"{name} outside {rng} on {int((below | above).sum())} pixel(s) (range "
                                        f"{float(vals.min()):.4g}..{float(vals.max()):.4g})", frame=frame,
                         key=f"{lvl}/{name}", severity=sev, pixels=int((below | above).sum()))
        return surface

    # ---------------------------------------------------------------------------------------------------- motion
    def check_motion(self, frame: int, lvl: str, b: dict[str, np.ndarray], cam: dict | None, surface) -> dict:
        """Compare stored motion with reprojection from depth and cameras (static surface pixels) and with the
        rotation-only motion (background pixels); returns this frame's and level's statistics."""
        o = self.opt
        tol = o.tol_px(lvl)
        motion, depth = b.get("motion"), b.get("depth")
        st: dict[str, Any] = {}
        if motion is None or depth is None or cam is None:
            return st
        d = depth[..., 0].astype(np.float64)
        mv = motion.astype(np.float64)
        fin = np.isfinite(d) & (d > 0)
        if surface is None:
            surface = fin
        static = surface & fin
        flags = b.get("flags")
        if flags is not None:
            # Moving objects are not static; alpha-blended pixels mix layers (Cycles averages the Vector pass over
            # samples that pass through or stop at the surface, while depth comes from sample 0 alone).
            static &= (flags[..., 0] & np.uint32(Flag.MOVING | Flag.ALPHA)) == 0
        background = ~surface
        # One call gives both fields: finite depth reprojects, +inf gets the rotation-only motion.
        jitter = cam.get("jitter", (0.0, 0.0))  # depth was sampled at p + jitter (see conventions)
        with np.errstate(all="ignore"):
            exp = reprojection_motion(np.where(static, d, np.inf), cam["intrinsics"], cam["world_from_camera"],
                                      cam["prev_intrinsics"], cam["prev_world_from_camera"], jitter)
        exp_ok = np.isfinite(exp).all(axis=-1)  # points behind the previous camera have no motion
        key = f"{lvl}/motion"
        for cls, mask, need in (("static", static, o.motion_min_fraction),
                                ("background", background, o.background_min_fraction)):
            usable = mask & exp_ok
            n = int(usable.sum())
            st[f"{cls}_pixels"] = n
            if not n:
                continue
            err = np.linalg.norm(mv[usable] - exp[usable], axis=-1)
            err = np.where(np.isfinite(err), err, np.inf)
            frac = float(np.mean(err <= tol))
            med = float(np.median(err))
            st[f"{cls}_fraction"], st[f"{cls}_median_px"] = frac, med
            if n < o.min_pixels or frac >= need:
                continue
            if cls == "static":
                self.add("motion-reprojection",
                         f"motion agrees with reprojection from depth and cameras within {tol:g} px on only "
                         f"{_fmt_frac(frac)} of {n} static surface pixels (need {_fmt_frac(need)}; median error "
                         f"{med:.4g} px)", frame=frame, key=key, fraction=frac, median_px=med, pixels=n)
            else:
                stored = float(np.median(np.linalg.norm(mv[usable], axis=-1)))
                expected = float(np.median(np.linalg.norm(exp[usable], axis=-1)))
                hint = (" (stored background motion is zero, as Blender's Vector pass leaves it: the exporter must "
                        "fill the rotation-only motion)" if stored == 0.0 and expected > tol else "")
                self.add("background-motion",
                         f"background motion matches the camera's rotation-only motion within {tol:g} px on only "
                         f"{_fmt_frac(frac)} of {n} background pixels (need {_fmt_frac(need)}; median error "
                         f"{med:.4g} px, median |stored| {stored:.4g} px, median |expected| {expected:.4g} px)"
                         f"{hint}", frame=frame, key=key, fraction=frac, median_px=med, pixels=n)
        return st

    # ------------------------------------------------------------------------------------------------------- run
    def accumulate(self, lvl: str, b: dict[str, np.ndarray], surface, mst: dict) -> None:
        acc = self.level_acc.setdefault(lvl, {k: [] for k in (
            "surface_fraction", "radiance_mean", "radiance_max", "static_fraction", "static_median_px",
            "static_pixels", "background_fraction", "background_median_px", "background_pixels")})
        if surface is not None:
            acc["surface_fraction"].append(float(surface.mean()))
        rad = b.get("radiance")
        if rad is not None:
            finite = rad[np.isfinite(rad)]
            if finite.size:
                acc["radiance_mean"].append(float(finite.mean()))
                acc["radiance_max"].append(float(finite.max()))
        for k in ("static_fraction", "static_median_px", "static_pixels", "background_fraction",
                  "background_median_px", "background_pixels"):
            if k in mst:
                acc[k].append(mst[k])

    def summarise(self, h: dict | None) -> None:
        for lvl, acc in self.level_acc.items():
            def agg(k, fn):
                return float(fn(acc[k])) if acc[k] else None
            self.stats["levels"][lvl] = {
                "size": list(h["sizes"][lvl]) if h else None,
                "surface_fraction_mean": agg("surface_fraction", np.mean),
                "radiance_mean": agg("radiance_mean", np.mean),
                "radiance_max": agg("radiance_max", np.max),
                "motion": {
                    "tol_px": self.opt.tol_px(lvl),
                    "static_fraction_min": agg("static_fraction", np.min),
                    "static_fraction_mean": agg("static_fraction", np.mean),
                    "static_median_px_max": agg("static_median_px", np.max),
                    "static_pixels": int(sum(acc["static_pixels"])),
                    "background_fraction_min": agg("background_fraction", np.min),
                    "background_fraction_mean": agg("background_fraction", np.mean),
                    "background_median_px_max": agg("background_median_px", np.max),
                    "background_pixels": int(sum(acc["background_pixels"])),
                },
            }

    def run(self, frames: Iterable[int] | None, quick: bool, progress: bool) -> None:
        manifest = self.load_manifest()
        if manifest is None:
            return
        h = self.check_header(manifest)
        if h is None:
            return
        finished = self.check_frames(h)
        if frames is not None:
            wanted = set(int(f) for f in frames)
            selected = [f for f in finished if f in wanted]
            if not selected and finished:
                raise ValueError(f"{self.root}: none of the selected frames is a finished frame of this clip "
                                 f"(finished: {finished[0]}..{finished[-1]})")
        else:
            selected = finished
        full = set(selected) if not quick else ({selected[0], selected[-1]} if selected else set())
        bar = None
        if progress and len(selected) > 3:
            from tqdm import tqdm
            bar = tqdm(total=len(selected), desc="validate", unit="frame", file=sys.stderr, leave=False)
        try:
            for f in selected:
                cams = self.check_record(f, h["frame_data"][f], h)
                per = {}
                for lvl in LEVELS:
                    b = self.read_level(f, lvl, h, header_only=f not in full)
                    if f not in full:
                        continue
                    surface = self.check_values(f, lvl, b)
                    mst = self.check_motion(f, lvl, b, cams.get(lvl), surface)
                    for code, msg, det in check_motion_next(  # motion_next: gbuffer_export.forward_motion
                            b, cams.get(lvl), h["frame_data"][f].get(lvl), surface, tol=self.opt.tol_px(lvl),
                            min_fraction=self.opt.motion_min_fraction, min_pixels=self.opt.min_pixels,
                            background_min_fraction=self.opt.background_min_fraction):
                        self.add(code, msg, frame=f, key=f"{lvl}/motion_next", **det)
                    self.accumulate(lvl, b, surface, mst)
                    if mst:
                        per[lvl] = mst
                if per:
                    self.stats["per_frame"][str(f)] = per
                self.stats["frames_checked"] += 1
                self.stats["frames_value_checked"] += int(f in full)
                if bar is not None:
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        self.summarise(h)


def validate_clip(path: str | Path, *, frames: Iterable[int] | None = None, quick: bool = False,
                  options: ValidationOptions | None = None, progress: bool = False) -> ValidationReport:
    """Validate the clip in directory ``path``.

    frames: check only these frames' records and files (manifest-wide checks still cover the whole clip);
        ValueError when none of them is finished.
    quick: read pixel data (value and motion checks) of the first and last selected frame only; the other frames
        get existence, size and channel checks from the EXR headers.
    progress: show a tqdm bar on stderr when more than 3 frames are checked.
    Raises ClipError only when ``path`` is not a directory; every problem of the clip is a finding.
    """
    root = Path(path)
    if not root.is_dir():
        raise ClipError(f"{root}: not a directory")
    t0 = time.perf_counter()
    v = _Validator(root, options or ValidationOptions())
    v.run(frames, quick, progress)
    v.stats["seconds"] = time.perf_counter() - t0
    v.stats["errors"] = sum(f.severity == ERROR for f in v.findings)
    v.stats["warnings"] = sum(f.severity == WARNING for f in v.findings)
    return ValidationReport(str(root), v.findings, v.stats)


__all__ = ["CODES", "Finding", "ValidationOptions", "ValidationReport", "validate_clip"]
