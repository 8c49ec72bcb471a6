"""Tests of clip validation (gbuffer_export.validate and ``blendsr validate``) on exact synthetic clips.

An intact synthetic clip must validate with no finding and motion agreement ~1.0; each corruption below must
produce its specific finding code, and every code of ``CODES`` has a corruption that fires it."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from tests.conftest import edit_header, edit_manifest, edit_record, requires_bpy, run_cli
from gbuffer_export.cli import main
from gbuffer_export.clip import ClipError, buffer_path
from gbuffer_export.conventions import BUFFERS, SCHEMA_VERSION, Flag
from gbuffer_export.exr import read_exr, write_exr
from gbuffer_export.synthetic import SyntheticLook, look_at, make_synthetic_clip
from gbuffer_export.validate import CODES, ERROR, WARNING, ValidationOptions, validate_clip

FRAMES = (1, 2, 3)
HR = (64, 36)
SCALE = 4


@pytest.fixture(scope="module")
def base_clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("base") / "clip", frames=FRAMES, hr_size=HR, scale=SCALE)


@pytest.fixture(scope="module")
def base_clip_jitter(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("basej") / "clip", frames=FRAMES, hr_size=HR, scale=SCALE,
                               jitter=True)


@pytest.fixture
def clip(base_clip, tmp_path):
    dst = tmp_path / "clip"
    shutil.copytree(base_clip, dst)
    return dst


# --------------------------------------------------------------------------------------------------- helpers

def read(clip, frame, key):
    lvl, name = key.split("/")
    return read_exr(buffer_path(clip, frame, lvl, name), BUFFERS[name].channels)


def write(clip, frame, key, arr, channels=None):
    lvl, name = key.split("/")
    channels = channels or BUFFERS[name].channels
    write_exr(buffer_path(clip, frame, lvl, name), {c: arr[..., i] for i, c in enumerate(channels)})


def surface(clip, frame, lvl="hr"):
    return (read(clip, frame, f"{lvl}/flags")[..., 0] & np.uint32(Flag.BACKGROUND)) == 0


def edit_buffer(clip, frame, key, fn):
    """Rewrite a buffer with ``fn(array)``: its return value, or the array it modified in place."""
    arr = read(clip, frame, key)
    out = fn(arr)
    write(clip, frame, key, arr if out is None else out)


def region(shape, frac_rows=(0.3, 0.5), frac_cols=(0.3, 0.6)):
    m = np.zeros(shape[:2], bool)
    h, w = shape[:2]
    m[int(frac_rows[0] * h):int(frac_rows[1] * h), int(frac_cols[0] * w):int(frac_cols[1] * w)] = True
    return m


def findings(report, code):
    return [f for f in report.findings if f.code == code]


# --------------------------------------------------------------------------------------------------- intact clips

@pytest.mark.parametrize("jitter", [False, True])
def test_intact_clip_has_no_findings(base_clip, base_clip_jitter, jitter):
    path = base_clip_jitter if jitter else base_clip
    r = validate_clip(path)
    assert r.findings == [], [f.line() for f in r.findings]
    assert r.ok
    s = r.stats
    assert (s["frames_planned"], s["frames_finished"], s["frames_checked"]) == (3, 3, 3)
    assert s["files_read"] == 3 * 2 * len(BUFFERS)
    for lvl, (w, h) in (("hr", HR), ("lr", (HR[0] // SCALE, HR[1] // SCALE))):
        m = s["levels"][lvl]["motion"]
        assert s["levels"][lvl]["size"] == [w, h]
        assert m["static_fraction_min"] == 1.0 and m["background_fraction_min"] == 1.0
        assert m["static_median_px_max"] < 1e-4 and m["background_median_px_max"] < 1e-4
        assert m["static_pixels"] > 0 and m["background_pixels"] > 0
        # every pixel is either static surface or background in this static scene
        assert m["static_pixels"] + m["background_pixels"] == 3 * w * h
    assert set(s["per_frame"]) == {"1", "2", "3"}
    json.dumps(r.to_dict(), allow_nan=False)


def test_jittered_clip_needs_the_jitter(base_clip_jitter, tmp_path):
    """The LR motion of a jittered clip is that of the surface seen at p + jitter: dropping the record's jitter
    makes the LR motion disagree, so the check really uses it."""
    dst = tmp_path / "clip"
    shutil.copytree(base_clip_jitter, dst)
    for f in FRAMES:
        edit_record(dst, f, lambda r: r["lr"].__setitem__("jitter", [0.0, 0.0]))
    r = validate_clip(dst, options=ValidationOptions(motion_tol_px=1e-3))
    assert {f.key for f in findings(r, "background-motion") + findings(r, "motion-reprojection")} == {"lr/motion"}


# --------------------------------------------------------------------------------------------------- corruptions

def _no_frames(clip):
    edit_manifest(clip, lambda m: (m.__setitem__("frames", []), m.__setitem__("frame_data", {})))
    for d in ("frames", "hr", "lr"):
        shutil.rmtree(clip / d)


def _missing_frame(clip):
    edit_manifest(clip, lambda m: m["frame_data"].pop("2"))
    (clip / "frames" / "000002.json").unlink()


def _orphan_files(clip):
    shutil.copy(buffer_path(clip, 3, "hr", "radiance"), buffer_path(clip, 4, "hr", "radiance"))


def _temp_file(clip):
    src = buffer_path(clip, 1, "hr", "radiance")
    shutil.copy(src, src.with_name(".000001.tmp4242.exr"))


def _truncate(clip):
    p = buffer_path(clip, 2, "hr", "normal")
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])


def _nan_radiance(clip):
    def fn(a):
        a[10:12, 20:23] = np.nan  # 6 pixels
        a[0, 0, 1] = np.nan  # a 7th, one channel only
    edit_buffer(clip, 2, "hr/radiance", fn)


def _depth_where(clip, value, on_surface):
    s = surface(clip, 2)
    mask = s if on_surface else ~s
    idx = np.argwhere(mask)[:5]

    def fn(a):
        a[idx[:, 0], idx[:, 1]] = value
    edit_buffer(clip, 2, "hr/depth", fn)


def _non_unit_normals(clip):
    s = surface(clip, 2) & region(HR[::-1])
    edit_buffer(clip, 2, "hr/normal", lambda a: np.where(s[..., None], 0.5 * a, a))


def _normal_on_background(clip):
    bg = ~surface(clip, 2)
    edit_buffer(clip, 2, "hr/normal", lambda a: np.where(bg[..., None], np.float32([0, 0, 1]), a))


def _fbeta(clip, value, on_surface):
    s = surface(clip, 2)
    m = (s & region(HR[::-1])) if on_surface else ~s
    edit_buffer(clip, 2, "hr/fbeta", lambda a: np.where(m[..., None], np.float32(value), a))


def _motion_offset(clip, frame=2, key="hr/motion", offset=(1.0, 0.0)):
    lvl = key.split("/")[0]
    s = surface(clip, frame, lvl)
    edit_buffer(clip, frame, key, lambda a: np.where(s[..., None], a + np.float32(offset), a))


def _background_motion_zero(clip):
    bg = ~surface(clip, 2)
    edit_buffer(clip, 2, "hr/motion", lambda a: np.where(bg[..., None], 0.0, a).astype(np.float32))


def _unknown_flag(clip):
    def fn(a):
        a[3, 4] |= np.uint32(1 << 20)
    edit_buffer(clip, 2, "hr/flags", fn)


def _radiance_channels(clip, channels):
    a = read(clip, 2, "hr/radiance")
    extra = np.ones(a.shape[:2] + (1,), np.float32)
    full = np.concatenate([a, extra], axis=-1)
    write(clip, 2, "hr/radiance", full[..., :len(channels)], channels)


def _level_camera(clip, **over):
    """Declare the clip's camera a level walk (validate/camera.py) with a report whose rules its frames break."""
    report = {"kind": "walk", "rules": {"clearance_m": 0.25}, "metres_per_unit": 1.0, "fps": 24.0,
              "level_extent_m": 1e6, "declared_max_speed_mps": 1e6, "clearance_m": 1.0,
              "min_clearance_rule_m": 0.25, "region": None, **over}
    edit_header(clip, lambda m: m.__setitem__("camera", report))


