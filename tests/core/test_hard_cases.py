"""Hard cases across the numpy core: off-screen motion, disocclusions, one-frame clips, 1x1 levels, +inf depth."""
from __future__ import annotations

import numpy as np
import pytest

from gbuffer_export import open_clip
from gbuffer_export.conventions import backward_warp, reprojection_motion, transform_points, unproject
from gbuffer_export.demod import demodulate, remodulate
from gbuffer_export.synthetic import make_synthetic_clip
from gbuffer_export.validate import validate_clip


def test_motion_pointing_off_screen_is_invalid_not_nan():
    img = np.arange(5 * 6 * 3, dtype=np.float32).reshape(5, 6, 3)
    motion = np.zeros((5, 6, 2), np.float32)
    motion[:, :2, 0] = -10.0          # left columns come from outside the image
    motion[0, 5] = (np.nan, np.inf)   # garbage vector
    out, valid = backward_warp(img, motion, fill=-1.0)
    assert np.isfinite(out).all()
    assert not valid[:, :2].any() and not valid[0, 5] and valid[1:, 2:].all()
    assert np.all(out[:, :2] == -1.0) and np.array_equal(out[1:, 2:], img[1:, 2:])


def test_disocclusions_are_detected_by_depth_consistency(tmp_path):
    """Where the camera's motion reveals ground hidden by a sphere in frame t-1, warping frame t-1 by the
    (correct) motion lands on the sphere: the warped depth disagrees with the reprojected depth there."""
    clip = open_clip(make_synthetic_clip(tmp_path / "c", frames=[1, 2], hr_size=(128, 72)))
    cam = clip.camera(2, "hr")
    d_cur = clip.read(2, "hr/depth")[..., 0]
    d_prev = clip.read(1, "hr/depth")[..., 0]
    motion = clip.read(2, "hr/motion")
    assert np.isfinite(motion).all()
    warped, valid = backward_warp(np.where(np.isfinite(d_prev), d_prev, 1e6)[..., None], motion)
    pts_prev = transform_points(np.linalg.inv(cam["prev_world_from_camera"]) @ cam["world_from_camera"],
                                unproject(np.where(np.isfinite(d_cur), d_cur, 1.0), cam["intrinsics"]))
    expected_prev_depth = -pts_prev[..., 2]
    surf = np.isfinite(d_cur) & valid
    rel = np.abs(warped[..., 0] - expected_prev_depth) / expected_prev_depth
    disoccluded = surf & (rel > 0.05)
    assert 0 < disoccluded.sum() < 0.15 * surf.sum()   # bands at silhouettes, not everywhere
    assert np.median(rel[surf]) < 1e-3                   # elsewhere the warp is exact


def test_one_frame_clip_and_1x1_level(tmp_path):
    path = make_synthetic_clip(tmp_path / "tiny", frames=[7], hr_size=(4, 4), scale=4)
    rep = validate_clip(path)
    assert rep.ok, [f.line() for f in rep.errors]
    clip = open_clip(path)
    assert clip.frames == [7] and clip.sizes["lr"] == (1, 1)
    lr = {b: clip.read(7, f"lr/{b}") for b in ("radiance", "emission", "fbeta", "flags")}
    irr, used = demodulate(lr["radiance"], lr["emission"], lr["fbeta"], lr["flags"])
    assert irr.shape == (1, 1, 3) and np.isfinite(irr).all()
    assert np.array_equal(remodulate(irr, used, lr["emission"]), lr["radiance"])
    # the first (and only) frame still has a previous camera, so its motion is defined
    assert np.isfinite(clip.read(7, "hr/motion")).all()


def test_background_depth_is_inf_and_motion_finite(tmp_path):
    clip = open_clip(make_synthetic_clip(tmp_path / "c", frames=[1, 2]))
    d = clip.read(2, "hr/depth")[..., 0]
    bg = ~np.isfinite(d)
    assert bg.any() and np.all(d[bg] == np.inf)
    cam = clip.camera(2, "hr")
    m = reprojection_motion(d, cam["intrinsics"], cam["world_from_camera"], cam["prev_intrinsics"],
                            cam["prev_world_from_camera"])
    assert np.isfinite(m).all()
    assert np.allclose(m[bg], clip.read(2, "hr/motion")[bg], atol=1e-4)


@pytest.mark.torch
def test_models_run_on_a_one_frame_1x1_clip(tmp_path):
    pytest.importorskip("torch")
    from training.inference.loading import load_model, upscale_frame
    clip = open_clip(make_synthetic_clip(tmp_path / "tiny", frames=[3], hr_size=(4, 4), scale=4))
    for name in ("bicubic", "demod-bilinear"):
        out = upscale_frame(load_model(name, 4), clip, 3)
        assert out["sr"].shape == (4, 4, 3) and np.isfinite(out["sr"]).all()
