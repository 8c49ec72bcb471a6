"""Findings and the report: the codes a check may emit (``CODES``), one ``Finding`` per problem, the
``ValidationReport`` of a clip, and the ``Collector`` that every check function adds its findings to."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .options import ValidationOptions


ERROR = "error"
WARNING = "warning"

#: Every finding code, with what it means. Codes are stable identifiers: scripts may match on them.
CODES: dict[str, str] = {
    # manifest and frames
    "manifest-missing": "CLIP/manifest.json does not exist",
    "manifest-invalid": "manifest is not valid JSON, not a BlendSR manifest, or a header value has the wrong type",
    "schema-newer": "manifest schema_version is newer than this blendsr reads",
    "manifest-incomplete": "a required header key is missing",
    "manifest-identity": "the manifest's identity is missing or not the hash of its header (clip.header_identity): "
                         "a field the identity covers (exposure, render, scene, levels, buffers, ...) was edited, "
                         "added or removed after rendering",
    "manifest-colour-space": "scene_linear is a working space training cannot convert into its space (warning)",
    "manifest-inconsistent": "header values contradict each other (hr size != lr size * scale, unknown buffer)",
    "no-frames": "the clip has no finished frame",
    "missing-frame": "a planned frame has no record (not rendered, or the clip is half-written)",
    "unplanned-frame": "a finished frame is not among the planned frames",
    "manifest-stale": "a frames/ record is absent from the manifest or differs from it (manifest not merged)",
    "missing-record": "a frame of the manifest has no frames/ record (a later merge would drop it)",
    "incomplete-frame": "buffer files or a torn record of a frame that is not finished",
    "leftover-temp": "a temporary file or .render-* folder of an interrupted write (warning; the next render of the "
                     "clip removes it)",
    "unsafe-link": "a symbolic link inside the clip (manifest, record, level folder or buffer): never read",
    "mixed-clip": "a frame record from another render than the header's (spp, Cycles seed, or previous camera != "
                  "the frame before's camera): two renders wrote one folder",
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
    "negative-radiance": "radiance below 0 on more than 1% of the surface pixels (light is never negative)",
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
    "emission-background": "on a point-sampled LR level, radiance is not the environment that emission holds on "
                           "background (render.gbuffer.emission_background = \"environment\")",
    "empty-frame": "the HR depth is finite (a surface) on less than MIN_SURFACE_SHARE (0.5%) of a frame's pixels "
                   "while the clip's scene has geometry: nothing but sky or background in view (geometry lost on "
                   "import?)",
    "black-frame": "radiance is zero, or not finite, on every pixel of a frame (an unlit scene)",
    # usable views (exposure, depth)
    "exposure-invalid": "the manifest's exposure is malformed, or not the auto exposure its frames' metering gives",
    "dark-frame": "an exposed HR frame is practically black (log-average luminance < 0.02, or more than 20% of its "
                  "pixels below 1e-3)",
    "bright-frame": "an exposed HR frame is blown out (log-average luminance > 2)",
    "metering-mismatch": "the HR radiance is not the radiance its auto exposure was metered on (changed after "
                         "rendering)",
    "flat-view": "fewer than 75% of the checked frames hold near and far content (HR depth p90/p10 >= 3) (warning)",
    # level cameras (manifest camera.kind walk or fly)
    "camera-view": "a level camera's HR frame is half background or more, or its median depth exceeds the level",
    "camera-motion": "a level camera moves faster than declared, or its planned clearance is below its rule",
    "camera-region": "a level camera's eye leaves the region of its split",
    # motion
    "motion-reprojection": "stored motion disagrees with reprojection from depth and cameras on static surfaces",
    "background-motion": "background motion is not the camera's rotation-only motion",
    "motion-unchecked": "a level's motion is not checked against reprojection because its depth is not data (an "
                        "imported NSS capture's HR depth, interpolated from LR) (warning)",
    "next-camera": "a clip with motion_next lacks a rigid next_world_from_camera or a valid next_intrinsics",
    "motion-next-reprojection": "stored motion_next disagrees with reprojection to the next camera on static "
                                "surfaces",
    "motion-next-background": "background motion_next is not the rotation-only motion to the next camera",
}


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
        return json_safe(asdict(self))


@dataclass
class ValidationReport:
    """Result of ``validate_clip``: the findings and summary statistics (counts, timings, motion agreement)."""

    path: str
    findings: list[Finding]
    stats: dict[str, Any]
    #: the verdict recorded in the clip (``verdict.record_verdict``), None when none was recorded
    verdict: dict[str, Any] | None = None

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
        for lvl, lv in s.get("levels", {}).items():
            m = lv.get("motion", {})
            if m.get("static_fraction_min") is not None:
                parts.append(f"{lvl} motion agrees on >= {100 * m['static_fraction_min']:.1f}% of static pixels "
                             f"(worst median {m['static_median_px_max']:.3g} px)")
        parts.append(f"{s.get('seconds', 0.0):.2f} s")
        return "; ".join(parts)

    def to_dict(self) -> dict:
        return json_safe({"path": self.path, "ok": self.ok, "errors": len(self.errors),
                           "warnings": len(self.warnings), "findings": [f.to_dict() for f in self.findings],
                           "stats": self.stats})


def json_safe(obj):
    """Replace NaN/Inf by None and numpy scalars by Python ones, recursively (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def as_int(v) -> int | None:
    if isinstance(v, bool):
        return None
    if isinstance(v, int):
        return v
    if isinstance(v, float) and v.is_integer():
        return int(v)
    return None


def fmt_frac(x: float) -> str:
    return f"{100.0 * x:.3g}%"



class Collector:
    """State of one validation run: the clip's root, the options, the findings so far and the statistics."""

    def __init__(self, root: Path, options: ValidationOptions):
        self.root = root
        self.opt = options
        self.findings: list[Finding] = []
        self.stats: dict[str, Any] = {"frames_planned": 0, "frames_finished": 0, "frames_checked": 0,
                                      "frames_value_checked": 0, "files_read": 0, "files_header_only": 0,
                                      "options": asdict(options), "levels": {}, "per_frame": {}}
        self.level_acc: dict[str, dict[str, list]] = {}

    def add(self, code: str, message: str, *, frame: int | None = None, key: str | None = None,
            severity: str = ERROR, **details) -> None:
        self.findings.append(Finding(code, severity, message, frame, key, details))
