"""The add-on's bpy-free parts: finding the library, the export summary, the worker's config round trip and the
render job (progress from the clip's frame records, cancel kills the worker, a rerun resumes)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from blender_addon import estimate, jobs, library, worker
from tests.conftest import REPO, make_blend, requires_bpy
from gbuffer_export.config import RenderConfig
from gbuffer_export.conventions import BUFFERS


def test_site_dirs_for(tmp_path):
    venv = tmp_path / "venv"
    sp = venv / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    sp.mkdir(parents=True)
    (venv / "pyvenv.cfg").write_text("home = /usr/bin\n")
    assert library.site_dirs_for(venv) == [sp.resolve()]
    assert library.site_dirs_for(sp) == [sp.resolve()]
    checkout = tmp_path / "checkout"
    (checkout / "gbuffer_export").mkdir(parents=True)
    assert library.site_dirs_for(checkout) == [checkout.resolve()]
    assert library.site_dirs_for(tmp_path / "missing") == []


def test_status_without_library_then_from_preferences_path(tmp_path):
    """In an isolated Python (no site-packages) the library is missing and the hint says how to install it;
    the venv root given as 'Library path' makes it importable (its .pth files, e.g. an editable install, work)."""
    (tmp_path / "blender_addon").symlink_to(REPO / "blender_addon")
    venv = Path(sys.prefix)
    code = f"""
import json, sys
sys.path.insert(0, {str(tmp_path)!r})
from blender_addon import library
a = library.status()
b = library.status({str(venv)!r})
import gbuffer_export
print(json.dumps({{"a": [a.ok, a.message, list(a.hint)], "b": [b.ok, b.root, b.torch, b.training],
                  "gbe": gbuffer_export.__file__, "added": library.ADDED_SITE_DIRS,
                  "paths": library.worker_paths(b)}}))
