"""End-to-end renders of tiny scenes through ``blendsr render`` (Cycles in a subprocess)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from tests.conftest import requires_bpy, run_cli
from tests.render.cli_batch import make_blends, run_cli_batch
from gbuffer_export import open_clip
from gbuffer_export.conventions import Flag, backward_warp, reprojection_motion

pytestmark = [pytest.mark.bpy, requires_bpy]
FAST = ["--hr-spp", "4", "--lr-spp", "2", "--gbuffer-spp", "1", "--no-progress"]


@pytest.fixture(scope="module")
def blends(tmp_path_factory):
    """The scenes of tests/scenes.py this module renders or refuses, built in one process."""
    return make_blends(["basic", "nocamera", "empty", "ortho"], tmp_path_factory.mktemp("blends"))


@pytest.fixture(scope="module")
def basic_blend(blends):
    return blends["basic"]


@pytest.fixture(scope="module")
def basic_clips(basic_blend, tmp_path_factory):
    """The basic scene's clips, rendered in one process (``cli_batch``): "all" (frames 2:4 at 128x72, every buffer,
    Halton jitter), "rad" (radiance only, frame 1) and "none" (no jitter, frame 3 at 128x72: depth and flags)."""
    root = tmp_path_factory.mktemp("clips")
    run_ok(["render", basic_blend, "-o", root / "all", "--frames", "2:4", "--hr-size", "128x72", "--buffers", "all",
            *FAST],
           ["render", basic_blend, "-o", root / "rad", "--frames", "1:1", "--buffers", "radiance", *FAST],
           ["render", basic_blend, "-o", root / "none", "--frames", "3:3", "--hr-size", "128x72", "--jitter", "none",
            "--buffers", "depth,flags", *FAST])
    return {k: root / k for k in ("all", "rad", "none")}


@pytest.fixture(scope="module")
def basic_clip(basic_clips):
    return basic_clips["all"]


#: the furnace renders: no jitter, white world, the buffers of F_beta's checks
FURNACE = ["--frames", "1:1", "--hr-size", "128x72", "--jitter", "none", "--buffers", "radiance,emission,fbeta,flags",
           "--no-progress"]


@pytest.fixture(scope="module")
def furnace_clips(tmp_path_factory):
    """The furnace scene (64 spp) and the sub-pixel checker in a furnace (HR 64 spp, LR 16) with the footprint and
    the point HR F_beta: scenes built in one process, clips rendered in another."""
    root = tmp_path_factory.mktemp("furnace")
    blends = make_blends(["furnace", "finetex"], root)
    run_ok(["render", blends["furnace"], "-o", root / "furnace", "--hr-spp", "64", "--lr-spp", "64", *FURNACE],
           *[["render", blends["finetex"], "-o", root / fb, "--hr-spp", "64", "--lr-spp", "16", "--hr-fbeta", fb,
              *FURNACE] for fb in ("footprint", "point")])
    return {k: root / k for k in ("furnace", "footprint", "point")}


def run_ok(*argvs):
    """``run_cli_batch`` whose every command must succeed."""
    for proc in run_cli_batch(*argvs):
        assert proc.returncode == 0, f"{' '.join(proc.args)} exited {proc.returncode}:\n{proc.stderr[-3000:]}"


def _motion_agreement(clip, frame, level):
    cam = clip.camera(frame, level)
    depth = clip.read(frame, f"{level}/depth")[..., 0]
    motion = clip.read(frame, f"{level}/motion")
    flags = clip.read(frame, f"{level}/flags")[..., 0]
    ref = reprojection_motion(depth, cam["intrinsics"], cam["world_from_camera"], cam["prev_intrinsics"],
                              cam["prev_world_from_camera"], cam["jitter"])
    err = np.linalg.norm(motion - ref, axis=-1)
    static = np.isfinite(depth) & ((flags & int(Flag.MOVING)) == 0)
    bg = ~np.isfinite(depth)
    return err, static, bg


def test_clip_complete_and_consistent(basic_clip):
    clip = open_clip(basic_clip)
    assert clip.frames == [2, 3, 4] and clip.complete
    assert clip.sizes == {"hr": (128, 72), "lr": (32, 18)}
    m = clip.manifest
    assert m["blender_version"].startswith("5.0") and m["scene"]["file"] == "basic.blend"
    assert len(m["scene"]["sha256"]) == 64
    assert m["material_summary"]["features"].get("metallic") == 1
    for f in clip.frames:
        for lvl in ("hr", "lr"):
            rad = clip.read(f, f"{lvl}/radiance")
            assert rad.dtype == np.float32 and np.isfinite(rad).all() and rad.max() > 0.05
            n = clip.read(f, f"{lvl}/normal")
            depth = clip.read(f, f"{lvl}/depth")[..., 0]
            surf = np.isfinite(depth)
            assert surf.mean() > 0.3 and (~surf).mean() > 0.05  # sky is visible
            assert np.allclose(np.linalg.norm(n[surf], axis=-1), 1, atol=1e-3)
            fb = clip.read(f, f"{lvl}/fbeta")
            assert np.all(fb[~surf] == 1.0) and fb[surf].min() >= 0 and fb[surf].max() <= 1.05
            flags = clip.read(f, f"{lvl}/flags")[..., 0]
            assert np.all((flags & int(Flag.BACKGROUND)) == np.where(surf, 0, int(Flag.BACKGROUND)))
            # ground plane has no material, the cube moves
            assert (flags & int(Flag.NO_MATERIAL)).any() and (flags & int(Flag.MOVING)).any()
    # the ground (no material) at the bottom centre faces the camera: camera-space normal mostly +Y/+Z
    n = clip.read(3, "hr/normal")[-2, 64]
    assert n[1] > 0.1 and n[2] > 0.1


def test_motion_matches_reprojection(basic_clip):
    clip = open_clip(basic_clip)
    for f in clip.frames:
        for lvl in ("hr", "lr"):
            err, static, bg = _motion_agreement(clip, f, lvl)
            assert np.mean(err[static] < 0.05) > 0.95, (f, lvl, np.median(err[static]))
            assert np.mean(err[bg] < 0.05) > 0.99, (f, lvl)
            assert np.abs(clip.read(f, f"{lvl}/motion")[bg]).max() > 0.01  # camera rotates: bg moves


def test_first_frame_motion_is_meaningful(basic_clip):
    clip = open_clip(basic_clip)
    cam = clip.camera(2, "hr")
    assert not np.allclose(cam["world_from_camera"], cam["prev_world_from_camera"])
    assert np.abs(clip.read(2, "hr/motion")).max() > 0.5


def test_motion_next_matches_reprojection_and_the_next_frames_motion(basic_clip):
    """motion_next (the Vector pass's Z, W) points to frame t+1: it equals reprojection to the next camera on static
    pixels and the rotation-only field on background, and chaining it with frame t+1's backward motion comes back
    to p everywhere the surface stays visible, the moving cube included."""
    clip = open_clip(basic_clip)
    assert "motion_next" in clip.buffers
    for lvl in ("hr", "lr"):
        for f in clip.frames:
            cam = clip.camera(f, lvl)
            depth = clip.read(f, f"{lvl}/depth")[..., 0]
            flags = clip.read(f, f"{lvl}/flags")[..., 0]
            mn = clip.read(f, f"{lvl}/motion_next")
            ref = reprojection_motion(depth, cam["intrinsics"], cam["world_from_camera"], cam["next_intrinsics"],
                                      cam["next_world_from_camera"], cam["jitter"])
            err = np.linalg.norm(mn - ref, axis=-1)
            static = np.isfinite(depth) & ((flags & int(Flag.MOVING)) == 0)
            assert np.mean(err[static] < 0.05) > 0.95, (lvl, f, np.median(err[static]))
            assert np.mean(err[~np.isfinite(depth)] < 0.01) > 0.99
            if f + 1 in clip.frames and lvl == "hr":  # round trip t -> t+1 -> t on the moving cube
                back, valid = backward_warp(clip.read(f + 1, "hr/motion"), mn)  # motion_{t+1} at p + mn
                moving = ((flags & int(Flag.MOVING)) != 0) & valid
                trip = np.linalg.norm(mn + back, axis=-1)
                assert moving.sum() > 20 and np.median(trip[moving]) < 0.1, np.median(trip[moving])
                assert np.abs(mn[moving]).max() > 0.2  # the cube moves between frames


def test_jitter_sign(basic_clip, basic_clips):
    """LR depth rendered with jitter equals un-jittered depth sampled at p + jitter (1/z is affine on a plane). The
    jittered render is the module's clip (Halton jitter, the default; its frame 3 has jitter (-0.25, 0.17) LR px)."""
    outs = {"none": open_clip(basic_clips["none"]), "halton": open_clip(basic_clip)}
    assert outs["halton"].manifest["render"]["jitter"] == "halton"
    jit = outs["halton"].camera(3, "lr")["jitter"]
    assert np.abs(jit).max() > 0.1
    d0 = outs["none"].read(3, "lr/depth")[..., 0]
    d1 = outs["halton"].read(3, "lr/depth")[..., 0]
    fl = outs["none"].read(3, "lr/flags")[..., 0]
    ground = np.isfinite(d0) & ((fl & int(Flag.NO_MATERIAL)) > 0)
    ground[:, :2] = ground[:, -2:] = False
    h, w = d0.shape
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    inv = 1.0 / d0
    coef, *_ = np.linalg.lstsq(np.stack([xs[ground], ys[ground], np.ones(ground.sum())], 1), inv[ground], rcond=None)
    pred = 1.0 / (coef[0] * (xs + jit[0]) + coef[1] * (ys + jit[1]) + coef[2])
    wrong = 1.0 / (coef[0] * (xs - jit[0]) + coef[1] * (ys - jit[1]) + coef[2])
    sel = ground & np.isfinite(d1)
    err = np.median(np.abs(d1[sel] - pred[sel]) / pred[sel])
    err_wrong = np.median(np.abs(d1[sel] - wrong[sel]) / wrong[sel])
    assert err < 1e-3 and err_wrong > 3 * err, (err, err_wrong)


def test_only_requested_buffers(basic_clips):
    out = basic_clips["rad"]
    clip = open_clip(out)
    assert clip.buffers == ("radiance",)
    assert sorted(p.name for p in (out / "hr").iterdir()) == ["radiance"]
    assert "gbuffer" not in clip.record(1)["hr"]["seconds"]  # no G-buffer render was made
    assert clip.manifest["render"]["passes"]["normal"] is False


def test_resume_and_shards(basic_blend, tmp_path):
    out = tmp_path / "sharded"
    args = ["render", basic_blend, "-o", out, "--frames", "1:4", "--buffers", "radiance,depth,motion", *FAST]
    run_cli(*args, "--shard", "1/2", check=True)
    clip = open_clip(out)
    assert clip.frames == [1, 3] and not clip.complete
    run_cli(*args, "--shard", "2/2", check=True)
    clip = open_clip(out)
    assert clip.frames == [1, 2, 3, 4] and clip.complete
    # interrupted frame: record and one buffer gone -> only that frame is rendered again
    keep = (out / "hr" / "radiance" / "000001.exr").stat().st_mtime_ns
    (out / "frames" / "000003.json").unlink()
    (out / "lr" / "motion" / "000003.exr").unlink()
    assert open_clip(out).frames == [1, 2, 3, 4]  # manifest not yet merged: validation catches the missing file
    proc = run_cli(*args, check=True)
    assert "3 of 4 frames already done" in proc.stderr
    assert (out / "hr" / "radiance" / "000001.exr").stat().st_mtime_ns == keep
    assert (out / "lr" / "motion" / "000003.exr").is_file() and open_clip(out).complete


def test_background_emission_is_the_environment(basic_clip):
    """On background pixels the emission buffer holds the sky the camera sees (the basic scene's uniform world of
    (0.6, 0.7, 1.0)), so radiance - emission, the demodulated L_D there, is 0; surfaces keep their own emission."""
    clip = open_clip(basic_clip)
    assert clip.manifest["render"]["gbuffer"]["emission_background"] == "environment"
    for lvl in ("hr", "lr"):
        em, rad = clip.read(3, f"{lvl}/emission"), clip.read(3, f"{lvl}/radiance")
        bg = (clip.read(3, f"{lvl}/flags")[..., 0] & int(Flag.BACKGROUND)) != 0
        assert np.allclose(em[bg], [0.6, 0.7, 1.0], rtol=1e-4), lvl
        assert np.all(em[~bg] == 0.0), lvl  # nothing in the basic scene emits
        if lvl == "lr":  # point-sampled: radiance is exactly the sky there
            assert np.abs(rad[bg] - em[bg]).max() < 1e-4
    from gbuffer_export.validate import validate_clip
    assert not [f for f in validate_clip(basic_clip).findings if f.code == "emission-background"]


def test_white_furnace(furnace_clips):
    """Objects invisible to secondary rays under a uniform white world: radiance / fbeta = 1."""
    out = furnace_clips["furnace"]
    clip = open_clip(out)
    for lvl in ("hr", "lr"):
        rad, em, fb = (clip.read(1, f"{lvl}/{b}") for b in ("radiance", "emission", "fbeta"))
        surf = (clip.read(1, f"{lvl}/flags")[..., 0] & int(Flag.BACKGROUND)) == 0
        ratio = (rad - em) / np.maximum(fb, 0.01)
        med = np.median(ratio[surf])
        assert abs(med - 1) < 0.01, (lvl, med)


def test_hr_fbeta_follows_the_ground_truth_filter_on_subpixel_texture(furnace_clips):
    """A checker finer than the pixel in a white furnace: the HR ground truth (Blackman-Harris) averages it, so the
    HR F_beta must be the same footprint average (radiance / fbeta = 1 with no texture left), not the aliased value
    at the pixel centre; the point-sampled LR keeps radiance and F_beta point-sampled alike."""
    out = furnace_clips["footprint"]
    clip = open_clip(out)
    for lvl in ("hr", "lr"):
        rad, em, fb = (clip.read(1, f"{lvl}/{b}")[2:-2, 2:-2, :3] for b in ("radiance", "emission", "fbeta"))
        ratio = ((rad - em) / np.maximum(fb, 0.01))[..., 0]  # red: the channel the checker varies most
        lo, med, hi = np.percentile(ratio, [10, 50, 90])
        assert abs(med - 1) < 0.03 and hi - lo < 0.1, (lvl, lo, med, hi)  # point-sampled HR F_beta: 0.8 .. 1.3
    assert clip.manifest["render"]["gbuffer"]["hr_fbeta"] == "footprint"
    # --hr-fbeta point: the HR F_beta as before (aliased), and the manifest as before (no key)
    old = open_clip(furnace_clips["point"])
    assert "hr_fbeta" not in old.manifest["render"]["gbuffer"]
    np.testing.assert_array_equal(old.read(1, "hr/radiance"), clip.read(1, "hr/radiance"))
    rad, em, fb = (old.read(1, f"hr/{b}")[2:-2, 2:-2, :3] for b in ("radiance", "emission", "fbeta"))
    lo, hi = np.percentile(((rad - em) / np.maximum(fb, 0.01))[..., 0], [10, 90])
    assert hi - lo > 0.3, (lo, hi)


def _one_line_exit_2(proc, needle):
    assert proc.returncode == 2, proc.stderr[-2000:]
    last = [ln for ln in proc.stderr.splitlines() if ln.startswith("blendsr: error:")]
    assert len(last) == 1 and needle in last[0], proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("case,args,needle", [
    ("missing", ["render", "/nonexistent/x.blend"], "not found"),
    ("notblend", ["render", "{txt}"], "not a .blend"),
    ("badsize", ["render", "{basic}", "--hr-size", "65x36"], "not divisible"),
    ("buffer", ["render", "{basic}", "--buffers", "radiance,velocity"], "unknown buffer"),
])
def test_bad_input_one_line_exit_2(case, args, needle, basic_blend, tmp_path):
    """Refusals before the scene loads, each a process of its own (``python -m gbuffer_export.cli``'s exit status);
    those that need the scene loaded are in ``test_bad_scenes_one_line_exit_2``."""
    files = {"basic": basic_blend, "txt": tmp_path / "scene.blend"}
    (tmp_path / "scene.blend").write_text("hello")
    args = [a.format(**{k: str(v) for k, v in files.items()}) for a in args]
    _one_line_exit_2(run_cli(*args, "-o", tmp_path / "out", *FAST), needle)


#: refusals once the scene is loaded: case -> (the scene fixture of tests/scenes.py, extra arguments, the words)
SCENE_REFUSALS = {
    "frames": ("basic", ["--frames", "5:40"], "outside the scene"),
    "nocam": ("nocamera", [], "no camera"),
    "empty": ("empty", [], "no geometry to render"),  # "empty" matched the file's name, not the reason
    "ortho": ("ortho", [], "orthographic"),
}


def test_bad_scenes_one_line_exit_2(blends, basic_clip, tmp_path):
    """Each refusal of ``SCENE_REFUSALS`` is one line and exit 2, and an output folder holding another clip (the
    module's, 128x72) is refused without touching it: the commands in one process (``cli_batch``), each opening
    its own scene."""
    basic_blend = blends["basic"]
    cases = list(SCENE_REFUSALS.items())
    argvs = [["render", blends[kind], *extra, "-o", tmp_path / f"out_{case}", *FAST]
             for case, (kind, extra, _) in cases]
    argvs.append(["render", basic_blend, "-o", basic_clip, "--frames", "2:4", "--hr-size", "64x36", *FAST])
    procs = run_cli_batch(*argvs)
    for (case, (kind, _, needle)), proc in zip(cases, procs):
        _one_line_exit_2(proc, needle)
        assert not (tmp_path / f"out_{case}" / "manifest.json").exists(), case
    other = procs[-1]
    assert other.returncode == 2 and "different clip" in other.stderr, other.stderr[-2000:]
    assert json.loads((basic_clip / "manifest.json").read_text())["levels"]["hr"]["width"] == 128
