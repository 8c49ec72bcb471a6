"""Clips with several LR levels (``--scales``): sizes, the clip API, version-1 clips, validation of every level."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from tests.conftest import edit_header, edit_manifest, edit_record

from gbuffer_export import open_clip
from gbuffer_export.clip import ClipError, buffer_path
from gbuffer_export.conventions import (BUFFERS, check_level_sizes, level_name, lr_size, nearest_divisible_sizes,
                                        reprojection_motion, scale_fraction)
from gbuffer_export.exr import read_exr, write_exr
from gbuffer_export.synthetic import make_synthetic_clip
from gbuffer_export.validate import validate_clip

HR = (80, 40)
SCALES = (2, 2.5, 4)
LEVEL_SIZES = {"hr": (80, 40), "lr": (40, 20), "lr_x2.5": (32, 16), "lr_x4": (20, 10)}


@pytest.fixture(scope="module")
def multi_clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("multi") / "clip", frames=(1, 2, 3), hr_size=HR,
                               scales=SCALES, jitter=True)


@pytest.fixture
def clip(multi_clip, tmp_path):
    dst = tmp_path / "clip"
    shutil.copytree(multi_clip, dst)
    return dst


# ---------------------------------------------------------------------------------------------- sizes and names

def test_scale_fractions_and_sizes():
    assert scale_fraction(2.5).numerator == 5 and scale_fraction(2.5).denominator == 2
    assert (scale_fraction(1.6).numerator, scale_fraction(1.6).denominator) == (8, 5)
    assert (scale_fraction(3.75).numerator, scale_fraction(3.75).denominator) == (15, 4)
    assert lr_size((80, 40), 2.5) == (32, 16) and lr_size((64, 36), 2.5) is None
    assert lr_size((64, 32), 1.6) == (40, 20) and lr_size((60, 30), 3.75) == (16, 8)
    assert lr_size((64, 36), 4) == (16, 9)
    for bad in (0.5, 0, -2, float("nan"), float("inf"), True, "2"):
        with pytest.raises(ValueError):
            scale_fraction(bad)
    assert level_name(2.5, 2) == "lr_x2.5" and level_name(4.0, 2) == "lr_x4" and level_name(2, 2.0) == "lr"


def test_size_error_names_the_nearest_valid_sizes():
    assert nearest_divisible_sizes((64, 36), (2, 2.5, 4)) == ((60, 20), (80, 40))
    with pytest.raises(ValueError) as e:
        check_level_sizes((64, 36), (2, 2.5, 4))
    msg = str(e.value)
    assert "\n" not in msg and "--hr-size 64x36" in msg and "scale 2.5" in msg and "60x20 or 80x40" in msg
    # every size offered really divides
    for size in nearest_divisible_sizes((64, 36), (2, 2.5, 4)):
        assert all(lr_size(size, s) is not None for s in (2, 2.5, 4))
    assert check_level_sizes((80, 40), (2, 2.5, 4)) == {2.0: (40, 20), 2.5: (32, 16), 4.0: (20, 10)}


# ---------------------------------------------------------------------------------------------- the clip API

def test_multi_level_clip_layout_and_api(multi_clip):
    c = open_clip(multi_clip)
    assert c.scales == [2.0, 2.5, 4.0] and c.scale == 2 and isinstance(c.scale, int)
    assert c.sizes == LEVEL_SIZES
    m = c.manifest
    assert m["schema_version"] == 2
    assert {lvl: v["scale"] for lvl, v in m["levels"].items()} == {"hr": 1.0, "lr": 2.0, "lr_x2.5": 2.5,
                                                                     "lr_x4": 4.0}
    for lvl, (w, h) in LEVEL_SIZES.items():
        for b in c.buffers:
            assert buffer_path(multi_clip, 1, lvl, b).is_file()
        assert c.read(2, f"{lvl}/radiance").shape == (h, w, 3)
    k_hr = c.camera(1, "hr")["intrinsics"]
    for s in SCALES:
        v = c.at_scale(s)
        lvl = level_name(s, SCALES[0])
        assert v.scale == s and v.scales == [float(s)] and v.levels == ("hr", "lr")
        assert v.sizes == {"hr": HR, "lr": LEVEL_SIZES[lvl]}
        assert np.allclose(v.camera(1, "lr")["intrinsics"], k_hr / s)
        assert np.array_equal(v.read(3, "lr/depth"), c.read(3, f"{lvl}/depth"))
        assert np.array_equal(v.read(3, "hr/depth"), c.read(3, "hr/depth"))
        assert v.record(2)["lr"] == c.record(2)[lvl]
        assert v.at_scale(s) is v
    # each level has its own jitter, in pixels of that level (the same Halton position)
    assert c.camera(2, "lr")["jitter"].tolist() == c.camera(2, "lr_x4")["jitter"].tolist() != [0.0, 0.0]
    with pytest.raises(ClipError, match="no LR level at scale 3 .has 2, 2.5, 4"):
        c.at_scale(3)
    with pytest.raises(ClipError, match="no level 'lr_x3'"):
        c.read(1, "lr_x3/radiance")


def test_level_motion_is_in_pixels_of_the_level(multi_clip):
    """Stored motion of every level equals reprojection from that level's depth and cameras (jitter included)."""
    c = open_clip(multi_clip)
    for lvl in LEVEL_SIZES:
        cam = c.camera(2, lvl)
        depth = c.read(2, f"{lvl}/depth")[..., 0]
        ref = reprojection_motion(depth, cam["intrinsics"], cam["world_from_camera"], cam["prev_intrinsics"],
                                  cam["prev_world_from_camera"], cam["jitter"])
        surf = np.isfinite(depth)
        assert np.abs(c.read(2, f"{lvl}/motion") - ref)[surf].max() < 1e-3, lvl


