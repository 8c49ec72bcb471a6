"""Issue 43 (Reliability 3) items for training: a run resumes from its own config.toml, a model change names
model.name, loader workers die with their trainer and RUN/.lock is free within a second of kill -9, a malformed
manifest is one line, train and evaluate refuse what validate refuses (negative or non-finite radiance, a split leak)
in validate's words, and a full cache filesystem names the file."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from tests.conftest import ENV, REPO, set_args  # noqa: E402
from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402

pytestmark = pytest.mark.torch

SMALL = ["data.batch_size=2", "model.fusesr.width=8", "model.fusesr.blocks=1", "run.progress=false",
         "run.amp=\"none\"", "run.threads=1"]


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)


def one_line(capsys) -> str:
    """The one error line a refused command printed (notes aside; no traceback)."""
    err = [ln for ln in capsys.readouterr().err.strip().splitlines() if not ln.startswith("note: ")]
    assert len(err) == 1, err
    return err[0]


def fresh_copy(clip, dest):
    shutil.copytree(clip, dest, ignore=shutil.ignore_patterns(".blendsr_cache"))
    return dest


# ------------------------------------------------------------------------------------ resume and lock (item 5)
def test_a_run_resumes_from_its_own_config_toml(clip, tmp_path, capsys):
    """The default crop 64 shrinks to 9 on LR 16x9: config.toml holds the user's 64 (the checkpoint's
    user_config) and says 9 in a comment, so resuming with it is the same run."""
    from training.checkpoint import load_checkpoint
    from training.config import load_config
    run = tmp_path / "run"
    assert main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(run), "--max-steps", "1",
                 *set_args(SMALL)]) == 0
    text = (run / "config.toml").read_text()
    assert "#   data.crop = 9 " in text
    assert load_config(run / "config.toml").to_dict() == load_checkpoint(run / "checkpoints" / "last.pt")["user_config"]
    assert main(["train", "-o", str(run), "--resume", "--config", str(run / "config.toml"), "--max-steps", "2"]) == 0
    assert load_checkpoint(run / "checkpoints" / "last.pt")["step"] == 2
    # a config.toml of the effective configuration (as written before) names the derived value: the same run too
    from training.config import config_from_checkpoint
    old = tmp_path / "effective.toml"
    old.write_text(config_from_checkpoint(load_checkpoint(run / "checkpoints" / "last.pt")["config"]).to_toml())
    assert "crop = 9" in old.read_text()
    assert main(["train", "-o", str(run), "--resume", "--config", str(old), "--max-steps", "3"]) == 0
    capsys.readouterr()
    # a real change is still named
    assert main(["train", "-o", str(run), "--resume", "--config", str(old), "--max-steps", "4",
                 "--set", "data.crop=8"]) == 2
    assert "data.crop = 8 differs from the checkpoint's 64" in one_line(capsys)


def test_a_model_change_on_resume_names_model_name(clip, tmp_path, capsys):
    run = tmp_path / "run"
    argv = ["train", "--data", str(clip), "-o", str(run), *set_args(SMALL)]
    assert main(argv + ["--model", "fusesr", "--max-steps", "1"]) == 0
    capsys.readouterr()
    assert main(argv + ["--model", "fusesr-l", "--max-steps", "2", "--resume"]) == 2
    line = one_line(capsys)
    assert "this run is fusesr, not fusesr-l (model.name differs" in line and "blocks" not in line, line


def test_killed_trainer_takes_its_loader_workers_and_frees_the_lock_within_a_second(clip, tmp_path):
    import psutil
    from gbuffer_export.locks import FolderBusyError, FolderLock
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "gbuffer_export.cli", "train", "--model", "fusesr", "--data",
                             str(clip), "-o", str(run), "--max-steps", "1000000", "--set", "data.crop=8",
                             *set_args(SMALL + ["data.workers=2", "run.log_every=1"])],
                            cwd=REPO, env=ENV, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        t0 = time.monotonic()
        while not ((run / "log.csv").is_file() and len((run / "log.csv").read_text().splitlines()) > 2):
            assert proc.poll() is None and time.monotonic() - t0 < 120, "training did not start"
            time.sleep(0.05)
        workers = psutil.Process(proc.pid).children(recursive=True)
        assert len(workers) >= 2, workers
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        killed = time.monotonic()
        while True:
            try:
                FolderLock(run, "busy").close()
                break
            except FolderBusyError:
                assert time.monotonic() - killed < 1.0, "RUN/.lock still held a second after kill -9"
                time.sleep(0.01)
        def running(p):  # a zombie has ended (whoever adopted it reaps it later)
            try:
                return p.status() != psutil.STATUS_ZOMBIE
            except psutil.NoSuchProcess:
                return False
        while any(running(p) for p in workers):
            assert time.monotonic() - killed < 1.0, "loader workers outlived their trainer by a second"
            time.sleep(0.01)
    finally:
        with __import__("contextlib").suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def test_die_with_parent_watch_thread_ends_an_orphan(tmp_path):
    """The fallback where prctl is not available (macOS, Windows): a watch thread exits the orphan."""
    code = ("import os, sys, time\n"
            "from gbuffer_export import locks\n"
            "parent = os.getpid()\n"
            "pid = os.fork()\n"
            "if pid == 0:\n"
            "    sys.platform = 'darwin'  # take the portable path\n"
            "    assert locks.die_with_parent(parent) == 'watch'\n"
            "    print(os.getpid(), flush=True)\n"
            "    time.sleep(30)\n"
            "    os._exit(0)\n"
            "time.sleep(0.5)\n"
            "os._exit(0)\n")
    import psutil
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=ENV, capture_output=True, text=True, timeout=60)
    child = int(proc.stdout.split()[0])
    t0 = time.monotonic()
    while psutil.pid_exists(child) and psutil.Process(child).status() != psutil.STATUS_ZOMBIE:
        assert time.monotonic() - t0 < 2.0, "the orphan kept running"
        time.sleep(0.05)


# ------------------------------------------------------------------------------------ bad input (item 4)
def test_a_frame_data_key_that_is_not_a_number_is_one_line_naming_the_manifest(clip, tmp_path, capsys):
    bad = fresh_copy(clip, tmp_path / "bad")
    m = json.loads((bad / "manifest.json").read_text())
    m["frame_data"]["x1"] = m["frame_data"]["1"]
    (bad / "manifest.json").write_text(json.dumps(m))
    assert main(["train", "--model", "fusesr", "--data", str(bad), "-o", str(tmp_path / "run"), "--max-steps", "1",
                 *set_args(SMALL)]) == 2
    assert one_line(capsys) == (f"blendsr: error: {bad / 'manifest.json'}: frame_data key 'x1' is not a frame "
                                "number with a record (an object)")


# ------------------------------------------------------------------------------------ what validate refuses (item 6)
def _negative(clip, dest):
    from gbuffer_export.clip import open_clip
    from gbuffer_export.exr import write_exr
    bad = fresh_copy(clip, dest)
    c = open_clip(bad)
    a = c.read(2, "lr/radiance")
    a[:, :8] = -0.5
    write_exr(c.path_of(2, "lr/radiance"), {ch: a[..., i] for i, ch in enumerate("RGB")})
    return bad, c.path_of(2, "lr/radiance")


def _validate_line(clip, code: str) -> str:
    from gbuffer_export.validate import validate_clip
    rep = validate_clip(clip, progress=False)
    found = [f for f in rep.errors if f.code == code]
    assert found, [f.line() for f in rep.errors]
    return found[0].line().split(" ", 1)[1]  # without 'ERROR '


def test_train_and_evaluate_refuse_negative_radiance_in_validates_words(clip, tmp_path, capsys):
    bad, exr = _negative(clip, tmp_path / "neg")
    words = _validate_line(bad, "negative-radiance")
    assert words.startswith("frame 2 lr/radiance: radiance is negative on ")
    assert main(["train", "--model", "fusesr", "--data", str(bad), "-o", str(tmp_path / "run"), "--max-steps", "1",
                 *set_args(SMALL)]) == 2
    line = one_line(capsys)
    assert line.startswith(f"blendsr: error: {exr}: {words};"), (line, words)
    assert main(["evaluate", "--model", "bilinear", "--data", str(bad), "--json", str(tmp_path / "e.json"),
                 "--no-flip"]) == 2
    assert one_line(capsys) == f"blendsr: error: {exr}: {words} (as 'blendsr validate' reports)"
    assert not (tmp_path / "e.json").exists()
    # data.nonfinite = "sanitize" trains on it, clamped to 0, with a warning
    with pytest.warns(RuntimeWarning, match="negative value"):
        assert main(["train", "--model", "fusesr", "--data", str(bad), "-o", str(tmp_path / "run2"), "--max-steps",
                     "1", *set_args(SMALL + ['data.nonfinite="sanitize"'])]) == 0


def test_train_refuses_nan_radiance_in_validates_words(clip, tmp_path, capsys):
    from gbuffer_export.clip import open_clip
    from gbuffer_export.exr import write_exr
    bad = fresh_copy(clip, tmp_path / "nan")
    c = open_clip(bad)
    a = c.read(3, "hr/radiance")
    a[1, 2, 0] = np.nan
    write_exr(c.path_of(3, "hr/radiance"), {ch: a[..., i] for i, ch in enumerate("RGB")})
    words = _validate_line(bad, "non-finite")
    assert main(["train", "--model", "fusesr", "--data", str(bad), "-o", str(tmp_path / "run"), "--max-steps", "1",
                 *set_args(SMALL)]) == 2
    assert one_line(capsys).startswith(f"blendsr: error: {c.path_of(3, 'hr/radiance')}: {words};")


def test_train_and_evaluate_refuse_a_split_leak_in_validates_words(clip, tmp_path, capsys):
    from gbuffer_export.dataset.build import INDEX, SCHEMA
    from gbuffer_export.dataset.check import validate_dataset
    ds = tmp_path / "ds"
    entries = []
    for cid, split in (("a", "train"), ("b", "test")):
        fresh_copy(clip, ds / "clips" / cid)
        entries.append({"id": cid, "path": f"clips/{cid}", "split": split, "frames_planned": 3,
                        "scene_id": "builtin-s0007", "licence": {"licence": "CC0"}})
    (ds / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": 1, "clips": entries}))
    words = "scene 'builtin-s0007' is in both the train and the test split"
    assert validate_dataset(ds, quick=True, progress=False).index_errors == [words]
    assert main(["train", "--model", "fusesr", "--data", str(ds), "-o", str(tmp_path / "run"), "--max-steps", "1",
                 *set_args(SMALL)]) == 2
    assert one_line(capsys).startswith(f"blendsr: error: {ds / INDEX}: {words}: a split leak")
    assert main(["evaluate", "--model", "bilinear", "--data", str(ds), "--json", str(tmp_path / "e.json")]) == 2
    assert one_line(capsys).startswith(f"blendsr: error: {ds / INDEX}: {words}: a split leak")
    assert not (tmp_path / "run" / "checkpoints").exists() and not (tmp_path / "e.json").exists()


# ------------------------------------------------------------------------------------ messages (item 9)
def test_a_full_cache_filesystem_names_the_file(clip, tmp_path, monkeypatch, capsys):
    """Issue 43 item 9: the one line names the cache file that could not be written (the index or an array), not
    only 'no space left on device'."""
    from gbuffer_export import clip as clip_module
    from training.cache import default_cache_path
    cache_dir = tmp_path / "cache"
    real = clip_module.os.fsync

    def full(fd):  # the index's write fails as on a full disk
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(clip_module.os, "fsync", full)
    argv = ["train", "--model", "fusesr", "--data", str(clip), "-o", str(tmp_path / "run"), "--max-steps", "1",
            *set_args(SMALL + [f'data.cache_dir="{cache_dir}"'])]
    assert main(argv) == 2
    index = default_cache_path(clip, cache_dir) / "index.json"
    assert one_line(capsys).startswith(f"blendsr: error: {index}: no space left for the training cache")
    assert not [p for p in cache_dir.rglob("*") if ".tmp" in p.name]
    monkeypatch.setattr(clip_module.os, "fsync", real)
    monkeypatch.setattr(os, "posix_fallocate", lambda fd, off, n: (_ for _ in ()).throw(OSError(28, "full")),
                        raising=False)
    assert main(argv) == 2
    line = one_line(capsys)
    assert line.startswith(f"blendsr: error: {default_cache_path(clip, cache_dir)}/") and ".npy: no space left" in line
