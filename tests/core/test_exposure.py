"""The clip's exposure (docs/clip-format.md, "Exposure"; gbuffer_export.conventions) and validate's usable-view
checks (gbuffer_export/validate/exposure.py), on synthetic clips: a scene lit in other units is metered and exposed
to middle grey, every reader applies the one exposure, and a clip whose radiance is scaled by 1e-5 fails validate."""
from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from tests.conftest import edit_header, edit_manifest, make_blend, requires_bpy, run_cli
from gbuffer_export import conventions as cv
from gbuffer_export.clip import buffer_path, open_clip
from gbuffer_export.config import RenderConfig
from gbuffer_export.errors import BlendSRError
from gbuffer_export.exr import read_exr, write_exr
from gbuffer_export.synthetic import SyntheticLook, make_synthetic_clip
from gbuffer_export.typed_table import ConfigError
from gbuffer_export.validate import validate_clip

FRAMES = (1, 2, 3)
HR = (64, 36)
#: the synthetic scene's log-average luminance at light 1 (measured: 0.59 over frames 1-4)
BRIGHT = 0.59


def _clip(tmp_path, name="clip", **look):
    return make_synthetic_clip(tmp_path / name, frames=FRAMES, hr_size=HR, scale=4, look=SyntheticLook(**look))


def _scale_radiance(clip, factor):
    """Every radiance file of the clip multiplied by ``factor``, the manifest and records left as they were."""
    for f in FRAMES:
        for lvl in ("hr", "lr"):
            p = buffer_path(clip, f, lvl, "radiance")
            a = read_exr(p, ("R", "G", "B")) * np.float32(factor)
            write_exr(p, {c: a[..., i] for i, c in enumerate("RGB")})


def _hr_log_average(clip) -> float:
    c = open_clip(clip)
    return cv.log_average_luminance([cv.luminance_stats(c.read(f, "hr/radiance"), c.scene_linear) for f in c.frames])


@pytest.fixture(scope="module")
def dim_auto(tmp_path_factory):
    """A scene lit in other units (radiance 1e-4 of the bright scene's), rendered with auto exposure."""
    return make_synthetic_clip(tmp_path_factory.mktemp("dim") / "clip", frames=FRAMES, hr_size=HR, scale=4,
                               scales=(4, 2), look=SyntheticLook(light=1e-4, exposure="auto"))  # NSS needs the 2x level


# ------------------------------------------------------------------------------------------- the rule itself

def test_auto_exposure_keeps_1_inside_the_band_and_aims_at_the_key_outside():
    lo, hi = cv.AUTO_EXPOSURE_BAND
    assert cv.auto_exposure_value(lo) == cv.auto_exposure_value(hi) == cv.auto_exposure_value(0.3) == 1.0
    assert cv.auto_exposure_value(None) == 1.0  # nothing lit: nothing to meter (validate refuses such a clip)
    assert cv.auto_exposure_value(1e-3) == pytest.approx(180.0)
    assert cv.auto_exposure_value(36.0) == pytest.approx(0.005)
    assert cv.auto_exposure_value(1e-12) == cv.EXPOSURE_LIMITS[1]  # practically unlit: clamped, stays dark
    assert cv.auto_exposure_value(1e12) == cv.EXPOSURE_LIMITS[0]


def test_luminance_stats_meter_only_lit_pixels_in_the_clip_working_space():
    rgb = np.zeros((4, 4, 3))
    rgb[:2] = 0.5
    s = cv.luminance_stats(rgb, "Linear Rec.709")
    assert (s["lit_pixels"], s["pixels"]) == (8, 16) and s["log_mean"] == pytest.approx(math.log(0.5))
    assert cv.luminance_stats(np.zeros((2, 2, 3)), "ACEScg")["log_mean"] is None
    # Y of pure green differs between working spaces: Rec.709's 0.7152, ACEScg's (AP1) about 0.674
    g = np.zeros((1, 1, 3))
    g[..., 1] = 1.0
    assert cv.luminance(g, "Linear Rec.709")[0, 0] == pytest.approx(0.7152)
    assert cv.luminance(g, "ACEScg")[0, 0] == pytest.approx(0.6741, abs=1e-3)
    assert cv.log_average_luminance([{"log_mean": 0.0, "lit_pixels": 3}, {"log_mean": math.log(8), "lit_pixels": 1},
                                     {"log_mean": None, "lit_pixels": 0}]) == pytest.approx(8 ** 0.25)