"""
    proc = subprocess.run([sys.executable, "-I", "-S", "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    ok, msg, hint = r["a"]
    assert not ok and "not importable" in msg
    assert any("pip install blendsr" in h for h in hint) and any("Library path" in h for h in hint)
    assert r["b"][0] and Path(r["b"][1]) == REPO and r["b"][3]
    assert Path(r["gbe"]).resolve() == (REPO / "gbuffer_export" / "__init__.py")
    assert r["paths"]["sys_path"] == [str(REPO)] and r["paths"]["site_dirs"] == r["added"] and r["added"]


def test_estimate_counts_size_and_cost_model(tmp_path):
    cfg = RenderConfig(output=tmp_path / "c", frames=(3, 12), hr_size=(640, 360), buffers="radiance,depth,motion")
    est = estimate.estimate_export(cfg)
    assert (est.frames, est.buffers, est.levels, est.files) == (10, 3, 2, 60)
    chans = 3 + 1 + 2
    assert est.megabytes == pytest.approx(chans * 4 * (640 * 360 + 160 * 90) * 10 / 1e6)
    e = estimate
    per = (2 * e.RENDER_OVERHEAD_S + e.K_PATH_S * (640 * 360 * 64 + 160 * 90 * 4) + e.GBUFFER_OVERHEAD_S
           + e.K_GBUFFER_S * 640 * 360 * cfg.gbuffer_spp + e.K_WRITE_S * (640 * 360 + 160 * 90) * chans
           + e.FRAME_OVERHEAD_S)
    assert est.seconds_per_frame == pytest.approx(per)
    assert est.seconds == pytest.approx(e.STARTUP_S + 10 * per)
    # radiance only: no G-buffer pass
    rad = estimate.estimate_export(RenderConfig(output=tmp_path / "c", frames=(1, 1), hr_size=(640, 360),
                                                buffers="radiance"))
    no_gbuffer = e.GBUFFER_OVERHEAD_S + e.K_GBUFFER_S * 640 * 360 * cfg.gbuffer_spp
    assert rad.seconds_per_frame == pytest.approx(per - no_gbuffer - e.K_WRITE_S * (640 * 360 + 160 * 90) * 3)
    # finished frames in the folder shorten what is left
    (tmp_path / "c" / "frames").mkdir(parents=True)
    for f in (2, 3, 4):  # frame 2 is outside the range
        (tmp_path / "c" / "frames" / f"{f:06d}.json").write_text("{}")
    done = estimate.frames_done_in(cfg.output, cfg.frames)
    assert done == 2
    est2 = estimate.estimate_export(cfg, done)
    assert est2.seconds_left == pytest.approx(e.STARTUP_S + 8 * per)
    assert estimate.channels_of(("normal", "flags")) == {"normal": len(BUFFERS["normal"].channels), "flags": 1}


def test_worker_config_round_trip(tmp_path):
    cfg = RenderConfig(output=tmp_path / "o", frames=(2, 5), hr_size=(64, 32), shard=(2, 3), buffers="depth",
                       camera_path="orbit", max_bounces=2)
    back = RenderConfig(**worker.config_kwargs(json.loads(json.dumps(cfg.to_json()))))
    assert back == cfg
    one = RenderConfig(output=tmp_path / "o", frames=(2, 5), only_frames=(4,))  # the preview's frame
    back = RenderConfig(**worker.config_kwargs(json.loads(json.dumps(one.to_json()))))
    assert back == one and back.only_frames == (4,)


@requires_bpy
@pytest.mark.bpy
def test_job_progress_cancel_resume_and_errors(tmp_path, blend_dir):
    blend = make_blend("basic", blend_dir / "addon_basic.blend")
    out = tmp_path / "clip"
    cfg = RenderConfig(output=out, scene=blend, frames=(1, 3), hr_size=(64, 36), hr_spp=256, lr_spp=2,
                       gbuffer_spp=1, progress=False)
    paths = {"site_dirs": [], "sys_path": [str(REPO)]}
    job = jobs.RenderJob(cfg.to_json(), [1, 2, 3], job_dir=tmp_path / "j1", library_paths=paths)
    assert job.command[:2] == [sys.executable, str(jobs.WORKER)]
    t0 = time.monotonic()
    while job.frames_done() < 1:
        assert job.poll() is None, job.log_file.read_text()[-2000:]
        assert time.monotonic() - t0 < 180
        time.sleep(0.05)
    done, total, left = job.progress()
    assert total == 3 and done >= 1 and left is not None and left > 0
    assert "frames" in job.status_line()
    job.cancel()
    res = job.result()
    assert not res.ok and "cancelled" in res.error
    with pytest.raises(ProcessLookupError):
        os.kill(job.proc.pid, 0)
    done_after_cancel = job.frames_done()
    assert 1 <= done_after_cancel < 3, "cancel came too late to test (the worker had finished)"

    job2 = jobs.RenderJob(cfg.to_json(), [1, 2, 3], job_dir=tmp_path / "j2", library_paths=paths, validate="quick")
    assert job2.done_at_start == done_after_cancel
    res2 = job2.result()
    assert res2.ok and res2.valid, (res2.error, res2.log[-2000:])
    assert "resuming" in res2.log and job2.frames_done() == 3
    assert res2.output == str(out) and "OK" in res2.validation

    # a worker error comes back as a one-line message
    nocam = make_blend("nocamera", blend_dir / "addon_nocamera.blend")
    bad = RenderConfig(output=tmp_path / "bad", scene=nocam, frames=(1, 1), hr_size=(64, 36), progress=False)
    res3 = jobs.RenderJob(bad.to_json(), [1], job_dir=tmp_path / "j3", library_paths=paths).result()
    assert not res3.ok and res3.returncode == 2 and "no camera" in res3.error


def test_worker_command_in_the_blender_application(tmp_path):
    cmd = jobs.worker_command(tmp_path / "job.json", blender_binary="/opt/blender/blender")
    assert cmd[:2] == ["/opt/blender/blender", "--background"]
    assert cmd[cmd.index("--python") + 1] == str(jobs.WORKER) and cmd[-2:] == ["--", str(tmp_path / "job.json")]


def test_format_seconds():
    assert jobs.format_seconds(42) == "42 s"
    assert jobs.format_seconds(600) == "10.0 min"
    assert jobs.format_seconds(7200) == "2.0 h"


def test_below_baseline_marks_follow_the_weights_json(tmp_path, monkeypatch):
    """A shipped network below demod-jbu on its val split is marked, from the JSON beside its weights (json only, no
    torch), in the add-on's model menu and in the README's shipped-networks sentence."""
    code = ("import sys; from training import pretrained as p; "
            "print([p.below_baseline(n) for n in p.PRETRAINED], 'torch' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("False"), proc.stderr  # no torch imported
    from training import pretrained
    readme = (REPO / "README.md").read_text()
    for name in pretrained.PRETRAINED:  # the README marks exactly the networks the JSON puts below demod-jbu
        marked = f"`pretrained:{name}` (below `demod-jbu` on val" in readme
        assert marked is pretrained.below_baseline(name), name
        if marked:
            assert f"{pretrained.val_margin(name):+.2f} dB)" in readme
    # the rule on made-up scores: below by 0.2 dB -> marked; above, or no val scores -> not
    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", tmp_path)
    for name, scores, below in (("fusesr", {"fusesr": {"psnr": 30.0}, "demod-jbu": {"psnr": 30.2}}, True),
                                ("nsrd", {"nsrd": {"psnr": 30.3}, "demod-jbu": {"psnr": 30.2}}, False),
                                ("rdg-s", None, False)):
        doc = {"model": name} if scores is None else {"model": name, "scores_on_val_split": scores}
        (tmp_path / pretrained.PRETRAINED[name]).with_suffix(".json").write_text(json.dumps(doc))
        assert pretrained.below_baseline(name) is below, name
        assert pretrained.below_baseline_note(name) == ("below demod-jbu on val" if below else "")
    assert pretrained.val_margin("fusesr") == pytest.approx(-0.2)
    # the menu's label: "NSRD (pretrained, below demod-jbu on val)"
    from blender_addon.library import marked_items
    items = marked_items((("pretrained:nsrd", "NSRD (pretrained)", "d"), ("bicubic", "Bicubic", "b")),
                         {"pretrained:nsrd": "below demod-jbu on val"})
    assert [i[:2] for i in items] == [("pretrained:nsrd", "NSRD (pretrained, below demod-jbu on val)"),
                                      ("bicubic", "Bicubic")] and [i[3] for i in items] == [0, 1]


def test_dataset_run_options_round_trip_through_the_worker_job_file():
    """``mapping.run_options_json`` -> JSON -> ``RunOptions(**...)`` (worker.run_dataset's reading) is the same
    options: the lists the JSON holds become the tuples they stand for (``RunOptions.__post_init__``)."""
    from blender_addon import mapping
    from gbuffer_export.dataset.build import RunOptions
    opts = RunOptions(workers=2, threads=1, buffers_for=("fusesr", "nsrr"), clips=("a*", "b"), splits=("test",),
                      progress=False, order="mixed")
    back = RunOptions(**json.loads(json.dumps(mapping.run_options_json(opts))))
    assert back == opts and isinstance(back.clips, tuple) and isinstance(back.buffers_for, tuple)
