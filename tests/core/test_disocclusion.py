"""Disocclusion masks (gbuffer_export.disocclusion): an analytic sliding square, and a Cycles render of a box sliding
in front of a wall (tests/scenes.py ``occluder``), where the wall pixels the box uncovers are known from the flags."""
from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import make_blend, requires_bpy, run_cli
from gbuffer_export import disocclusion, open_clip
from gbuffer_export.conventions import Flag, backward_warp
from gbuffer_export.synthetic import make_synthetic_clip

H, W, SHIFT = 24, 40, 3  # a square sliding SHIFT px to the right per frame


def _square(x0):
    m = np.zeros((H, W), bool)
    m[8:16, x0:x0 + 8] = True
    return m


def _sliding_square():
    """Frames t-1 (square at x 10..17) and t (13..20) of a static camera: motion of t, motion_next of t-1, depths."""
    prev, cur = _square(10), _square(10 + SHIFT)
    motion = np.zeros((H, W, 2))
    motion[cur, 0] = -SHIFT
    motion_next_prev = np.zeros((H, W, 2))
    motion_next_prev[prev, 0] = SHIFT
    depth_prev, depth = np.where(prev, 2.0, 5.0), np.where(cur, 2.0, 5.0)
    uncovered = prev & ~cur
    return motion, motion_next_prev, depth, depth_prev, uncovered


def test_sliding_square_flags_exactly_the_uncovered_pixels():
    motion, motion_next_prev, depth, depth_prev, uncovered = _sliding_square()
    assert uncovered.sum() == 8 * SHIFT
    k, eye = (30.0, 30.0, W / 2, H / 2), np.eye(4)
    by_motion = disocclusion.from_motion(motion, motion_next_prev)
    cam = {"intrinsics": k, "world_from_camera": eye, "prev_world_from_camera": eye}
    by_depth = disocclusion.from_depth(depth, motion, depth_prev, cam)
    np.testing.assert_array_equal(by_motion, uncovered)
    np.testing.assert_array_equal(by_depth, uncovered)


def test_motion_leaving_the_image_is_flagged():
    motion = np.zeros((H, W, 2))
    motion[:, :, 0] = -2.0  # everything was 2 px further left: the 2 leftmost columns came from outside
    mask = disocclusion.from_motion(motion, -motion)
    assert mask[:, :1].all() and not mask[:, 2:].any()


def test_jitter_difference_moves_the_sample():
    """Frame t's samples sit 1 px right of frame t-1's (jitter +0.5 vs -0.5): pixel p of frame t is checked against
    frame t-1's pixel p + 1."""
    motion = np.zeros((H, W, 2))
    mn = np.zeros((H, W, 2))
    mn[:, 20] = (5.0, 0.0)  # one column of frame t-1 whose forward motion does not come back
    plain = disocclusion.from_motion(motion, mn)
    shifted = disocclusion.from_motion(motion, mn, jitter=(0.5, 0.0), jitter_prev=(-0.5, 0.0))
    assert np.flatnonzero(plain.any(axis=0)).tolist() == [20]
    assert np.flatnonzero(shifted[:, :-1].any(axis=0)).tolist() == [19]  # (the last column leaves the image)


def test_methods_agree_on_a_static_synthetic_clip(tmp_path):
    """Independent computations (forward motion vs. depth and cameras) on an exact static clip at HR."""
    clip = open_clip(make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4))
    for f in (2, 3):
        a, b = (disocclusion.clip_mask(clip, f, "hr", m) for m in ("motion", "depth"))
        assert 0.01 < a.mean() < 0.2 and np.mean(a == b) > 0.95, (a.mean(), b.mean(), np.mean(a == b))


def test_motion_next_is_written_on_request_and_for_nsrd():
    from gbuffer_export.conventions import DEFAULT_BUFFERS, parse_buffer_list
    from gbuffer_export.dataset.buffers import buffers_for_models
    assert "motion_next" not in DEFAULT_BUFFERS and "motion_next" in parse_buffer_list("all")
    assert "motion_next" in buffers_for_models(["nsrd"]) and "motion_next" not in buffers_for_models(["fusesr"])


def test_bad_input(tmp_path):
    clip = open_clip(make_synthetic_clip(tmp_path / "c", frames=range(1, 3), hr_size=(16, 8), scale=2,
                                         buffers=("radiance", "depth", "motion", "flags")))
    with pytest.raises(ValueError, match="frames 0 and 1 must both be finished"):
        disocclusion.clip_mask(clip, 1, "hr")
    with pytest.raises(ValueError, match="method 'flow'"):
        disocclusion.clip_mask(clip, 2, "hr", "flow")
    assert disocclusion.clip_mask(clip, 2, "hr").shape == (8, 16)  # auto: depth (no motion_next)


@requires_bpy
@pytest.mark.bpy
def test_known_occluder_render(blend_dir, tmp_path):
    """Wall pixels of frame t that the sliding box covered in frame t-1 (read from frame t-1's MOVING flags at the
    motion's target) are flagged by both methods at both levels (LR jittered); wall and box pixels seen in both
    frames are not. Pixels whose target straddles the box's edge belong to neither set."""
    blend = make_blend("occluder", blend_dir / "occluder.blend")
    out = tmp_path / "clip"
    run_cli("render", blend, "-o", out, "--frames", "2:4", "--hr-size", "64x36", "--scale", "2", "--jitter", "halton",
            "--buffers", "radiance,depth,motion,motion_next,flags", "--hr-spp", "4", "--lr-spp", "2", "--gbuffer-spp",
            "1", "--no-progress", check=True)
    assert run_cli("validate", out).returncode == 0  # motion_next checked against reprojection
    clip = open_clip(out)
    for lvl in ("hr", "lr"):
        for f in (3, 4):
            cam, cam_prev = clip.camera(f, lvl), clip.camera(f - 1, lvl)
            moving = (clip.read(f, f"{lvl}/flags")[..., 0] & int(Flag.MOVING)) != 0
            moving_prev = (clip.read(f - 1, f"{lvl}/flags")[..., 0] & int(Flag.MOVING)) != 0
            off = disocclusion.sample_offset(clip.read(f, f"{lvl}/motion"), cam["jitter"], cam_prev["jitter"])
            was_box, inside = backward_warp(moving_prev.astype(np.float64), off)
            uncovered = ~moving & inside & (was_box == 1.0)
            wall_both = ~moving & inside & (was_box == 0.0)
            box_both = moving & inside & (was_box == 1.0)
            assert uncovered.sum() >= 10 and wall_both.sum() >= 100 and box_both.sum() >= 50
            for method in ("motion", "depth"):
                mask = disocclusion.clip_mask(clip, f, lvl, method)
                assert mask[uncovered].mean() >= 0.95, (lvl, f, method, mask[uncovered].mean())
                assert mask[wall_both].mean() <= 0.01, (lvl, f, method, mask[wall_both].mean())
                assert mask[box_both].mean() <= 0.05, (lvl, f, method, mask[box_both].mean())