def test_a_manifest_without_exposure_reads_at_1_and_a_malformed_one_is_one_line():
    assert cv.exposure_of({}) == 1.0
    assert cv.exposure_of({"exposure": {"mode": "auto", "key": 0.18}}) == 1.0  # no frame metered yet
    assert cv.exposure_of({"exposure": {"mode": "fixed", "value": 2.0}}) == 2.0
    for bad in ({"mode": "fixed"}, {"mode": "auto", "value": 0}, {"mode": "auto", "value": "2"}, {"mode": "other"}, 3):
        with pytest.raises(BlendSRError) as exc:
            cv.exposure_of({"exposure": bad})
        assert "exposure" in str(exc.value) and "\n" not in str(exc.value)


def test_the_render_key_takes_auto_or_a_multiplier_and_names_itself_when_wrong():
    assert RenderConfig(output="o").exposure == "auto"  # the default
    assert RenderConfig(output="o", exposure="0.5").exposure == 0.5
    assert RenderConfig(output="o", exposure=4).exposure == 4.0
    assert cv.exposure_header(1.0) == {}  # exposure 1: the header (and the identity) clips had before the key
    assert cv.exposure_header(2)["exposure"] == {"mode": "fixed", "value": 2.0, "ev": 1.0}
    assert cv.exposure_header("auto")["exposure"]["mode"] == "auto"
    for bad in ("bright", 0, -2, 1e9, float("nan"), True):
        with pytest.raises(ConfigError) as exc:
            RenderConfig(output="o", exposure=bad)
        assert exc.value.key == "exposure" and str(exc.value).startswith("exposure") and "\n" not in str(exc.value)


# ------------------------------------------------------------------------------------------- auto exposure of a clip

def test_a_scene_lit_in_other_units_is_metered_and_exposed_to_middle_grey(dim_auto):
    c = open_clip(dim_auto)
    block = c.manifest["exposure"]
    measured = _hr_log_average(dim_auto)  # the physical HR radiance, read independently of the records
    assert block["mode"] == "auto" and block["frames_metered"] == len(FRAMES)
    assert block["log_average"] == pytest.approx(measured, rel=1e-6)
    assert measured == pytest.approx(1e-4 * BRIGHT, rel=0.05)
    assert c.exposure == block["value"] == pytest.approx(cv.EXPOSURE_KEY / measured, rel=1e-6)
    assert block["ev"] == pytest.approx(math.log2(block["value"]))
    # every record carries its metering; the exposed radiance is the stored radiance times the exposure
    assert all(cv.frame_luminance(c.record(f)) for f in c.frames)
    for key in ("hr/radiance", "lr/radiance", "hr/emission"):
        raw, exp = c.read(2, key), c.read(2, key, exposed=True)
        np.testing.assert_allclose(exp, raw * np.float32(c.exposure), rtol=1e-6)
    np.testing.assert_array_equal(c.read(2, "hr/fbeta", exposed=True), c.read(2, "hr/fbeta"))  # a ratio: unchanged
    assert cv.log_average_luminance([cv.luminance_stats(c.read(f, "hr/radiance", exposed=True), c.scene_linear)
                                     for f in c.frames]) == pytest.approx(cv.EXPOSURE_KEY, rel=1e-5)
    r = validate_clip(dim_auto)
    assert r.ok and not r.findings, [f.line() for f in r.findings]
    assert all(v["log_average"] == pytest.approx(0.18, rel=0.1) for v in r.stats["exposed_frames"].values())


def test_a_well_exposed_scene_keeps_exposure_1_and_a_set_value_is_recorded(tmp_path):
    auto = open_clip(_clip(tmp_path, "auto", exposure="auto"))
    assert auto.exposure == 1.0 and auto.manifest["exposure"]["log_average"] == pytest.approx(BRIGHT, rel=0.05)
    fixed = open_clip(_clip(tmp_path, "fixed", exposure=0.5))
    assert fixed.manifest["exposure"] == {"mode": "fixed", "value": 0.5, "ev": -1.0} and fixed.exposure == 0.5
    assert "luminance" not in fixed.record(1)["hr"]  # only an auto exposure meters
    old = open_clip(_clip(tmp_path, "old"))
    assert "exposure" not in old.manifest and old.exposure == 1.0
    np.testing.assert_array_equal(old.read(1, "hr/radiance", exposed=True), old.read(1, "hr/radiance"))