def test_version_1_clip_still_reads_and_validates(tmp_path):
    """A clip as version 1 wrote it (no per-level scale, schema_version 1) opens and validates unchanged."""
    path = make_synthetic_clip(tmp_path / "old", frames=(1, 2), hr_size=(64, 36), scale=4)

    def to_v1(m):
        m["schema_version"] = 1
        for v in m["levels"].values():
            v.pop("scale")
    edit_header(path, to_v1)  # as version 1 wrote it: the identity of its own header
    c = open_clip(path)
    assert c.scale == 4 and c.scales == [4.0] and c.at_scale(4) is c and c.sizes["lr"] == (16, 9)
    r = validate_clip(path)
    assert r.findings == [], [f.line() for f in r.findings]


# ---------------------------------------------------------------------------------------------- validation

def test_every_level_validates(multi_clip):
    r = validate_clip(multi_clip)
    assert r.findings == [], [f.line() for f in r.findings]
    s = r.stats
    assert s["files_read"] == 3 * len(LEVEL_SIZES) * len(BUFFERS)
    assert set(s["levels"]) == set(LEVEL_SIZES)
    for lvl, (w, h) in LEVEL_SIZES.items():
        m = s["levels"][lvl]["motion"]
        assert s["levels"][lvl]["size"] == [w, h]
        assert m["static_fraction_min"] == 1.0 and m["background_fraction_min"] == 1.0
        assert m["static_pixels"] + m["background_pixels"] == 3 * w * h
    assert "lr_x2.5 motion agrees" in r.summary_line()


def _shift_motion(clip):
    p = buffer_path(clip, 2, "lr_x2.5", "motion")
    a = read_exr(p, BUFFERS["motion"].channels)
    write_exr(p, {ch: a[..., i] + 1.0 for i, ch in enumerate(BUFFERS["motion"].channels)})


