"""``blendsr render --scales``: one LR render per level (Cycles in a subprocess), every level validated."""
from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import requires_bpy, run_cli
from tests.render.cli_batch import make_blends, run_cli_batch
from gbuffer_export import open_clip
from gbuffer_export.conventions import Flag
from gbuffer_export.validate import validate_clip

REPO = Path(__file__).resolve().parents[2]


def _revision() -> str | None:
    """This checkout's commit by git itself (``rev-parse HEAD``, ``-dirty`` when ``status`` lists a tracked file);
    None where there is no git or no checkout."""
    def git(*args):
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, timeout=60)
    try:
        head, status = git("rev-parse", "HEAD"), git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    if head.returncode or status.returncode:
        return None
    return head.stdout.strip() + ("-dirty" if status.stdout.strip() else "")


pytestmark = [pytest.mark.bpy, requires_bpy]
FAST = ["--hr-spp", "4", "--lr-spp", "2", "--gbuffer-spp", "1", "--no-progress"]
LEVELS = {"hr": (80, 40), "lr": (40, 20), "lr_x2.5": (32, 16), "lr_x4": (20, 10)}


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    """The basic scene (frames 2:3) and the furnace (frame 1, 32 spp, no jitter) at 80x40 with --scales 2,2.5,4:
    scenes built in one process, clips rendered in another (``cli_batch``)."""
    d = tmp_path_factory.mktemp("scales")
    blends = make_blends(["basic", "furnace"], d)
    procs = run_cli_batch(
        ["render", blends["basic"], "-o", d / "basic", "--frames", "2:3", "--hr-size", "80x40", "--scales", "2,2.5,4",
         *FAST],
        ["render", blends["furnace"], "-o", d / "furnace", "--frames", "1:1", "--hr-size", "80x40", "--scales",
         "2,2.5,4", "--hr-spp", "32", "--lr-spp", "32", "--jitter", "none", "--buffers",
         "radiance,emission,fbeta,flags", "--no-progress"])
    for proc in procs:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return {"basic": d / "basic", "furnace": d / "furnace"}


def test_scales_render_validates_at_every_level(clips):
    """--scales 2,2.5,4 at 80x40: one clip with four levels, each with its own size, intrinsics, jitter, seed and
    timings; motion agrees with reprojection at every level."""
    out = clips["basic"]
    clip = open_clip(out)
    assert clip.complete and clip.scales == [2.0, 2.5, 4.0] and clip.scale == 2 and clip.sizes == LEVELS
    for f in clip.frames:
        rec = clip.record(f)
        seeds = {rec[lvl]["seed"] for lvl in LEVELS}
        assert len(seeds) == 4  # hr ground truth and three LR renders, each its own Cycles seed
        # the frame's cost: wall seconds and the render process's CPU seconds (Cycles renders in it), both spent
        assert rec["seconds_total"] > 0 and rec["cpu_seconds_total"] > 0
        # the code that rendered it: this checkout's commit (None outside a git checkout); the dirty mark is
        # tests/core/test_provenance.py's (here another test may write a tracked file while this one renders)
        want = _revision()
        assert (rec["commit"] and rec["commit"].removesuffix("-dirty")) == (want and want.removesuffix("-dirty"))
        for lvl, (w, h) in LEVELS.items():
            assert clip.read(f, f"{lvl}/radiance").shape == (h, w, 3)
            assert rec[lvl]["seconds"]["radiance"] > 0
            if lvl != "hr":
                s = clip.level_scale[lvl]
                assert np.allclose(clip.camera(f, lvl)["intrinsics"], clip.camera(f, "hr")["intrinsics"] / s)
                assert rec[lvl]["jitter"] == rec["lr"]["jitter"]  # Halton position of the frame, level pixels
    assert clip.record(3)["lr"]["jitter"] != [0.0, 0.0]
    r = validate_clip(out)
    assert r.ok, [f.line() for f in r.findings]
    for lvl in LEVELS:
        m = r.stats["levels"][lvl]["motion"]
        assert m["static_pixels"] > 0 and m["static_fraction_min"] >= 0.99, (lvl, m)
        assert m["background_pixels"] > 0 and m["background_fraction_min"] >= 0.99, (lvl, m)
    # a level's view reads like a single-scale clip
    v = clip.at_scale(2.5)
    assert v.sizes == {"hr": (80, 40), "lr": (32, 16)} and v.scale == 2.5
    assert np.array_equal(v.read(2, "lr/depth"), clip.read(2, "lr_x2.5/depth"))


def test_white_furnace_at_every_level(clips):
    """Objects invisible to secondary rays under a uniform white world: radiance / fbeta = 1 at every level."""
    clip = open_clip(clips["furnace"])
    for lvl in LEVELS:
        rad, em, fb = (clip.read(1, f"{lvl}/{b}") for b in ("radiance", "emission", "fbeta"))
        surf = (clip.read(1, f"{lvl}/flags")[..., 0] & int(Flag.BACKGROUND)) == 0
        assert surf.sum() > 20, lvl
        med = np.median(((rad - em) / np.maximum(fb, 0.01))[surf])
        assert abs(med - 1) < 0.02, (lvl, med)


@pytest.mark.parametrize("args,needle", [
    (["--hr-size", "64x36", "--scales", "2,2.5,4"], "--hr-size 64x36 is not divisible by scale 2.5"),
    (["--hr-size", "64x36", "--scales", "2,2.5,4"], "nearest sizes that every scale divides: 60x20 or 80x40"),
    (["--hr-size", "80x40", "--scales", "2,0.5"], "--scales 0.5: must be a number >= 1"),
    (["--hr-size", "80x40", "--scales", "2,x"], "--scales '2,x': expected comma-separated numbers"),
    (["--hr-size", "80x40", "--scales", "2,4,2"], "a scale is given twice"),
])
def test_bad_scales_one_line_exit_2(args, needle, tmp_path):
    proc = run_cli("render", "-o", tmp_path / "out", *args, *FAST)
    assert proc.returncode == 2, proc.stderr[-2000:]
    last = [ln for ln in proc.stderr.splitlines() if ln.startswith("blendsr: error:")]
    assert len(last) == 1 and needle in last[0], proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and not (tmp_path / "out").exists()