def _linked_buffer(clip):
    """hr/albedo of frame 2 replaced by a link to a copy outside the clip."""
    src = buffer_path(clip, 2, "hr", "albedo")
    outside = clip.parent / "outside_albedo.exr"
    shutil.copyfile(src, outside)
    src.unlink()
    src.symlink_to(outside)


def _moved_prev_camera(clip):
    """Frame 3's previous camera is not frame 2's camera (a frame of another render)."""
    def fn(r):
        for lvl in r.values():
            lvl["prev_world_from_camera"][0][3] += 0.25
    edit_record(clip, 3, fn)


def _ground_only(clip):
    """The clip replaced by one whose camera looks straight down at the ground from 1 unit: every frame shows one
    surface at about one depth."""
    shutil.rmtree(clip)
    make_synthetic_clip(clip, frames=FRAMES, hr_size=HR, scale=SCALE, look=SyntheticLook(camera=lambda t: look_at(
        np.array([20.0 + 0.05 * t, 1.0, 20.0]), np.array([20.0 + 0.05 * t, 0.0, 20.001]))))


#: code -> (corruption, severity, frame, key) of the finding it must produce (None: not checked).
CASES = {
    # nothing in view: the HR depth of frame 2 infinite everywhere (only sky), as a scene whose geometry was lost
    "empty-frame": (lambda c: edit_buffer(c, 2, "hr/depth", lambda a: np.full_like(a, np.inf)), ERROR, 2,
                    "hr/depth"),
    "black-frame": (lambda c: edit_buffer(c, 2, "hr/radiance", np.zeros_like), ERROR, 2, "hr/radiance"),
    # usable views (validate/exposure.py): the exposed radiance (1e-5 of it: practically black; 100 times: blown
    # out), a malformed exposure, a metering that is not the radiance's, a view of one surface at one depth
    "dark-frame": (lambda c: edit_buffer(c, 2, "hr/radiance", lambda a: a * np.float32(1e-5)), ERROR, 2,
                   "hr/radiance"),
    "bright-frame": (lambda c: edit_buffer(c, 2, "hr/radiance", lambda a: a * np.float32(100)), ERROR, 2,
                     "hr/radiance"),
    "exposure-invalid": (lambda c: edit_manifest(c, lambda m: m.__setitem__("exposure", {"mode": "auto", "value": -1})),
                         ERROR, None, "exposure"),
    "metering-mismatch": (lambda c: edit_record(c, 2, lambda r: r["hr"].__setitem__(
        "luminance", {"log_mean": 0.0, "lit_pixels": 1, "pixels": 1})), ERROR, 2, "hr/radiance"),
    "flat-view": (_ground_only, WARNING, None, "hr/depth"),
    "camera-view": (lambda c: _level_camera(c, level_extent_m=1e-3), ERROR, 2, "hr/depth"),
    "camera-motion": (lambda c: _level_camera(c, clearance_m=0.1), ERROR, None, None),
    "camera-region": (lambda c: _level_camera(c, region={"lo": [1e3, 1e3], "hi": [2e3, 2e3], "grid": [1, 1],
                                                         "cells": None}), ERROR, 2, "hr"),
    "unsafe-link": (_linked_buffer, ERROR, 2, "hr/albedo"),
    "mixed-clip": (_moved_prev_camera, ERROR, 3, "hr"),
    "manifest-missing": (lambda c: (c / "manifest.json").unlink(), ERROR, None, None),
    "manifest-invalid": (lambda c: (c / "manifest.json").write_text('{"schema": "blendsr.clip", '), ERROR, None,
                         None),
    "schema-newer": (lambda c: edit_manifest(c, lambda m: m.__setitem__("schema_version", SCHEMA_VERSION + 1)),
                     ERROR, None, None),
    # a header field the identity covers edited after rendering (exposure deleted; nulled; the identity removed)
    "manifest-identity": (lambda c: edit_manifest(c, lambda m: m.__setitem__("exposure", None)), ERROR, None,
                          "identity"),
    "manifest-incomplete": (lambda c: edit_manifest(c, lambda m: m.pop("blender_version")), ERROR, None, None),
    "manifest-colour-space": (lambda c: edit_header(c, lambda m: m.__setitem__("scene_linear", "AgX Log")),
                              WARNING, None, None),
    "manifest-inconsistent": (lambda c: edit_manifest(c, lambda m: m["levels"]["hr"].__setitem__("width", 68)),
                              ERROR, None, None),
    # the synthetic clip writes emission 0 on its sky: declaring that emission holds the environment contradicts it
    "emission-background": (lambda c: edit_header(c, lambda m: m["render"].__setitem__(
        "gbuffer", {"emission_background": "environment"})), ERROR, None, "lr/emission"),
    "no-frames": (_no_frames, ERROR, None, None),
    "missing-frame": (_missing_frame, ERROR, 2, None),
    "unplanned-frame": (lambda c: edit_header(c, lambda m: m["frames"].remove(3)), WARNING, 3, None),
    "manifest-stale": (lambda c: (c / "frames" / "000002.json").write_text(json.dumps(
        {**json.loads((c / "frames" / "000002.json").read_text()), "extra": 1})), ERROR, 2, None),
    "missing-record": (lambda c: (c / "frames" / "000002.json").unlink(), ERROR, 2, None),
    "incomplete-frame": (_orphan_files, ERROR, 4, None),
    "leftover-temp": (_temp_file, WARNING, None, "hr/radiance"),
    "record-incomplete": (lambda c: edit_record(c, 2, lambda r: r["lr"].pop("seed")), ERROR, 2, "lr"),
    "bad-camera": (lambda c: edit_record(c, 2, lambda r: r["hr"]["intrinsics"].__setitem__(0, -10.0)), ERROR, 2,
                   "hr"),
    "jitter-range": (lambda c: edit_record(c, 2, lambda r: r["lr"].__setitem__("jitter", [0.7, 0.0])), ERROR, 2,
                     "lr"),
    "bad-record": (lambda c: edit_record(c, 2, lambda r: r["hr"].__setitem__("spp", 0)), ERROR, 2, "hr"),
    "level-mismatch": (lambda c: edit_record(c, 2, lambda r: r["lr"].__setitem__(
        "intrinsics", [v * 1.01 for v in r["lr"]["intrinsics"]])), ERROR, 2, "lr"),
    "missing-buffer": (lambda c: buffer_path(c, 2, "hr", "fbeta").unlink(), ERROR, 2, "hr/fbeta"),
    "truncated-exr": (_truncate, ERROR, 2, "hr/normal"),
    "bad-size": (lambda c: write(c, 2, "hr/albedo", np.zeros((9, 16, 3), np.float32)), ERROR, 2, "hr/albedo"),
    "bad-channels": (lambda c: _radiance_channels(c, ("R", "G")), ERROR, 2, "hr/radiance"),
    "extra-channels": (lambda c: _radiance_channels(c, ("R", "G", "B", "A")), WARNING, 2, "hr/radiance"),
    "bad-dtype": (lambda c: write(c, 2, "hr/flags", read(c, 2, "hr/flags").astype(np.float32)), ERROR, 2,
                  "hr/flags"),
    "non-finite": (_nan_radiance, ERROR, 2, "hr/radiance"),
    "negative-radiance": (lambda c: edit_buffer(c, 2, "hr/radiance", lambda a: np.where(
        surface(c, 2)[..., None], -np.abs(a) - 0.1, a).astype(np.float32)), ERROR, 2, "hr/radiance"),
    "implausible-value": (lambda c: edit_buffer(c, 2, "lr/radiance", lambda a: a.__setitem__((3, 4, 0), 1e30)),
                          WARNING, 2, "lr/radiance"),
    "depth-range": (lambda c: _depth_where(c, -1.0, True), ERROR, 2, "hr/depth"),
    "depth-inf-on-surface": (lambda c: _depth_where(c, np.inf, True), ERROR, 2, "hr/depth"),
    "depth-finite-on-background": (lambda c: _depth_where(c, 1e10, False), ERROR, 2, "hr/depth"),
    "non-unit-normal": (_non_unit_normals, ERROR, 2, "hr/normal"),
    "normal-on-background": (_normal_on_background, ERROR, 2, "hr/normal"),
    "fbeta-range": (lambda c: _fbeta(c, 3.0, True), ERROR, 2, "hr/fbeta"),
    "fbeta-background": (lambda c: _fbeta(c, 0.0, False), ERROR, 2, "hr/fbeta"),
    "value-range": (lambda c: edit_buffer(c, 2, "lr/roughness", lambda a: np.where(region(a.shape)[..., None], 1.5, a)),
                    ERROR, 2, "lr/roughness"),
    "flags-range": (_unknown_flag, ERROR, 2, "hr/flags"),
    "motion-reprojection": (_motion_offset, ERROR, 2, "hr/motion"),
    "background-motion": (_background_motion_zero, ERROR, 2, "hr/motion"),
    # an imported NSS capture's HR depth is interpolated (nss_to_clip): its HR motion is said to be unchecked
    "motion-unchecked": (lambda c: edit_header(c, lambda m: m.__setitem__(
        "imported", {"format": "nss", "hr_depth": "interpolated-from-lr"})), WARNING, None, "hr/motion"),
    # motion_next (validate/motion.py): the motion's corruptions, and a record without the next camera
    "motion-next-reprojection": (lambda c: _motion_offset(c, key="lr/motion_next", offset=(0.0, 0.5)), ERROR, 2,
                                 "lr/motion_next"),
    "motion-next-background": (lambda c: edit_buffer(c, 2, "hr/motion_next", lambda a: np.where(
        ~surface(c, 2)[..., None], -a, a).astype(np.float32)), ERROR, 2, "hr/motion_next"),
    "next-camera": (lambda c: edit_record(c, 3, lambda r: r["lr"].pop("next_intrinsics")), ERROR, 3,
                    "lr/motion_next"),
}