@pytest.mark.parametrize("code,key,corrupt", [
    ("motion-reprojection", "lr_x2.5/motion", _shift_motion),
    ("missing-buffer", "lr_x4/depth", lambda c: buffer_path(c, 3, "lr_x4", "depth").unlink()),
    ("bad-size", "lr_x2.5/radiance", lambda c: write_exr(buffer_path(c, 1, "lr_x2.5", "radiance"),
                                                          {ch: np.ones((16, 30), np.float32) for ch in "RGB"})),
    ("level-mismatch", "lr_x2.5", lambda c: edit_record(c, 2, lambda r: r["lr_x2.5"].__setitem__(
        "intrinsics", [v * 1.01 for v in r["lr_x2.5"]["intrinsics"]]))),
    ("manifest-inconsistent", "lr_x4", lambda c: edit_manifest(c, lambda m: m["levels"]["lr_x4"].__setitem__(
        "width", 21))),
    ("manifest-inconsistent", "lr_x4", lambda c: edit_manifest(c, lambda m: m["levels"]["lr_x4"].__setitem__(
        "scale", 3.0))),
    ("record-incomplete", "lr_x4", lambda c: edit_record(c, 1, lambda r: r.pop("lr_x4"))),
])
def test_each_level_is_checked(clip, code, key, corrupt):
    corrupt(clip)
    r = validate_clip(clip)
    hits = [f for f in r.findings if f.code == code]
    assert hits and {f.key for f in hits} == {key}, [f.line() for f in r.findings]
    assert not r.ok


def test_unknown_level_name_is_refused(clip):
    edit_manifest(clip, lambda m: m["levels"].__setitem__("lr_half", {"width": 1, "height": 1, "scale": 80.0}))
    r = validate_clip(clip)
    assert "manifest-invalid" in r.codes() and not r.ok


def test_resume_needs_every_level(tmp_path):
    """A frame missing a file of an extra level is not done, and cannot be committed."""
    from gbuffer_export.clip import ClipWriter
    path = make_synthetic_clip(tmp_path / "c", frames=(1, 2), hr_size=HR, scales=SCALES)
    m = json.loads((path / "manifest.json").read_text())
    header = {k: v for k, v in m.items() if k not in ("frame_data", "identity")}
    w = ClipWriter(path, header)
    assert w.is_frame_done(1)
    buffer_path(path, 1, "lr_x2.5", "flags").unlink()
    assert not w.is_frame_done(1)
    with pytest.raises(ClipError, match="lr_x2.5/flags was not written"):
        w.commit_frame(1, m["frame_data"]["1"])
    with pytest.raises(ClipError, match="no level 'lr_x3'"):
        w.write_buffer(1, "lr_x3", "depth", np.ones((10, 20, 1)))


def test_bench_render_reports_every_level(multi_clip):
    """``bench render``'s summary: each LR level's render seconds as a fraction of the ground truth."""
    from gbuffer_export.commands.bench_render import summarize
    m = json.loads((multi_clip / "manifest.json").read_text())
    for rec in m["frame_data"].values():
        rec["hr"]["seconds"] = {"radiance": 10.0, "gbuffer": 1.0, "convert": 0.5, "write": 0.5}
        for lvl, sec in (("lr", 0.4), ("lr_x2.5", 0.3), ("lr_x4", 0.2)):
            rec[lvl]["seconds"] = {"radiance": sec, "convert": 0.1, "write": 0.1}
        rec["seconds_total"] = 14.0
    med = summarize(m)
    assert med["lr_render"] == pytest.approx(0.9) and med["convert_and_write"] == pytest.approx(1.6)
    assert med["other"] == pytest.approx(14.0 - 10.0 - 1.0 - 0.9 - 1.6)
    assert med["levels"]["lr_x2.5"] == {"scale": 2.5, "size": [32, 16], "render_s": 0.3,
                                        "fraction_of_ground_truth": pytest.approx(0.03)}
    assert set(med["levels"]) == {"lr", "lr_x2.5", "lr_x4"}


def test_nearest_upscaling_of_the_contact_sheet_takes_any_scale():
    from gbuffer_export.preview import upscale_nearest
    a = np.arange(5 * 7 * 3, dtype=float).reshape(5, 7, 3)
    assert np.array_equal(upscale_nearest(a, 4), np.repeat(np.repeat(a, 4, 0), 4, 1))
    b = upscale_nearest(a[:4, :6], 2.5)
    assert b.shape == (10, 15, 3)
    _, counts = np.unique(b[0, :, 0], return_counts=True)
    assert counts.tolist() == [2, 3, 2, 3, 2, 3]  # HR pixel j goes to LR pixel floor((j + 0.5) / 2.5)
