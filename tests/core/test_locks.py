"""One writer per folder (gbuffer_export.locks): a second holder is refused in one line, the kernel releases the
lock of a killed process, a planted link is never written through; the dataset coordinator uses it."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from tests.conftest import run_cli
from gbuffer_export.clip import UnsafePathError
from gbuffer_export.locks import FolderBusyError, FolderLock

HOLD = "import sys, time; from gbuffer_export.locks import FolderLock; FolderLock(sys.argv[1], 'busy'); " \
       "print('held', flush=True); time.sleep(60)"


def test_a_second_holder_is_refused_until_the_first_closes(tmp_path):
    first = FolderLock(tmp_path, "another run is writing here")
    with pytest.raises(FolderBusyError, match=f"^{tmp_path}: another run is writing here$"):
        FolderLock(tmp_path, "another run is writing here")
    first.close()
    with FolderLock(tmp_path, "x"):
        pass


def test_a_killed_holder_leaves_no_stale_lock(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "held"
        with pytest.raises(FolderBusyError):
            FolderLock(tmp_path, "busy")
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    FolderLock(tmp_path, "busy").close()  # the lock file stays; the lock went with the process


def test_a_planted_link_is_refused(tmp_path):
    outside = tmp_path / "outside"
    outside.write_text("keep")
    root = tmp_path / "root"
    root.mkdir()
    (root / ".lock").symlink_to(outside)
    with pytest.raises(UnsafePathError, match="symbolic link"):
        FolderLock(root, "busy")
    assert outside.read_text() == "keep"


def test_dataset_refuses_a_folder_another_coordinator_holds(tmp_path):
    spec = tmp_path / "spec.toml"
    spec.write_text('[dataset]\nname = "lk"\nseed = 1\n[render]\nframes = 2\nhr_size = "64x32"\nscale = 4\n'
                    'hr_spp = 1\nlr_spp = 1\ngbuffer_spp = 1\n[[source]]\nname = "b"\nkind = "builtin"\n'
                    'seeds = "0:0"\ncameras = ["scene"]\n')
    ds = tmp_path / "ds"
    ds.mkdir()
    t0 = time.monotonic()
    with FolderLock(ds, "held by the test"):
        proc = run_cli("dataset", spec, "-o", ds, timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1] == \
        f"blendsr: error: {ds}: another 'blendsr dataset' is running on this folder"
    assert not (ds / "clips").exists() and time.monotonic() - t0 < 60
