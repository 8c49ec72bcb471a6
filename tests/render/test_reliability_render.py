"""Reliability of rendering: absurd sizes are refused up front; the same command gives bit-identical EXRs; one
writer per clip; Ctrl-C stops a render."""
import json
import os
import signal
import subprocess
import sys
import time

import pytest
from tests.conftest import ENV, REPO, assert_same_render, requires_bpy, run_cli

from gbuffer_export.conventions import DEFAULT_BUFFERS
from gbuffer_export.resources import ResourceError, check_render_resources, estimate_render


def test_estimate_grows_with_size_frames_and_buffers():
    a = estimate_render((640, 360), 4, DEFAULT_BUFFERS, 10)
    assert estimate_render((1280, 720), 4, DEFAULT_BUFFERS, 10).memory_bytes > a.memory_bytes
    assert estimate_render((640, 360), 4, DEFAULT_BUFFERS, 20).disk_bytes > a.disk_bytes
    assert estimate_render((640, 360), 4, ("radiance",), 10).disk_bytes < a.disk_bytes
    # 640x360 with the default buffers (19 channels): 10 frames of (230400 + 14400) px * 21 * 4 B + one temp EXR
    assert a.disk_bytes == 10 * (230400 + 14400) * 19 * 4 + 230400 * 40 * 4


def test_resources_refused_with_needed_and_available(tmp_path):
    with pytest.raises(ResourceError, match=r"needs about .* of memory and 1 GB is available"):
        check_render_resources((4000, 4000), 4, DEFAULT_BUFFERS, 1, tmp_path, available=(10**9, 10**12))
    with pytest.raises(ResourceError, match=r"100 frame\(s\) .* need up to .* of disk and 1 MB is free"):
        check_render_resources((640, 360), 4, DEFAULT_BUFFERS, 100, tmp_path, available=(10**11, 10**6))
    est = check_render_resources((64, 36), 4, DEFAULT_BUFFERS, 4, tmp_path / "new" / "clip")  # this machine
    assert est.frames == 4 and est.memory_bytes < 2**31


