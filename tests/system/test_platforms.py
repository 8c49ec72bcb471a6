"""Issue 42 item 3: every platform Blender runs on. No POSIX-only import on any path (every module imports without
fcntl and with /proc unreadable), memory from psutil with the cgroup limit kept, the training cache's reservation
without posix_fallocate, the folder lock through filelock."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import ENV, REPO

psutil = pytest.importorskip("psutil", reason="psutil is a dependency of blendsr: pip install -e .")


def test_every_module_imports_without_fcntl_and_with_proc_unreadable(tmp_path):
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve().parent.parent / "no_posix_imports.py"), str(REPO),
                           str(tmp_path)], cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    imported = int(proc.stdout.split("imported ")[1].split(",")[0])
    assert imported >= 60, proc.stdout  # the core alone has more than 60 modules


def test_available_memory_is_psutils_bounded_by_the_cgroup_limit(tmp_path, monkeypatch):
    from gbuffer_export import resources
    monkeypatch.delenv("BLENDSR_MEMORY_AVAILABLE", raising=False)

    class VM:
        available = 8 * 2**30
    monkeypatch.setattr(psutil, "virtual_memory", lambda: VM)
    limit, usage = tmp_path / "memory.max", tmp_path / "memory.current"
    monkeypatch.setattr(resources, "CGROUP_MEMORY", ((str(limit), str(usage)),))
    assert resources.available_memory() == 8 * 2**30  # no cgroup files: the system's
    limit.write_text("max\n")
    usage.write_text("123\n")
    assert resources.available_memory() == 8 * 2**30  # no limit
    limit.write_text(str(2 * 2**30))
    usage.write_text(str(2**30))
    assert resources.available_memory() == 2**30  # the container's limit leaves less
    monkeypatch.setenv("BLENDSR_MEMORY_AVAILABLE", "5e9")
    assert resources.available_memory() == 5 * 10**9
    monkeypatch.delenv("BLENDSR_MEMORY_AVAILABLE")
    monkeypatch.setattr(psutil, "virtual_memory", lambda: (_ for _ in ()).throw(OSError(13, "no /proc")))
    assert resources.available_memory() == 2**30  # psutil cannot read /proc: the cgroup's alone


def test_usable_cores_are_the_affinity_capped_by_the_cgroup_quota(tmp_path, monkeypatch):
    """Issue 57 item 2: the default thread count is what this process may use, not every core of the machine."""
    from gbuffer_export import resources
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 5}, raising=False)
    assert resources.usable_cores(tmp_path) == 4  # no cgroup files: the affinity mask
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert resources.usable_cores(tmp_path) == 4  # v2 without a quota
    (tmp_path / "cpu.max").write_text("250000 100000\n")
    assert resources.cgroup_cpu_quota(tmp_path) == 2.5 and resources.usable_cores(tmp_path) == 2
    (tmp_path / "cpu.max").write_text("50000 100000\n")
    assert resources.usable_cores(tmp_path) == 1  # half a core: at least one thread
    (tmp_path / "cpu.max").unlink()
    v1 = tmp_path / "cpu,cpuacct"
    v1.mkdir()
    (v1 / "cpu.cfs_quota_us").write_text("-1\n")
    (v1 / "cpu.cfs_period_us").write_text("100000\n")
    assert resources.cgroup_cpu_quota(tmp_path) is None and resources.usable_cores(tmp_path) == 4
    (v1 / "cpu.cfs_quota_us").write_text("300000\n")
    assert resources.usable_cores(tmp_path) == 3  # v1 quota
    monkeypatch.delattr(os, "sched_getaffinity")  # macOS, Windows: os.cpu_count, still capped by a quota file
    monkeypatch.setattr(os, "cpu_count", lambda: 16)
    assert resources.usable_cores(tmp_path) == 3 and resources.usable_cores(tmp_path / "none") == 16


def test_idle_cores_leave_out_the_cores_other_work_keeps_busy(tmp_path, monkeypatch):
    """Issue 57 item 2: the demo's default threads are the idle CPUs of this process's affinity, within the usable
    cores; OMP_NUM_THREADS, where set, is taken as it is."""
    from gbuffer_export import resources
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(resources, "usable_cores", lambda root=None: 4)
    monkeypatch.setattr(resources, "_affinity", lambda: [0, 1, 2, 3])
    for per_cpu, want in (([0, 0, 0, 0], 4), ([80, 0, 0, 0], 3), ([100, 100, 0, 0], 2), ([100] * 4, 1)):
        monkeypatch.setattr(psutil, "cpu_percent", lambda interval=None, percpu=False, p=per_cpu: p)
        assert resources.idle_cores(0.0)[0] == want
    # a 2-core quota in a container on a 64-core host at 20 %: its 2 cores, not 64 less the host's 12.8 busy
    monkeypatch.setattr(resources, "usable_cores", lambda root=None: 2)
    monkeypatch.setattr(resources, "_affinity", lambda: list(range(64)))
    monkeypatch.setattr(psutil, "cpu_percent", lambda interval=None, percpu=False: [20.0] * 64)
    assert resources.idle_cores(0.0) == (2, 12.8)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert resources.idle_cores(0.0) == (3, 0.0)
    monkeypatch.setenv("OMP_NUM_THREADS", "0")  # not a count: measured as without it
    assert resources.idle_cores(0.0) == (2, 12.8)
    monkeypatch.undo()
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(os.cpu_count() or 1)]
    try:  # every core busy beside it: one thread, whatever this machine has
        time.sleep(0.5)
        threads, load = resources.idle_cores(1.0)
        assert threads == 1 and load > 0.5 * min(len(busy), resources.usable_cores()), (threads, load)
    finally:
        for p in busy:
            p.kill()
            p.wait()


def test_torch_threads_default_to_the_usable_cores(monkeypatch):
    torch = pytest.importorskip("torch")
    from gbuffer_export import resources
    from training.config import RunConfig
    from training.device import set_threads
    before = torch.get_num_threads()
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(resources, "usable_cores", lambda root=None: 1)
    try:
        assert RunConfig().threads == 0 and set_threads(0) == 1 and torch.get_num_threads() == 1
        assert set_threads(2) == 2 and torch.get_num_threads() == 2
        monkeypatch.setenv("OMP_NUM_THREADS", "3")  # the user's cap (the suite's workers set it)
        assert set_threads(0) == 3 and torch.get_num_threads() == 3
        monkeypatch.setenv("OMP_NUM_THREADS", "0")  # not a count: the usable cores
        assert set_threads(0) == 1
    finally:
        torch.set_num_threads(before)


def test_peak_rss_is_at_least_the_current_rss():
    from gbuffer_export.resources import peak_rss_bytes
    assert peak_rss_bytes() >= psutil.Process().memory_info().rss * 0.9 > 0


def test_the_cache_reserves_its_arrays_without_posix_fallocate(tmp_path, monkeypatch):
    """macOS and Windows have no posix_fallocate: the array is written with zeros (every block allocated), and a
    full filesystem there is the same one line naming the file."""
    from training.cache import CacheSpaceError, reserve
    monkeypatch.delattr(os, "posix_fallocate", raising=False)
    path = tmp_path / "a.npy"
    fd = os.open(path, os.O_RDWR | os.O_CREAT)
    try:
        reserve(fd, 10_000_003, path)
    finally:
        os.close(fd)
    assert path.stat().st_size == 10_000_003 and path.read_bytes()[-7:] == bytes(7)
    real = os.write
    monkeypatch.setattr(os, "write", lambda fd, b: (_ for _ in ()).throw(OSError(28, "No space left on device")))
    fd = os.open(path, os.O_RDWR)
    try:
        with pytest.raises(CacheSpaceError, match=f"^{path}: no space left for the training cache"):
            reserve(fd, 100, path)
    finally:
        monkeypatch.setattr(os, "write", real)
        os.close(fd)


def test_locks_import_no_fcntl_and_use_filelock():
    import ast
    for rel in ("gbuffer_export/locks.py", "training/cache.py", "gbuffer_export/resources.py"):
        tree = ast.parse((REPO / rel).read_text())
        names = {a.name for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))
                 for a in n.names} | {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        assert "fcntl" not in names and '"/proc/' not in (REPO / rel).read_text(), rel  # no /proc/... path read
    assert "filelock" in (REPO / "gbuffer_export/locks.py").read_text()
