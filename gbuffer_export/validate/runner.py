"""The order of the checks: ``run`` takes the clip through the manifest, frame, record, file, value, usable-view
(exposure, depth) and motion checks (per frame and level) and summarises the statistics; ``validate_clip`` is the
entry point."""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np

from ..errors import BlendSRError
from ..clip import ClipError
from .camera import check_black_frame, check_empty_frame, check_level_motion, check_level_view, level_report
from .exposure import check_exposed_frame, check_exposure, check_flat_views, depth_ratio
from .files import read_level
from .manifest import check_frames, check_header, check_manifest
from .motion import check_motion, check_motion_next
from .options import ValidationOptions
from .records import check_against_header, check_record
from .report import ERROR, WARNING, Collector, ValidationReport
from .values import check_background_emission, check_values
from .verdict import HASH_ALGORITHM, VERDICT, before_validation, record_verdict


def accumulate(c: Collector, lvl: str, b: dict[str, np.ndarray], surface, mst: dict) -> None:
    """Add one frame and level's surface fraction, radiance and motion statistics to the per-level lists."""
    acc = c.level_acc.setdefault(lvl, {k: [] for k in (
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


def summarise(c: Collector, h: dict | None) -> None:
    """Per-level summary statistics (means, extremes, pixel counts) into ``c.stats['levels']``."""
    for lvl, acc in c.level_acc.items():
        def agg(k, fn):
            return float(fn(acc[k])) if acc[k] else None
        c.stats["levels"][lvl] = {
            "size": list(h["sizes"][lvl]) if h else None,
            "surface_fraction_mean": agg("surface_fraction", np.mean),
            "radiance_mean": agg("radiance_mean", np.mean),
            "radiance_max": agg("radiance_max", np.max),
            "motion": {
                "tol_px": c.opt.tol_px(lvl),
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


@dataclass
class ClipChecks:
    """What the per-frame checks of one clip share: its manifest and parsed header (``check_header``), the render
    settings they depend on, the level camera's report, the exposure, and the HR depth ratios found so far."""
    manifest: dict
    h: dict
    render: dict
    env_bg: bool  # the G-buffer pass sees the environment as emission: L_D = 0 on the sky at LR
    lr_denoised: bool
    level_cam: dict | None
    exposure: object
    derived_hr_depth: str | None  # an imported NSS capture's: interpolated, not data
    ratios: dict[int, float] = field(default_factory=dict)


def run(c: Collector, frames: Iterable[int] | None, quick: bool, progress: bool) -> None:
    """All checks of the clip into ``c``: manifest and frames once, then per selected frame its record and, per
    level, its files, the per-buffer value checks (``check_values``) and the motion checks."""
    manifest = check_manifest(c)
    if manifest is None:
        return
    h = check_header(c, manifest)
    if h is None:
        return
    finished = check_frames(c, h)
    render = manifest.get("render") if isinstance(manifest.get("render"), dict) else {}
    imported = manifest.get("imported") if isinstance(manifest.get("imported"), dict) else {}
    k = ClipChecks(manifest, h, render,
                   env_bg=isinstance(render.get("gbuffer"), dict)
                   and render["gbuffer"].get("emission_background") == "environment",
                   lr_denoised=isinstance(render.get("lr"), dict) and bool(render["lr"].get("denoise")),
                   level_cam=level_report(manifest), exposure=check_exposure(c, manifest),
                   derived_hr_depth=imported.get("hr_depth"))
    selected = _selected(c, finished, frames)
    full = set(selected) if not quick else ({selected[0], selected[-1]} if selected else set())
    bar = None
    if progress and len(selected) > 3:
        from tqdm import tqdm
        bar = tqdm(total=len(selected), desc="validate", unit="frame", file=sys.stderr, leave=False)
    try:
        for f in selected:
            _check_frame(c, k, f, f in full)
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    if k.derived_hr_depth and full:
        c.add("motion-unchecked", f"hr/motion is not checked against reprojection: hr/depth is "
                                  f"{k.derived_hr_depth} (the imported capture holds no HR depth)", key="hr/motion",
              severity=WARNING)
    if k.level_cam is not None:
        check_level_motion(c, selected, h["frame_data"], k.level_cam)
    check_flat_views(c, k.ratios)
    summarise(c, h)


def _selected(c: Collector, finished: list[int], frames: Iterable[int] | None) -> list[int]:
    """The finished frames among ``frames`` (None: all); BlendSRError when ``frames`` holds none of them."""
    if frames is None:
        return finished
    wanted = set(int(f) for f in frames)
    selected = [f for f in finished if f in wanted]
    if not selected and finished:
        raise BlendSRError(f"{c.root}: none of the selected frames is a finished frame of this clip "
                           f"(finished: {finished[0]}..{finished[-1]})")
    return selected


def _check_frame(c: Collector, k: ClipChecks, f: int, full: bool) -> None:
    """One frame: its record, then per level its files (headers only unless ``full``) and, when ``full``, the
    value, view and motion checks."""
    h = k.h
    cams = check_record(c, f, h["frame_data"][f], h)
    check_against_header(c, f, h["frame_data"][f], h, k.render, h["frame_data"].get(f - 1))
    per = {}
    for lvl in h["sizes"]:
        b = read_level(c, f, lvl, h, header_only=not full)
        if full:
            mst = _check_level_values(c, k, f, lvl, b, cams.get(lvl))
            if mst:
                per[lvl] = mst
    if per:
        c.stats["per_frame"][str(f)] = per
    c.stats["frames_checked"] += 1
    c.stats["frames_value_checked"] += int(full)


def _check_level_values(c: Collector, k: ClipChecks, f: int, lvl: str, b: dict, cam: dict | None) -> dict:
    """One frame and level's values, usable view and motion (statistics accumulated); the motion statistics."""
    surface = check_values(c, f, lvl, b)
    check_black_frame(c, f, lvl, b)
    if lvl == "hr":
        check_empty_frame(c, f, b)
        check_exposed_frame(c, f, b, k.exposure, k.manifest, k.h["frame_data"][f])
        r = depth_ratio(b)
        if r is not None:
            k.ratios[f] = r
        if k.level_cam is not None:
            view = check_level_view(c, f, b, k.level_cam)
            if view:
                c.stats.setdefault("camera_view", {})[str(f)] = view
    if k.env_bg and lvl != "hr" and not k.lr_denoised:  # point-sampled, not denoised: L_D = 0 on the sky
        check_background_emission(c, f, lvl, b, surface)
    # an imported clip's HR depth is not data (NSS has none): its HR motion cannot be reprojected
    mst = {} if lvl == "hr" and k.derived_hr_depth else check_motion(c, f, lvl, b, cam, surface)
    check_motion_next(c, f, lvl, b, cam, k.h["frame_data"][f].get(lvl), surface)
    accumulate(c, lvl, b, surface, mst)
    return mst


def validate_clip(path: str | Path, *, frames: Iterable[int] | None = None, quick: bool = False,
                  options: ValidationOptions | None = None, progress: bool = False) -> ValidationReport:
    """Validate the clip in directory ``path``.

    frames: check only these frames' records and files (manifest-wide checks still cover the whole clip);
        ValueError when none of them is finished.
    quick: read pixel data (value and motion checks) of the first and last selected frame only; the other frames
        get existence, size and channel checks from the EXR headers.
    progress: show a tqdm bar on stderr when more than 3 frames are checked.
    A validation of every frame (``frames`` None) with the default options records its verdict in the clip
    (``verdict.record_verdict``: ``CLIP/validation.json``, the files' hashes; ``report.verdict``).
    Raises ClipError only when ``path`` is not a directory; every problem of the clip is a finding.
    """
    root = Path(path)
    if not root.is_dir():
        raise ClipError(f"{root}: not a directory")
    t0 = time.perf_counter()
    c = Collector(root, options or ValidationOptions())
    recorded = frames is None and c.opt == ValidationOptions()
    before = before_validation(root) if recorded else None
    run(c, frames, quick, progress)
    c.stats["seconds"] = time.perf_counter() - t0
    c.stats["errors"] = sum(f.severity == ERROR for f in c.findings)
    c.stats["warnings"] = sum(f.severity == WARNING for f in c.findings)
    report = ValidationReport(str(root), c.findings, c.stats)
    if recorded:
        report.verdict = record_verdict(root, report, before, quick=quick)
        if report.verdict is not None:
            c.stats["verdict"] = {"file": str(root / VERDICT), "digest": report.verdict["digest"],
                                  "files": len(report.verdict["files"]), "hash": HASH_ALGORITHM}
    return report