# ------------------------------------------------------------------------------------------- validate refuses it

@pytest.mark.parametrize("exposure", [1.0, "auto"])
def test_a_clip_whose_radiance_is_scaled_by_1e_5_fails_validate(tmp_path, exposure):
    """The acceptance: the data a reader gets is the stored radiance times the manifest's exposure. An old clip
    (exposure 1) scaled by 1e-5 is practically black; an auto clip scaled after rendering keeps the exposure
    metered for its original radiance, so it is black too, and its metering no longer matches."""
    clip = _clip(tmp_path, exposure=exposure)
    assert validate_clip(clip).ok
    _scale_radiance(clip, 1e-5)
    r = validate_clip(clip)
    assert not r.ok
    dark = [f for f in r.errors if f.code == "dark-frame"]
    assert sorted(f.frame for f in dark) == list(FRAMES) and {f.key for f in dark} == {"hr/radiance"}
    assert all(f.details["log_average"] < 1e-4 for f in dark)
    assert ("metering-mismatch" in r.codes()) == (exposure == "auto")
    quick = validate_clip(clip, quick=True)  # what blendsr dataset runs on every finished clip
    assert not quick.ok and "dark-frame" in quick.codes()
    from gbuffer_export.dataset.build import quick_check
    assert "[dark-frame]" in quick_check(clip)
    cli = run_cli("validate", str(clip))
    assert cli.returncode == 1 and "dark-frame" in cli.stdout + cli.stderr


def test_a_dark_but_exposed_clip_passes_and_an_unlit_one_does_not(tmp_path):
    """Exposure decides: the dim clip of exposure 1 fails, the same data with the auto exposure recorded passes."""
    dim = _clip(tmp_path, "dim", light=1e-4)
    assert "dark-frame" in validate_clip(dim).codes()
    edit_header(dim, lambda m: m.__setitem__("exposure", {"mode": "fixed", "value": 0.18 / (1e-4 * BRIGHT)}))
    assert validate_clip(dim).ok


def test_dark_pixels_beyond_a_fifth_of_the_frame_fail_even_at_a_good_log_average(tmp_path):
    clip = _clip(tmp_path)
    p = buffer_path(clip, 2, "hr", "radiance")
    a = read_exr(p, ("R", "G", "B"))
    a[: int(0.3 * a.shape[0])] = 1e-5  # 30% of the rows nearly black, the rest as it was
    write_exr(p, {c: a[..., i] for i, c in enumerate("RGB")})
    r = validate_clip(clip)
    (hit,) = [f for f in r.errors if f.code == "dark-frame"]
    assert hit.frame == 2 and hit.details["dark_fraction"] == pytest.approx(0.3, abs=0.03)


def test_near_and_far_content(tmp_path):
    from gbuffer_export.validate.exposure import depth_ratio
    d = np.full((10, 10, 1), 2.0, np.float32)
    assert depth_ratio({"depth": d}) == 1.0
    d[:5] = 10.0
    assert depth_ratio({"depth": d}) == 5.0
    d[:2] = np.inf  # 20% background: the far decile is the sky
    assert depth_ratio({"depth": d}) == math.inf
    assert depth_ratio({"depth": np.full((4, 4, 1), np.inf, np.float32)}) is None
    r = validate_clip(_clip(tmp_path))
    assert r.stats["near_far_fraction"] == 1.0 and "flat-view" not in r.codes()


# ------------------------------------------------------------------------------------------- every reader