def test_every_code_has_a_corruption():
    assert set(CASES) == set(CODES)


@pytest.mark.parametrize("code", sorted(CASES))
def test_corruption_fires_its_code(clip, code):
    corrupt, severity, frame, key = CASES[code]
    corrupt(clip)
    r = validate_clip(clip)
    hits = findings(r, code)
    assert hits, f"{code} did not fire; findings: {[f.line() for f in r.findings]}"
    assert any(h.severity == severity and (frame is None or h.frame == frame) and (key is None or h.key == key)
               for h in hits), [h.line() for h in hits]
    assert r.ok == (severity == WARNING)  # warnings alone pass; every error case fails
    line = hits[0].line()
    assert line.startswith(hits[0].severity.upper()) and "\n" not in line and f"[{code}]" in line
    json.dumps(r.to_dict(), allow_nan=False)


def test_half_float_radiance_fails(clip):
    """The format says float32 for radiance (half overflows at 65504): a half radiance file is bad-dtype."""
    arr = read(clip, 2, "hr/radiance")
    write_exr(buffer_path(clip, 2, "hr", "radiance"), {ch: arr[..., i] for i, ch in enumerate("RGB")}, half=True)
    r = validate_clip(clip)
    assert not r.ok
    assert [(f.code, f.frame, f.key) for f in r.errors] == [("bad-dtype", 2, "hr/radiance")]


