"""Arm's NSS capture layout (gbuffer_export/formats): conventions against independent computations, the round trip
of a synthetic clip, and reprojection through the exported matrices on a tiny Cycles render."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tests.conftest import requires_bpy, run_cli
from gbuffer_export import open_clip
from gbuffer_export.conventions import Flag, pixel_grid, project, transform_points, unproject
from gbuffer_export.exr import read_exr, read_exr_channels
from gbuffer_export.formats import conventions as cv
from gbuffer_export.formats import nss
from gbuffer_export.synthetic import make_synthetic_clip

HALF_REL = 2.0 ** -11  # half precision: relative rounding error


def _camera(seed=0):
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(-0.5, 0.5, 2)
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    rz = np.array([[math.cos(b), -math.sin(b), 0], [math.sin(b), math.cos(b), 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rz @ rx, rng.uniform(-3, 3, 3)
    return m


def test_ratio_names_match_the_model_gym():
    assert [cv.ratio_name(s) for s in (2, 2.0, 1.5, 2.5, 3, 4)] == ["2", "2", "1_5", "2_5", "3", "4"]


def test_motion_uv_sign_and_units():
    m = np.zeros((4, 8, 2))
    m[..., 0], m[..., 1] = 2.0, -1.0  # surface was 2 px to the right and 1 px higher in the previous frame
    uv = cv.motion_to_uv(m)
    assert np.allclose(uv[..., 0], -2 / 8) and np.allclose(uv[..., 1], 1 / 4)  # current - previous, UV units
    assert np.allclose(cv.uv_to_motion(uv), m)


def test_device_depth_is_forward_z_with_the_planes():
    n, f = 0.5, 40.0
    z = np.array([n, 0.99 * f, 3.0, np.inf])
    d = cv.view_depth_to_device(z, n, f)
    assert d[0] == pytest.approx(0.0) and cv.view_depth_to_device(f, n, f) == pytest.approx(1.0) and d[3] == 1.0 and 0 < d[2] < 1
    back = cv.device_to_view_depth(d, n, f)
    assert np.allclose(back[:3], z[:3]) and np.isinf(back[3])


def test_view_projection_agrees_with_blendsr_projection():
    """NDC of the exported matrix against conventions.project (BlendSR's own pinhole), and the depth it gives."""
    w, h, n, f = 40, 24, 0.3, 60.0
    k = (35.0, 35.0, 19.0, 12.5)
    wfc = _camera(1)
    depth = np.random.default_rng(2).uniform(1, 20, (h, w))
    pts_cam = unproject(depth, k, (0.2, -0.3))
    world = transform_points(wfc, pts_cam)
    vp = cv.list_to_matrix(cv.matrix_to_list(cv.view_projection(wfc, k, w, h, n, f)))
    clip = np.concatenate([world, np.ones(world.shape[:2] + (1,))], -1) @ vp.T
    ndc = clip[..., :3] / clip[..., 3:]
    xs, ys = project(pts_cam, k)
    assert np.allclose((ndc[..., 0] + 1) / 2 * w, xs) and np.allclose((1 - ndc[..., 1]) / 2 * h, ys)
    assert np.allclose(ndc[..., 2], cv.view_depth_to_device(depth, n, f))
    rev = cv.view_projection(wfc, k, w, h, n, f, reverse_z=True)  # what the exports write: NDC z = 1 - d
    crev = np.concatenate([world, np.ones(world.shape[:2] + (1,))], -1) @ rev.T
    assert np.allclose(crev[..., 2] / crev[..., 3], 1 - cv.view_depth_to_device(depth, n, f))
    assert np.allclose(crev[..., [0, 1, 3]], clip[..., [0, 1, 3]])
    wfc2, k2 = cv.camera_from_view_projection(vp, w, h)
    assert np.allclose(wfc2, wfc) and np.allclose(k2, k)
    fx, fy = cv.fov(k, w, h)
    assert math.tan(fx / 2) == pytest.approx(w / 2 / k[0]) and math.tan(fy / 2) == pytest.approx(h / 2 / k[1])


@pytest.fixture(scope="module")
def synthetic_export(tmp_path_factory):
    root = tmp_path_factory.mktemp("nss")
    clip = make_synthetic_clip(root / "clip", frames=range(1, 5), hr_size=(40, 24), scales=(2, 4), jitter=True)
    nss.export_nss([clip], root / "nss")
    return clip, root / "nss"


def test_layout_and_json_follow_the_specification(synthetic_export):
    _, out = synthetic_export
    meta = json.loads((out / "0000.json").read_text())
    for key in ("Version", "EmulatedFramerate", "TargetResolution", "Samples", "Frames", "ReverseZ"):
        assert key in meta
    assert meta["TargetResolution"] == {"X": 40, "Y": 24}
    assert meta["UpscalingRatiosIndices"] == {"x2_index": 0, "x4_index": 1}
    assert [fr["CameraCut"] for fr in meta["Frames"]] == [True, False, False, False]
    for fr in meta["Frames"]:
        for key in ("Frame", "FovX", "FovY", "CameraNearPlane", "CameraFarPlane", "ViewProjection", "Jitter",
                    "NormalizedPerRatioJitter"):
            assert key in fr
        assert len(fr["ViewProjection"]) == 16 and len(fr["NormalizedPerRatioJitter"]) == 2
    types = {"ground_truth": ("RGBA", np.float16, (24, 40)), "motion_gt": ("RG", np.float16, (24, 40)),
             "x2/color": ("RGBA", np.float16, (12, 20)), "x2/depth": ("R", np.float32, (12, 20)),
             "x2/motion": ("RG", np.float16, (12, 20)), "x4/color": ("RGBA", np.float16, (6, 10)),
             "x4/depth": ("R", np.float32, (6, 10)), "x4/motion": ("RG", np.float16, (6, 10))}
    for d, (chans, dtype, shape) in types.items():
        files = sorted((out / d / "0000").glob("*.exr"))
        assert [p.name for p in files] == ["0000.exr", "0001.exr", "0002.exr", "0003.exr"]
        ch = read_exr_channels(files[0])
        assert sorted(ch) == sorted(chans) and all(a.dtype == dtype and a.shape == shape for a in ch.values())


def test_round_trip_within_half_precision(synthetic_export):
    clip_path, out = synthetic_export
    clip = open_clip(clip_path)
    for j, f in enumerate(clip.frames):
        fr = nss.read_frame(out, 0, j)
        pairs = [("hr/radiance", "hr/radiance"), ("hr/motion", "hr/motion")]
        for r, lvl in (("2", "lr"), ("4", "lr_x4")):
            pairs += [(f"{r}/radiance", f"{lvl}/radiance"), (f"{r}/motion", f"{lvl}/motion"),
                      (f"{r}/depth", f"{lvl}/depth")]
            assert np.allclose(fr[f"{r}/jitter"], clip.camera(f, lvl)["jitter"], atol=1e-9)
        for key, ck in pairs:
            a, b = fr[key], clip.read(f, ck)
            if key.endswith("depth"):
                b = b[..., 0]
                assert np.array_equal(np.isinf(a), np.isinf(b))
                fin = np.isfinite(b)
                assert np.allclose(a[fin], b[fin], rtol=1e-5)  # float32 device depth
            elif key.endswith("motion"):
                h, w = b.shape[:2]  # half UV: error relative to the UV value, in pixels of the level
                assert np.all(np.abs(a - b) <= HALF_REL * np.abs(b) + 1e-7 * max(w, h))
            else:
                assert np.all(np.abs(a - b) <= HALF_REL * np.abs(b) + 1e-7)
        cam = clip.camera(f, "hr")
        assert np.allclose(fr["world_from_camera"], cam["world_from_camera"], atol=1e-6)
        assert np.allclose(fr["intrinsics"], cam["intrinsics"], rtol=1e-6)


def test_import_gives_a_blendsr_clip(synthetic_export, tmp_path):
    clip_path, out = synthetic_export
    back = open_clip(nss.nss_to_clip(out, 0, tmp_path / "back"))
    src = open_clip(clip_path)
    assert back.scales == src.scales and back.sizes == src.sizes and len(back.frames) == len(src.frames)
    j, f = 2, src.frames[2]
    assert np.allclose(back.read(j, "lr_x4/motion"), src.read(f, "lr_x4/motion"), atol=1e-3)
    assert np.allclose(back.camera(j, "lr")["prev_world_from_camera"], src.camera(f, "lr")["prev_world_from_camera"],
                       atol=1e-6)


def exported_reprojection_error(out, ratio: str | None, j: int, hr_device_depth=None):
    """Pixels: exported motion minus the reprojection of the exported depth through the exported ViewProjection
    matrices of frames j and j - 1 (nothing of BlendSR's own conventions), at the jittered sample positions.
    ``ratio`` None: the HR ``motion_gt`` (NSS has no HR depth: ``hr_device_depth`` gives it)."""
    meta = json.loads((out / "0000.json").read_text())
    rec, prev = meta["Frames"][j], meta["Frames"][j - 1]
    fn = f"{j:04d}.exr"
    if ratio is None:
        d = np.asarray(hr_device_depth, np.float64)
        uv = read_exr(out / "motion_gt" / "0000" / fn, ("R", "G")).astype(np.float64)
        nj = {"X": 0.0, "Y": 0.0}
    else:
        d = read_exr(out / f"x{ratio}" / "depth" / "0000" / fn, ("R",))[..., 0].astype(np.float64)
        uv = read_exr(out / f"x{ratio}" / "motion" / "0000" / fn, ("R", "G")).astype(np.float64)
        nj = rec["NormalizedPerRatioJitter"][meta["UpscalingRatiosIndices"][f"x{ratio}_index"]]
    h, w = d.shape
    xs, ys = pixel_grid(h, w)
    xs, ys = xs + nj["X"] * w, ys + nj["Y"] * h
    # the matrix's NDC z is 1 - the stored forward-Z depth (reverse-Z, as Arm's NFRU reader reprojects)
    ndc = np.stack([2 * xs / w - 1, 1 - 2 * ys / h, 1.0 - d, np.ones_like(d)], -1)
    # Arm's layout (the model gym's readers): reshape row by row to the matrix that multiplies column vectors
    world = ndc @ np.linalg.inv(np.asarray(rec["ViewProjection"]).reshape(4, 4)).T
    clip_prev = world @ np.asarray(prev["ViewProjection"]).reshape(4, 4).T
    xp = (clip_prev[..., 0] / clip_prev[..., 3] + 1) / 2 * w
    yp = (1 - clip_prev[..., 1] / clip_prev[..., 3]) / 2 * h
    expected = np.stack([(xs - xp) / w, (ys - yp) / h], -1)  # current - previous, UV
    return (uv - expected) * np.array([w, h]), d < 1.0


@requires_bpy
@pytest.mark.bpy
def test_reprojection_through_exported_matrices_on_a_render(tmp_path_factory):
    root = tmp_path_factory.mktemp("nss_render")
    clip = root / "clip"
    run_cli("render", "-o", clip, "--frames", "1:3", "--hr-size", "64x36", "--scales", "2,4", "--hr-spp", "2",
            "--lr-spp", "1", "--gbuffer-spp", "1", "--threads", "1", "--buffers", "radiance,depth,motion,flags",
            "--no-progress", check=True)
    out = root / "nss"
    run_cli("export-dataset", clip, "--format", "nss", "-o", out, check=True)
    c = open_clip(clip)
    for ratio, lvl in (("2", "lr"), ("4", "lr_x4")):
        for j in (1, 2):
            err, surface = exported_reprojection_error(out, ratio, j)
            flags = c.read(c.frames[j], f"{lvl}/flags")[..., 0]
            static = surface & ((flags & int(Flag.MOVING | Flag.ALPHA | Flag.BACKGROUND)) == 0)
            assert static.sum() > 50
            within = np.mean(np.hypot(err[..., 0], err[..., 1])[static] <= 0.01)
            assert within >= 0.99, (ratio, j, within)
    meta = json.loads((out / "0000.json").read_text())
    for j in (1, 2):  # HR motion_gt, with the clip's HR depth in the exported near/far convention
        rec = meta["Frames"][j]
        z = c.read(c.frames[j], "hr/depth")[..., 0]
        err, surface = exported_reprojection_error(
            out, None, j, cv.view_depth_to_device(z, rec["CameraNearPlane"], rec["CameraFarPlane"]))
        flags = c.read(c.frames[j], "hr/flags")[..., 0]
        static = surface & ((flags & int(Flag.MOVING | Flag.ALPHA | Flag.BACKGROUND)) == 0)
        assert np.mean(np.hypot(err[..., 0], err[..., 1])[static] <= 0.01) >= 0.99


# ----------------------------------------------------------------------------------------------
# RDG
# ----------------------------------------------------------------------------------------------

def test_rdg_layout_and_encodings(synthetic_export, tmp_path):
    from gbuffer_export.conventions import backward_warp
    from gbuffer_export.formats import rdg
    from gbuffer_export.formats.png import read_png
    clip_path, _ = synthetic_export
    out = tmp_path / "rdg"
    scenes = rdg.export_rdg([clip_path], out)
    scene = next(iter(scenes))
    clip = open_clip(clip_path)
    assert (out / "meta_info_train.txt").read_text().split() == [scene, "4", "0", "0"]
    assert (out / "meta_info_test.txt").read_text().split() == [scene, "4", "0"]
    for root, lvl in (("GT", "hr"), ("LR", "lr"), ("LR_x4", "lr_x4")):
        base = out / root / scene
        assert sorted(p.name for p in base.iterdir()) == sorted(["Image", *scenes[scene]])
        f = clip.frames[2]
        img = read_png(base / "Image" / "002.png")
        try:  # an independent PNG decoder, where installed
            from PIL import Image
            assert np.array_equal(np.asarray(Image.open(base / "Image" / "002.png").convert("RGB")), img)
        except ImportError:
            pass
        lin = np.clip(clip.read(f, f"{lvl}/radiance"), 0, 1)
        assert np.abs(cv.srgb_decode(img / 255.0) - lin).max() < 0.02  # 8-bit sRGB steps
        # Motion as their loader reads it (second channel negated) is BlendSR's backward motion: warping frame
        # t-1 with it reproduces frame t where BlendSR's own warp does.
        stored = read_exr(base / "Motion" / "002.exr", ("R", "G", "B"))
        loaded = stored[..., :2] * np.array([1, -1])
        assert np.allclose(loaded, clip.read(f, f"{lvl}/motion"), atol=1e-5) and not stored[..., 2].any()
        warped, _ = backward_warp(clip.read(clip.frames[1], f"{lvl}/radiance"), loaded)
        ref, _ = backward_warp(clip.read(clip.frames[1], f"{lvl}/radiance"), clip.read(f, f"{lvl}/motion"))
        assert np.allclose(warped, ref, atol=1e-4)
        d = read_exr(base / "Depth" / "002.exr", ("R", "G", "B"))
        assert np.isfinite(d).all() and np.array_equal(d[..., 0], d[..., 2])
        n = read_exr(base / "Normal" / "002.exr", ("R", "G", "B"))
        r = clip.camera(f, lvl)["world_from_camera"][:3, :3]
        assert np.allclose(n @ r, clip.read(f, f"{lvl}/normal"), atol=1e-5)  # world space, rotated back


def test_the_nss_round_trip_validates(tmp_path):
    """Issue 56: ``import-nss`` of BlendSR's own NSS export passes ``validate``. The export's first frame points
    at a frame the sequence does not hold: imported, that camera cut has its own camera as the previous one and zero
    motion (its LR and HR motion checks then agree, not "static" against 0.2-0.5 px); the HR depth is interpolated
    (NSS has none), so HR motion is reported as unchecked (a warning), while every LR level's motion is checked."""
    from gbuffer_export.validate import WARNING, validate_clip
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 5), hr_size=(64, 32), scales=(2, 4), jitter=True)
    nss.export_nss([clip], tmp_path / "nss")
    back = nss.nss_to_clip(tmp_path / "nss", "0000", tmp_path / "back")
    report = validate_clip(back)
    assert report.ok, [f.line() for f in report.findings]
    assert report.codes(WARNING) == {"motion-unchecked"}
    b, src = open_clip(back), open_clip(clip)
    assert b.manifest["imported"]["camera_cuts"] == [0]
    assert not np.any(b.read(0, "lr/motion")) and not np.any(b.read(0, "hr/motion"))
    assert np.array_equal(b.camera(0, "lr")["prev_world_from_camera"], b.camera(0, "lr")["world_from_camera"])
    assert np.any(src.read(src.frames[0], "lr/motion"))  # the source did move into its first frame
    per = report.stats["per_frame"]
    assert per["0"]["lr"]["static_fraction"] == 1.0 and per["1"]["lr_x4"]["static_fraction"] >= 0.99
    # the interpolated HR depth is the source's on smooth surfaces (inverse depth is linear on a plane)
    d, ds = b.read(1, "hr/depth")[..., 0], src.read(src.frames[1], "hr/depth")[..., 0]
    fin = np.isfinite(d) & np.isfinite(ds)
    assert np.median(np.abs(d - ds)[fin] / ds[fin]) < 2e-3