@requires_bpy
def test_absurd_render_size_is_refused_in_one_line_before_rendering(tmp_path):
    out = tmp_path / "o"
    proc = run_cli("render", "-o", out, "--hr-size", "100000x100000", "--frames", "1:1", "--no-progress",
                   timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "of memory" in lines[0] and "is available" in lines[0], lines
    assert not out.exists()


def _buffers(clip):
    from gbuffer_export import open_clip
    c = open_clip(clip)
    return {(f, f"{lvl}/{b}"): c.read(f, f"{lvl}/{b}") for f in c.frames for lvl in ("hr", "lr")
            for b in c.manifest["buffers"]}


@requires_bpy
def test_the_same_render_command_gives_the_same_clip(tmp_path):
    """Same command twice: G-buffers equal to float rounding, radiance the same image in expectation (bit-identical
    on an idle machine with --threads 1, which the CPU contention of a parallel test run can break)."""
    args = ["--hr-size", "64x36", "--frames", "1:2", "--hr-spp", "4", "--lr-spp", "2", "--seed", "3", "--no-progress",
            "--threads", "1"]
    out = tmp_path / "clip"  # the same command: the same output path (its length shapes the heap too)
    run_cli("render", "-o", out, *args, timeout=300, check=True)
    out.rename(tmp_path / "first")
    run_cli("render", "-o", out, *args, timeout=300, check=True)
    a, b = _buffers(tmp_path / "first"), _buffers(out)
    assert len(a) >= 2 * 2 * 8
    assert_same_render(a, b)


def test_fbeta_unmodeled_flag_per_source():
    from gbuffer_export.conventions import UNTRUSTED, Flag, material_flags_for_source
    coat = int(Flag.COAT | Flag.EMISSIVE)
    assert material_flags_for_source(coat, "cycles") == coat  # Cycles' colour passes carry the coat
    for src in ("lut", "lut-paper", "model"):
        f = material_flags_for_source(coat, src)
        assert f & int(Flag.FBETA_UNMODELED) and f & int(UNTRUSTED)
        assert material_flags_for_source(int(Flag.MOVING), src) == int(Flag.MOVING)


def _furnace_clips(tmp_path, sources):
    """The furnace of coat, sheen and glass rendered once per F_beta source of ``sources`` (one process:
    ``cli_batch``); returns source -> clip."""
    import subprocess
    import sys

    from tests.conftest import ENV, REPO
    from tests.render.cli_batch import run_cli_batch
    blend, layout = tmp_path / "f.blend", tmp_path / "layout.json"
    subprocess.run([sys.executable, "-m", "gbuffer_export.blender.furnace", str(blend), str(layout), "--size",
                    "256", "64", "--columns", "4", "--materials",
                    "diel_grey_r0.50,coat_orange_r0.50,sheen_grey_r0.50,glass_r0.30"], check=True, cwd=REPO,
                   capture_output=True, timeout=300, env=ENV)
    clips = {src: tmp_path / f"clip_{src}" for src in sources}
    procs = run_cli_batch(*[["render", blend, "-o", clip, "--frames", "1:1", "--hr-size", "256x64", "--hr-spp", "1",
                             "--lr-spp", "256", "--buffers", "all", "--jitter", "none", "--no-progress", "--fbeta",
                             src] for src, clip in clips.items()], timeout=600)
    for proc in procs:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return clips


@requires_bpy
@pytest.mark.bpy
def test_unflagged_pixels_match_the_furnace_for_every_fbeta_source(tmp_path):
    """White furnace with coat, sheen and glass: every surface pixel that no UNTRUSTED bit marks has fbeta within 5%
    of the furnace radiance, for the model source (which cannot represent the layers) and for Cycles' passes."""
    import numpy as np

    from gbuffer_export import open_clip
    from gbuffer_export.conventions import UNTRUSTED, Flag
    within = {}
    for src, clip in _furnace_clips(tmp_path, ("model", "cycles")).items():
        c = open_clip(clip)
        flags = c.read(1, "lr/flags")[..., 0]
        truth = c.read(1, "lr/radiance") - c.read(1, "lr/emission")
        fb = c.read(1, "lr/fbeta")
        surface = (flags & int(Flag.BACKGROUND)) == 0
        trusted = surface & ((flags & int(UNTRUSTED)) == 0)
        layered = surface & ((flags & int(Flag.COAT | Flag.SHEEN | Flag.TRANSMISSION)) != 0)
        assert layered.sum() > 50 and trusted.sum() > 20
        rel = np.abs(fb - truth).max(axis=-1) / np.maximum(truth.max(axis=-1), 0.05)
        within[src] = float((rel[trusted] <= 0.05).mean())
        if src == "model":
            assert not (trusted & layered).any()  # coat, sheen, glass: untrusted under the model
        else:
            assert (trusted & layered).sum() == layered.sum()  # Cycles' passes carry them
    assert within["model"] >= 0.95 and within["cycles"] >= 0.95, within


TINY = ["--hr-size", "64x36", "--hr-spp", "2", "--lr-spp", "1", "--threads", "1", "--no-progress"]


def _render(out, *args):
    return subprocess.Popen([sys.executable, "-m", "gbuffer_export.cli", "render", "-o", str(out), *TINY, *args],
                            cwd=REPO, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


@requires_bpy
@pytest.mark.bpy
@pytest.mark.heavy
def test_two_renders_into_one_new_folder_never_make_a_mixed_clip(tmp_path):
    """Issue 26: two renders with other settings started together into one new folder. One writes the clip, the
    other is refused in one line naming the folder (exit 2); the clip validates and holds only the winner's frames.
    A race of two Cycles processes (make test-heavy); the writer's refusal itself is in the fast suite:
    tests/core/test_reliability_clip.py (a writer with other settings, a second writer of a clip)."""
    from gbuffer_export.validate import validate_clip
    out = tmp_path / "c"
    procs = [_render(out, "--frames", "1:4", "--seed", str(seed)) for seed in (0, 5)]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    codes = sorted(rc for rc, _ in results)
    assert codes == [0, 2], results
    err = next(e for rc, e in results if rc == 2)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("blendsr: error: ") and str(out) in lines[0], lines
    assert "Traceback" not in err
    winner = (0, 5)[[rc for rc, _ in results].index(0)]
    m = json.loads((out / "manifest.json").read_text())
    assert m["render"]["seed"] == winner and sorted(map(int, m["frame_data"])) == [1, 2, 3, 4]
    rep = validate_clip(out, quick=True)
    assert rep.ok, rep.summary_line()


@requires_bpy
@pytest.mark.bpy
@pytest.mark.heavy
def test_ctrl_c_stops_a_render_keeping_finished_frames(tmp_path):
    """SIGINT (Ctrl-C) during a render: it stops after the Cycles pass in flight with the resume line and exit 130;
    finished frames stay, the partial frame leaves no file and no temporary folder remains. Its cost is the timing
    of a signal into a running Cycles process (make test-heavy); Ctrl-C's one line and exit 130 are in the fast
    suite: tests/cli/test_early_interrupt.py."""
    from gbuffer_export.validate import validate_clip
    out = tmp_path / "c"
    proc = _render(out, "--frames", "1:40")
    deadline = time.time() + 240
    while not list((out / "frames").glob("*.json")) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, proc.stderr.read()[-2000:]
    os.killpg(proc.pid, signal.SIGINT)  # what the terminal does on Ctrl-C: the whole process group
    t0 = time.time()
    try:
        rc = proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        raise
    err = proc.stderr.read()
    assert rc == 130, err[-2000:]
    assert time.time() - t0 < 30 and "Traceback" not in err and "KeyboardInterrupt" not in err
    assert err.strip().splitlines()[-1] == "blendsr: interrupted; rerun the same command to resume"
    done = sorted(int(p.stem) for p in (out / "frames").glob("*.json"))
    assert 1 <= len(done) < 40
    assert not list(out.glob(".render-*"))
    rep = validate_clip(out, quick=True)
    codes = {f.code for f in rep.findings}
    assert codes == {"missing-frame"}, [f.line() for f in rep.findings if f.code != "missing-frame"]