def test_a_little_negative_radiance_from_a_denoiser_passes(clip):
    s = surface(clip, 2)
    idx = np.argwhere(s)[:2]

    def fn(a):
        a[idx[:, 0], idx[:, 1]] = -0.01
    edit_buffer(clip, 2, "hr/radiance", fn)
    assert not findings(validate_clip(clip), "negative-radiance")


def test_a_render_scratch_folder_is_a_warning(clip):
    (clip / ".render-999999-abc").mkdir()
    (clip / ".render-999999-abc" / "hr_radiance.exr").write_bytes(b"x")
    r = validate_clip(clip)
    assert r.ok
    assert [f.code for f in r.warnings] == ["leftover-temp"]
    assert ".render-999999-abc" in r.warnings[0].line()


def test_value_corruptions_fire_only_their_code(clip):
    """A localized value corruption is reported once, at the right frame and buffer, and nowhere else."""
    _non_unit_normals(clip)
    r = validate_clip(clip)
    assert [(f.code, f.frame, f.key) for f in r.findings] == [("non-unit-normal", 2, "hr/normal")]


# --------------------------------------------------------------------------------------------------- numbers

def test_non_finite_counts_pixels(clip):
    _nan_radiance(clip)

    def fn(a):
        a[30, 1:4] = np.inf
    edit_buffer(clip, 3, "hr/albedo", fn)
    r = validate_clip(clip)
    nan = [f for f in findings(r, "non-finite") if f.key == "hr/radiance"]
    inf = [f for f in findings(r, "non-finite") if f.key == "hr/albedo"]
    assert len(nan) == 1 and nan[0].frame == 2 and nan[0].details == {"pixels": 7, "nan": 7, "inf": 0}
    assert len(inf) == 1 and inf[0].frame == 3 and inf[0].details == {"pixels": 3, "nan": 0, "inf": 3}
    assert "7 of 2304 pixel(s)" in nan[0].message