def test_previews_and_exporters_read_the_exposed_radiance(dim_auto, tmp_path):
    from gbuffer_export.formats.nss import export_clip, nss_to_clip
    from gbuffer_export.formats.rdg import rdg_buffer
    from gbuffer_export.preview import contact_sheet, contact_sheet_layout
    c = open_clip(dim_auto)
    exposed = c.read(1, "hr/radiance", exposed=True)
    # contact sheet: the dim clip is visibly lit (its physical radiance would encode to black)
    from PIL import Image
    sheet = np.asarray(Image.open(contact_sheet(c, tmp_path / "sheet.png", frames=[1], legend=False)))
    x, y, w, h = contact_sheet_layout(c, frames=[1], legend=False).tile("hr/radiance").box
    tile = sheet[y:y + h, x:x + w]
    assert tile.mean() > 60, tile.mean()
    # RDG: the image and the emission of the exposed radiance
    np.testing.assert_allclose(rdg_buffer(c, 1, "hr", "Image"), exposed, rtol=1e-6)
    # NSS: exposed colour with Exposure 1 (no exposure left to apply), the clip's multiplier in BlendSR.exposure
    meta, = export_clip(dim_auto, tmp_path / "nss", 0)
    assert {fr["Exposure"] for fr in meta["Frames"]} == {1.0} and meta["BlendSR"]["exposure"] == c.exposure
    gt = read_exr(tmp_path / "nss" / "ground_truth" / "0000" / "0000.exr", ("R", "G", "B"))
    np.testing.assert_allclose(gt, exposed, rtol=2e-3, atol=1e-4)  # half floats
    # importing: a frame's Exposure multiplies its colour
    seq = tmp_path / "nss" / "0000.json"
    m = json.loads(seq.read_text())
    m["Frames"][0]["Exposure"] = 4.0
    seq.write_text(json.dumps(m))
    back = open_clip(nss_to_clip(tmp_path / "nss", 0, tmp_path / "back"))
    np.testing.assert_allclose(back.read(0, "hr/radiance"), 4 * gt, rtol=1e-6)
    assert back.exposure == 1.0
    m["Frames"][0]["Exposure"] = -1
    seq.write_text(json.dumps(m))
    from gbuffer_export.formats.nss import NssError
    with pytest.raises(NssError, match=r"Frames\[0\]\.Exposure"):
        nss_to_clip(tmp_path / "nss", 0, tmp_path / "back2")


def test_training_and_inference_read_the_exposed_radiance(dim_auto, tmp_path):
    pytest.importorskip("torch")
    from training.cache import ClipCache
    from training.inference.loading import ClipFrames
    c = open_clip(dim_auto)
    want = c.read(2, "hr/radiance", exposed=True)
    src = tmp_path / "clip"
    shutil.copytree(dim_auto, src)
    cache = ClipCache(src)
    cache.ensure(["hr/radiance"])
    np.testing.assert_allclose(cache.read(2, "hr/radiance"), want, rtol=2e-3)  # the cache may store half
    np.testing.assert_allclose(ClipFrames(src).read(2, "lr/radiance"), c.read(2, "lr/radiance", exposed=True),
                               rtol=1e-6)


def test_an_auto_clip_written_by_two_writers_meters_every_frame(dim_auto, tmp_path):
    """Shards and resumed runs: each writer meters the frames it writes, every merge computes the exposure over all
    finished frames, and the header read back from the manifest is the same clip (its metered keys are no part of
    the identity)."""
    from gbuffer_export.clip import ClipWriter
    from gbuffer_export.conventions import BUFFERS
    src = open_clip(dim_auto)
    header = {k: v for k, v in src.manifest.items() if k not in ("frame_data", "identity")}
    out = tmp_path / "two"
    for frames in ((1, 2), (3,)):
        w = ClipWriter(out, header)
        for f in frames:
            for lvl in src.levels:
                for b in src.buffers:
                    w.write_buffer(f, lvl, b, read_exr(buffer_path(dim_auto, f, lvl, b), BUFFERS[b].channels))
            w.commit_frame(f, {k: {kk: vv for kk, vv in v.items() if kk != "luminance"}
                               for k, v in src.record(f).items()})
        w.close()
        m = open_clip(out).manifest
        assert m["exposure"]["frames_metered"] == len(m["frame_data"]) == max(frames)
    assert m["exposure"]["value"] == pytest.approx(src.exposure, rel=1e-9)
    assert m["identity"] == src.manifest["identity"]
    assert validate_clip(out).ok


