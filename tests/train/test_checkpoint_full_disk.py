"""A disk that fills while training writes a checkpoint or its log (issue 56): the one-line error names the file
(not only its folder; before, a refused log.csv row named nothing), exit 2, no temporary left. Simulated (torch reports the failed write as a RuntimeError), and
for real on a small tmpfs filled after the first checkpoint where mounting one is allowed."""
from __future__ import annotations

import shutil
import subprocess
import sys
import time
from collections import namedtuple

import pytest

torch = pytest.importorskip("torch")

from gbuffer_export.errors import bad_input_line  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from tests.conftest import ENV, REPO, set_args  # noqa: E402
from training import checkpoint  # noqa: E402


def test_a_failed_checkpoint_write_on_a_full_disk_names_the_file(tmp_path, monkeypatch):
    path = tmp_path / "run" / "checkpoints" / "step_00000003.pt"

    def save(state, f):
        open(f, "wb").close()
        raise RuntimeError("[enforce fail at inline_container.cc:664] . unexpected pos 64 vs 0")
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(torch, "save", save)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(1 << 20, 1 << 20, 0))
    with pytest.raises(OSError) as err:
        checkpoint.save_checkpoint(path, {"x": 1})
    assert bad_input_line(err.value) == f"{path}: no space left on device"
    assert not list(path.parent.iterdir())  # no temporary left


def test_a_disk_that_fills_during_training_names_the_checkpoint(tmp_path):
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("mounting a tmpfs is not permitted here (needs root); the simulated test covers the logic")
    try:
        clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)
        sets = ["data.crop=8", "data.batch_size=2", "model.fusesr.width=8", "model.fusesr.blocks=1",
                "run.progress=false", "run.amp=\"none\"", "run.threads=1", "run.checkpoint_every=1",
                f'data.cache_dir="{tmp_path / "cache"}"']
        proc = subprocess.Popen([sys.executable, "-m", "gbuffer_export.cli", "train", "--model", "fusesr", "--data",
                                 str(clip), "-o", str(mnt / "run"), "--max-steps", "500", *set_args(sets)],
                                cwd=REPO, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        t0 = time.monotonic()
        while not (mnt / "run" / "checkpoints" / "last.pt").exists() and proc.poll() is None \
                and time.monotonic() - t0 < 300:
            time.sleep(0.05)
        try:
            with open(mnt / "filler", "wb", buffering=0) as f:
                while True:
                    f.write(b"\0" * 65536)
        except OSError:
            pass
        _, err = proc.communicate(timeout=300)
        lines = err.strip().splitlines()
        assert proc.returncode == 2 and "Traceback" not in err, err[-2000:]
        named = lines[-1].removeprefix("blendsr: error: ").removesuffix(": no space left on device")
        assert named != lines[-1] and named.startswith(f"{mnt / 'run'}/"), lines[-1]
        assert named.endswith((".pt", "log.csv", ".json")), lines[-1]  # the file, not only its folder
        assert not [p for p in mnt.rglob("*") if ".tmp" in p.name]
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)