def test_depth_problems_count_pixels(clip):
    _depth_where(clip, np.inf, True)
    r = validate_clip(clip)
    (f,) = findings(r, "depth-inf-on-surface")
    assert f.details["pixels"] == 5
    # those 5 pixels leave the static set; the motion check still passes
    assert not findings(r, "motion-reprojection")


@pytest.mark.parametrize("offset, fires", [(0.03, False), (0.07, True)])
def test_motion_tolerance_boundary(clip, offset, fires):
    _motion_offset(clip, offset=(0.0, offset))
    r = validate_clip(clip)
    assert bool(findings(r, "motion-reprojection")) == fires
    per = r.stats["per_frame"]["2"]["hr"]
    assert per["static_median_px"] == pytest.approx(offset, abs=1e-4)
    assert per["static_fraction"] == (0.0 if fires else 1.0)
    assert per["background_fraction"] == 1.0
    # the tolerance is a parameter
    r2 = validate_clip(clip, options=ValidationOptions(motion_tol_px=0.1))
    assert not findings(r2, "motion-reprojection")


def test_motion_off_by_one_pixel_reports_numbers(clip):
    _motion_offset(clip)
    r = validate_clip(clip)
    (f,) = findings(r, "motion-reprojection")
    assert (f.frame, f.key) == (2, "hr/motion")
    assert f.details["fraction"] == 0.0 and f.details["median_px"] == pytest.approx(1.0, abs=1e-4)
    assert r.stats["levels"]["hr"]["motion"]["static_fraction_min"] == 0.0
    assert r.stats["levels"]["lr"]["motion"]["static_fraction_min"] == 1.0


@pytest.mark.parametrize("fraction, fires", [(0.1, False), (0.3, True)])
def test_motion_check_tolerates_edges(clip, fraction, fires):
    """Depth is point-sampled, so some (edge) pixels may disagree: only below 80% agreement is it an error."""
    s = surface(clip, 2)
    rng = np.random.default_rng(0)
    idx = np.argwhere(s)
    bad = idx[rng.choice(len(idx), int(fraction * len(idx)), replace=False)]

    def fn(a):
        a[bad[:, 0], bad[:, 1]] += np.float32(2.0)
    edit_buffer(clip, 2, "hr/motion", fn)
    r = validate_clip(clip)
    assert bool(findings(r, "motion-reprojection")) == fires
    assert r.stats["per_frame"]["2"]["hr"]["static_fraction"] == pytest.approx(1 - len(bad) / len(idx))