def test_the_documented_thresholds_are_the_code_s():
    from pathlib import Path

    from gbuffer_export.validate import CODES
    from gbuffer_export.validate import exposure as ve
    doc = (Path(__file__).resolve().parents[2] / "docs" / "clip-format.md").read_text()
    for v in (ve.DARK_LOG_AVERAGE, ve.DARK_LUMINANCE, ve.BRIGHT_LOG_AVERAGE, ve.NEAR_FAR_RATIO):
        forms = (f"{v:g}", f"{v:.1f}", f"{v:.0e}".replace("e-0", "e-"))
        assert any(f"**{t}**" in doc for t in forms), v
    for v in (ve.DARK_MAX_FRACTION, ve.NEAR_FAR_MIN_FRACTION):
        assert f"**{100 * v:g}%**" in doc, v
    assert f"{ve.DARK_LOG_AVERAGE:g}" in CODES["dark-frame"] and "1e-3" in CODES["dark-frame"]
    assert ve.DARK_LUMINANCE == 1e-3
    assert f"{100 * ve.DARK_MAX_FRACTION:g}%" in CODES["dark-frame"]
    assert f"{ve.BRIGHT_LOG_AVERAGE:g}" in CODES["bright-frame"]
    assert f"{100 * ve.NEAR_FAR_MIN_FRACTION:g}%" in CODES["flat-view"]
    assert f"{ve.NEAR_FAR_RATIO:g}" in CODES["flat-view"]
    lo, hi = cv.AUTO_EXPOSURE_BAND
    assert f'"band": [{lo}, {hi}]' in doc and f'"key": {cv.EXPOSURE_KEY:g}' in doc


@pytest.mark.bpy
@requires_bpy
def test_a_scene_lit_by_a_weak_lamp_renders_well_exposed(blend_dir, tmp_path):
    """Blender end to end: a scene lit by a 0.01 W lamp and a sky of 1e-4 (its own light, in other units; a black
    sky would leave 40% of the frame black at any exposure, which validate refuses) is rendered with the
    default auto exposure: its physical radiance is stored, the manifest records an exposure that brings it to
    middle grey, the clip validates and its contact sheet is lit. Read at exposure 1 it is practically black."""
    scene = make_blend("dimlamp", blend_dir / "dimlamp.blend")
    out = tmp_path / "clip"
    # --light scene: the file's own weak light alone (auto would add a sun and sky to a view this dim, then expose)
    proc = run_cli("render", str(scene), "-o", str(out), "--frames", "1:2", "--hr-size", "64x36", "--scale", "2",
                   "--hr-spp", "8", "--lr-spp", "2", "--threads", "1", "--no-progress", "--light", "scene")
    assert proc.returncode == 0, proc.stderr[-2000:]
    c = open_clip(out)
    block = c.manifest["exposure"]
    assert block["mode"] == "auto" and block["frames_metered"] == 2
    assert block["log_average"] < 1e-3 and c.exposure > 100  # a dim render, brought up
    assert block["log_average"] == pytest.approx(_hr_log_average(out), rel=1e-5)
    r = validate_clip(out)
    assert r.ok, [f.line() for f in r.errors]
    assert all(0.02 <= v["log_average"] <= 2.0 for v in r.stats["exposed_frames"].values())
    from PIL import Image

    from gbuffer_export.preview import contact_sheet, contact_sheet_layout
    sheet = np.asarray(Image.open(contact_sheet(c, tmp_path / "sheet.png", frames=[1], legend=False)))
    x, y, w, h = contact_sheet_layout(c, frames=[1], legend=False).tile("hr/radiance").box
    assert sheet[y:y + h, x:x + w].mean() > 40  # the HR radiance tile
    edit_manifest(out, lambda m: m.pop("exposure"))  # the same data read at exposure 1
    assert "dark-frame" in validate_clip(out).codes()


def test_a_malformed_metering_is_no_metering():
    rec = {"hr": {"luminance": {"log_mean": "x", "lit_pixels": 4}}}
    assert cv.frame_luminance(rec) is None
    assert cv.frame_luminance({"hr": {"luminance": {"log_mean": 0.5, "lit_pixels": -1}}}) is None
    good = {"hr": {"luminance": {"log_mean": -1.0, "lit_pixels": 4, "pixels": 4}}}
    assert cv.frame_luminance(good) == good["hr"]["luminance"]
    block = cv.exposure_header("auto")["exposure"]
    m = cv.metered_exposure(block, {"1": rec, "2": good, "3": "not a record"})
    assert m["frames_metered"] == 1 and m["log_average"] == pytest.approx(math.exp(-1.0)) and m["value"] == 1.0