def test_moving_pixels_are_not_checked_for_reprojection(clip):
    s = surface(clip, 2)
    edit_buffer(clip, 2, "hr/flags", lambda a: np.where(s[..., None], a | np.uint32(Flag.MOVING), a))
    _motion_offset(clip)
    r = validate_clip(clip)
    assert r.findings == [], [f.line() for f in r.findings]
    assert r.stats["per_frame"]["2"]["hr"]["static_pixels"] == 0


def test_alpha_blended_pixels_are_not_checked_for_reprojection(clip):
    """An alpha-blended pixel's motion averages layers while its depth is sample 0's: not a static pixel."""
    s = surface(clip, 2)
    edit_buffer(clip, 2, "hr/flags", lambda a: np.where(s[..., None], a | np.uint32(Flag.ALPHA), a))
    _motion_offset(clip)
    r = validate_clip(clip)
    assert findings(r, "motion-reprojection") == []
    assert r.stats["per_frame"]["2"]["hr"]["static_pixels"] == 0


def test_background_motion_zero_message(clip):
    _background_motion_zero(clip)
    r = validate_clip(clip)
    (f,) = findings(r, "background-motion")
    assert "Blender" in f.message and f.details["fraction"] == 0.0
    assert not findings(r, "motion-reprojection")


def test_non_unit_normal_threshold(clip):
    """99% of surface pixels must be unit length: a handful of edge pixels passes, a region fails."""
    s = surface(clip, 2)
    idx = np.argwhere(s)[:10]  # 10 of ~2100 surface pixels < 1%

    def fn(a):
        a[idx[:, 0], idx[:, 1]] *= 0.5
    edit_buffer(clip, 2, "hr/normal", fn)
    assert not findings(validate_clip(clip), "non-unit-normal")
    _non_unit_normals(clip)
    (f,) = findings(validate_clip(clip), "non-unit-normal")
    n_region = int((s & region(s.shape)).sum())
    assert f.details["pixels"] == len({tuple(i) for i in idx} | {tuple(i) for i in np.argwhere(s & region(s.shape))})
    assert f.details["fraction_off"] == pytest.approx(f.details["pixels"] / int(s.sum()))
    assert n_region > 0.01 * s.sum()


def test_short_normals_on_alpha_pixels_are_a_warning(clip):
    """Zero normals where flags say ALPHA (Cycles' partial coverage) warn; the same pixels unflagged fail."""
    s = surface(clip, 2) & region(HR[::-1])
    _non_unit_normals(clip)
    (f,) = findings(validate_clip(clip), "non-unit-normal")
    assert f.severity == ERROR
    edit_buffer(clip, 2, "hr/flags", lambda a: np.where(s[..., None], a | np.uint32(Flag.ALPHA), a))
    r = validate_clip(clip)
    (f,) = findings(r, "non-unit-normal")
    assert f.severity == WARNING and r.ok
    assert f.details["pixels"] == int(s.sum()) == f.details["alpha_pixels"]


def test_fbeta_few_pixels_is_a_warning(clip):
    s = surface(clip, 2)
    i, j = np.argwhere(s)[0]

    def fn(a):
        a[i, j] = 1.2
    edit_buffer(clip, 2, "hr/fbeta", fn)
    r = validate_clip(clip)
    (f,) = findings(r, "fbeta-range")
    assert f.severity == WARNING and r.ok and f.details["pixels"] == 1
    assert not findings(validate_clip(clip, options=ValidationOptions(fbeta_max=1.25)), "fbeta-range")


def test_albedo_above_one_is_a_warning_below_zero_an_error(clip):
    edit_buffer(clip, 2, "hr/albedo", lambda a: np.where(region(a.shape)[..., None], 1.3, a))
    (f,) = findings(validate_clip(clip), "value-range")
    assert f.severity == WARNING
    edit_buffer(clip, 2, "hr/albedo", lambda a: np.where(region(a.shape)[..., None], -0.2, a))
    (f,) = findings(validate_clip(clip), "value-range")
    assert f.severity == ERROR


def test_material_values_out_of_range_on_alpha_pixels_are_a_warning(clip):
    """Cycles accumulates material passes over alpha-blended layers (roughness 1.59 seen on GlassVaseFlowers):
    out of range only on ALPHA-flagged pixels warns, the same values on one unflagged pixel more fail."""
    s = surface(clip, 2) & region(HR[::-1])
    edit_buffer(clip, 2, "hr/albedo", lambda a: np.where(s[..., None], -0.2, a))
    (f,) = findings(validate_clip(clip), "value-range")
    assert f.severity == ERROR
    edit_buffer(clip, 2, "hr/flags", lambda a: np.where(s[..., None], a | np.uint32(Flag.ALPHA), a))
    r = validate_clip(clip)
    (f,) = findings(r, "value-range")
    assert f.severity == WARNING and r.ok and "ALPHA" in f.message and f.details["pixels"] == int(s.sum())
    i, j = np.argwhere(surface(clip, 2) & ~s)[0]

    def one_more(a):
        a[i, j] = -0.2
    edit_buffer(clip, 2, "hr/albedo", one_more)
    (f,) = findings(validate_clip(clip), "value-range")
    assert f.severity == ERROR


def test_half_written_clip_never_passes(clip):
    """A render interrupted in frame 4 of 4: buffers of frame 4 partly written, no record."""
    edit_header(clip, lambda m: m["frames"].append(4))
    for name in ("radiance", "albedo"):
        shutil.copy(buffer_path(clip, 3, "hr", name), buffer_path(clip, 4, "hr", name))
    r = validate_clip(clip)
    assert not r.ok
    assert {"missing-frame", "incomplete-frame"} <= r.codes(ERROR)
    assert all(f.frame == 4 for f in r.findings)


# --------------------------------------------------------------------------------------------------- modes

def test_quick_mode_reads_only_first_and_last_frame(clip):
    _nan_radiance(clip)  # frame 2: only a full read sees it
    buffer_path(clip, 2, "lr", "depth").unlink()
    r = validate_clip(clip, quick=True)
    assert not findings(r, "non-finite")
    assert [(f.frame, f.key) for f in findings(r, "missing-buffer")] == [(2, "lr/depth")]
    assert r.stats["frames_value_checked"] == 2 and r.stats["frames_checked"] == 3
    assert r.stats["files_read"] == 2 * 2 * len(BUFFERS)
    assert r.stats["files_header_only"] == 2 * len(BUFFERS) - 1
    assert findings(validate_clip(clip), "non-finite")


def test_frame_subset(clip):
    _nan_radiance(clip)  # frame 2
    r = validate_clip(clip, frames=[1])
    assert r.findings == [] and r.stats["frames_checked"] == 1
    assert findings(validate_clip(clip, frames=range(2, 4)), "non-finite")
    edit_manifest(clip, lambda m: m["frame_data"].pop("3"))
    (clip / "frames" / "000003.json").unlink()
    assert findings(validate_clip(clip, frames=[1]), "missing-frame")  # clip-wide checks still run
    with pytest.raises(ValueError, match="none of the selected frames"):
        validate_clip(clip, frames=[99])


def test_not_a_directory(tmp_path):
    with pytest.raises(ClipError, match="not a directory"):
        validate_clip(tmp_path / "nothing")


def test_options_are_validated():
    with pytest.raises(ValueError, match="motion_tol_px"):
        ValidationOptions(motion_tol_px=0)
    with pytest.raises(ValueError, match="motion_min_fraction"):
        ValidationOptions(motion_min_fraction=1.5)
    assert ValidationOptions(lr_motion_tol_px=0.2).tol_px("lr") == 0.2
    assert ValidationOptions().tol_px("lr") == 0.05


# --------------------------------------------------------------------------------------------------- CLI

def test_cli_intact(clip, capsys):
    assert main(["validate", str(clip), "--no-progress"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and out[0].startswith("OK: ") and "0 error(s)" in out[0]


def test_cli_errors_exit_1(clip, capsys):
    _nan_radiance(clip)
    assert main(["validate", str(clip), "--no-progress"]) == 1
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("ERROR frame 2 hr/radiance: 7 of 2304 pixel(s) non-finite")
    assert lines[-1].startswith("FAILED: ") and "1 error(s)" in lines[-1]


def test_cli_warning_only_exits_0(clip, capsys):
    _temp_file(clip)
    assert main(["validate", str(clip), "--no-progress"]) == 0
    assert capsys.readouterr().out.startswith("WARNING hr/radiance: ")


def test_cli_json(clip, capfd):
    """--json prints only JSON on stdout, also when OpenEXR's C++ code prints warnings about a truncated file."""
    _truncate(clip)
    _nan_radiance(clip)
    assert main(["validate", str(clip), "--json", "--no-progress"]) == 1
    out = capfd.readouterr().out
    obj = json.loads(out)
    assert obj["ok"] is False and obj["errors"] == 2 and obj["warnings"] == 0
    assert {(f["code"], f["frame"], f["key"]) for f in obj["findings"]} == {
        ("truncated-exr", 2, "hr/normal"), ("non-finite", 2, "hr/radiance")}
    assert obj["stats"]["levels"]["lr"]["motion"]["static_fraction_min"] == 1.0


def test_cli_options(clip, capsys):
    _motion_offset(clip, offset=(0.07, 0.0))
    assert main(["validate", str(clip), "--no-progress"]) == 1
    assert main(["validate", str(clip), "--no-progress", "--tolerance-px", "0.1"]) == 0
    assert main(["validate", str(clip), "--no-progress", "--frames", "3:3"]) == 0
    assert main(["validate", str(clip), "--no-progress", "--quick"]) == 0  # frame 2 is in the middle
    capsys.readouterr()


def test_cli_bad_input_exits_2(clip, tmp_path, capsys):
    assert main(["validate", str(tmp_path / "missing")]) == 2
    assert "not a directory" in capsys.readouterr().err
    f = tmp_path / "file.txt"
    f.write_text("x")
    assert main(["validate", str(f)]) == 2
    assert main(["validate", str(clip), "--tolerance-px", "-1"]) == 2
    assert main(["validate", str(clip), "--frames", "5:2"]) == 2
    assert main(["validate", str(clip), "--frames", "90:99"]) == 2
    err = capsys.readouterr().err
    assert err.count("blendsr: error:") == 4


def test_cli_directory_without_manifest_exits_1(tmp_path, capsys):
    assert main(["validate", str(tmp_path), "--no-progress"]) == 1
    assert "[manifest-missing]" in capsys.readouterr().out


# --------------------------------------------------------------------------------------------------- real render

@pytest.mark.bpy
@requires_bpy
def test_tiny_blender_render_validates(tmp_path):
    """A clip rendered by Cycles (default scene, jittered LR) passes, with motion agreeing on static pixels."""
    out = tmp_path / "clip"
    run_cli("render", "-o", out, "--frames", "1:3", "--hr-size", "96x64", "--hr-spp", "2", "--lr-spp", "1",
            "--gbuffer-spp", "1", "--no-progress", timeout=300, check=True)
    r = validate_clip(out)
    assert r.ok, [f.line() for f in r.findings]
    assert r.stats["frames_checked"] == 3
    for lvl in ("hr", "lr"):
        m = r.stats["levels"][lvl]["motion"]
        assert m["static_pixels"] > 0 and m["static_fraction_min"] >= 0.99
        assert m["background_pixels"] > 0 and m["background_fraction_min"] >= 0.99
    # the same clip with Blender's raw background motion (zeros) fails
    lr_bg = (read(out, 2, "lr/flags")[..., 0] & np.uint32(Flag.BACKGROUND)) != 0
    edit_buffer(out, 2, "lr/motion", lambda a: np.where(lr_bg[..., None], 0.0, a).astype(np.float32))
    assert "background-motion" in validate_clip(out).codes(ERROR)


def _background_emission_findings(flags: np.ndarray, radiance: np.ndarray, emission: np.ndarray) -> list:
    from pathlib import Path

    from gbuffer_export.validate.report import Collector
    from gbuffer_export.validate.values import check_background_emission
    c = Collector(Path("clip"), ValidationOptions())
    surface = (flags & np.uint32(Flag.BACKGROUND)) == 0
    check_background_emission(c, 1, "lr", {"radiance": radiance, "emission": emission, "flags": flags[..., None]},
                              surface)
    return [f for f in c.findings if f.code == "emission-background"]


def test_background_emission_skips_alpha_fringes_and_a_handful_of_pixels():
    """Background pixels within 2 px of an ALPHA-flagged surface carry the light of alpha-blended layers that the
    G-buffer leaves out (Cycles' alpha threshold): not checked. The same disagreement elsewhere fails, and fewer than
    4 disagreeing pixels never fail."""
    flags = np.full((16, 16), int(Flag.BACKGROUND), np.uint32)
    flags[:, :8] = 0                                  # surface on the left half, background on the right (128 px)
    env = np.full((16, 16, 3), 0.5, np.float32)
    rad = env.copy()
    rad[:, 8:10] += 0.2                               # 32 of 128 background pixels (25%) next to the surface
    assert _background_emission_findings(flags, rad, env), "a 25% disagreement next to an opaque surface fails"
    alpha = flags.copy()
    alpha[:, 6:8] |= np.uint32(Flag.ALPHA)            # the surface's last 2 columns are alpha-blended
    assert not _background_emission_findings(alpha, rad, env)
    far = env.copy()
    far[:, 11:13] += 0.2                              # the same 32 pixels, 4-5 px from the alpha surface
    assert _background_emission_findings(alpha, far, env)
    few = np.zeros((16, 16), np.uint32)
    few[0, :8] = int(Flag.BACKGROUND)                 # 8 background pixels
    for n, fails in ((3, False), (4, True)):
        r = env.copy()
        r[0, :n] += 0.2
        assert bool(_background_emission_findings(few, r, env)) is fails, n
