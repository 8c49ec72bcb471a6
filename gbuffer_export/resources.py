"""Memory and disk a render needs, estimated before it starts (pure Python; no bpy).

``blendsr render`` calls ``check_render_resources`` once the HR size, buffers and frames are known and before
anything is rendered or written; an absurd size (``--hr-size 100000x100000``) is refused with one line that says how
much is needed and how much there is, instead of growing until the machine swaps.

Memory model, peak resident memory of the render process::

    bytes = MEMORY_BASE + MEMORY_PER_HR_PIXEL * W * H

``MEMORY_PER_HR_PIXEL`` covers Cycles' render buffers, Blender's render result, the multilayer EXR read back and
the converted output arrays of one HR frame (the LR frame is 1/scale^2 of that and included). Measured with
``/usr/bin/time -f %M`` on ``blendsr render --frames 1:1 --hr-spp 1 --lr-spp 1 --buffers all`` of the built-in
scene at 640x360, 1280x720 and 1920x1080 (docs/results.md, "Render memory"): rounded up so that the estimate stays
above the measured peaks; scenes with large textures or geometry need more.

Disk model: the uncompressed payload of the frames still to render, ``(W*H + w*h) * channels * 4`` bytes per frame
(an upper bound: the EXRs are ZIP-compressed; float32 and uint32 are 4 bytes), plus Cycles' temporary multilayer
EXR of one frame.

Available memory is the smaller of the operating system's available memory (psutil, on Linux, macOS and Windows)
and what the cgroup memory limit leaves (Linux containers, when there is one). ``BLENDSR_MEMORY_AVAILABLE`` (bytes)
overrides it, for tests and for machines where swap should count.
"""
from __future__ import annotations

import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

from .config import ConfigError
from .conventions import BUFFERS

#: Resident memory of a render process before any pixel: Python, bpy, the scene (measured: ~0.6 GB).
MEMORY_BASE = 700 * 2**20
#: Peak bytes per HR pixel (the LR level included), all buffers; measured slope 656 B/pixel, rounded up.
MEMORY_PER_HR_PIXEL = 800
#: Channels of Cycles' temporary multilayer EXR per pixel (combined, depth, normal, vector, colour passes, AOVs).
TEMP_EXR_CHANNELS = 40


class ResourceError(ConfigError):
    """A render would need more memory or disk than there is (one line: needed, available, what to change)."""


@dataclass(frozen=True)
class RenderEstimate:
    memory_bytes: int   # peak resident memory of the render process
    disk_bytes: int     # upper bound of what the frames still to render write (uncompressed)
    frames: int


def human(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1000.0
    return f"{n:.3g} PB"


def estimate_render(hr_size: tuple[int, int], scale, buffers, frames: int) -> RenderEstimate:
    """Memory and disk of a render; ``scale``: one LR scale or a sequence of them (one LR level each)."""
    w, h = hr_size
    scales = tuple(scale) if isinstance(scale, (tuple, list)) else (scale,)
    lr_pixels = sum(int(w / s) * int(h / s) for s in scales)
    channels = sum(len(BUFFERS[b].channels) for b in buffers)
    per_frame = (w * h + lr_pixels) * channels * 4
    temp = w * h * TEMP_EXR_CHANNELS * 4
    return RenderEstimate(memory_bytes=MEMORY_BASE + MEMORY_PER_HR_PIXEL * w * h,
                          disk_bytes=per_frame * frames + (temp if frames else 0), frames=frames)


#: cgroup v2 and v1 files: (limit, usage) of the memory controller (Linux containers; absent elsewhere).
CGROUP_MEMORY = (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                 ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes"))


def cgroup_available() -> int | None:
    """Bytes left under this process's cgroup memory limit (Linux containers); None without a limit or elsewhere."""
    for limit, usage in CGROUP_MEMORY:
        try:
            lim = Path(limit).read_text().strip()
            if lim != "max" and int(lim) < 2**60:
                return int(lim) - int(Path(usage).read_text().strip())
            return None
        except (OSError, ValueError):
            continue
    return None


def system_available() -> int | None:
    """The operating system's available memory (``psutil.virtual_memory().available``: Linux, macOS, Windows);
    None when psutil cannot tell (an unreadable /proc)."""
    try:
        import psutil  # imported here: on Linux its import reads /proc
        return int(psutil.virtual_memory().available)
    except (ImportError, OSError, RuntimeError, AttributeError):
        return None


def available_memory() -> int | None:
    """Bytes of memory a new allocation can use (see module doc); None when unknown."""
    env = os.environ.get("BLENDSR_MEMORY_AVAILABLE")
    if env:
        return int(float(env))
    found = [v for v in (system_available(), cgroup_available()) if v is not None]
    return max(min(found), 0) if found else None


def peak_rss_bytes() -> int | None:
    """Peak resident memory of this process so far: ``getrusage`` where it exists (ru_maxrss is KiB on Linux,
    bytes on macOS), the peak working set on Windows (psutil); None when unknown."""
    try:
        import resource
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return int(peak) if sys.platform == "darwin" else int(peak) * 1024
    except (ImportError, OSError, AttributeError):
        pass
    try:
        import psutil
        info = psutil.Process().memory_info()
        return int(getattr(info, "peak_wset", info.rss))
    except (ImportError, OSError, RuntimeError):
        return None


#: The cgroup file system: v2 ``cpu.max`` ("QUOTA PERIOD", or "max PERIOD" without a quota), v1
#: ``cpu/cpu.cfs_quota_us`` (-1 without one) over ``cpu/cpu.cfs_period_us`` (also under ``cpu,cpuacct``). In a
#: container (Docker, Kubernetes, systemd-nspawn) these are the container's own: its cgroup namespace or bind mount.
CGROUP_ROOT = Path("/sys/fs/cgroup")


def _read_quota(folder: Path) -> float | None:
    """CPUs of the quota in one cgroup folder (v2 ``cpu.max`` or v1 ``cpu.cfs_quota_us``), None when unlimited."""
    try:
        quota, period = (folder / "cpu.max").read_text().split()[:2]
        return int(quota) / int(period) if quota != "max" and int(period) > 0 else None
    except (OSError, ValueError):
        pass
    try:
        quota, period = (int((folder / f"cpu.cfs_{k}_us").read_text()) for k in ("quota", "period"))
        return quota / period if quota > 0 and period > 0 else None
    except (OSError, ValueError):
        return None


def cgroup_cpu_quota(root: Path | None = None) -> float | None:
    """CPUs the cgroup CPU quota allows this process (v2 ``cpu.max``, else v1 ``cpu.cfs_quota_us`` over
    ``cpu.cfs_period_us``; the smallest found), or None without a quota or off Linux."""
    root = CGROUP_ROOT if root is None else Path(root)
    found = [q for q in map(_read_quota, (root, root / "cpu", root / "cpu,cpuacct")) if q is not None]
    return min(found) if found else None


def usable_cores(root: Path | None = None) -> int:
    """Cores this process may use: the CPUs of its affinity mask (``os.sched_getaffinity``; ``os.cpu_count``
    where the platform has none), capped by the cgroup CPU quota (rounded down, at least 1). The default thread
    count of training, evaluation, benchmarks and ``blendsr demo`` (torch's own default counts every core of the
    machine, whatever the container may use)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    quota = cgroup_cpu_quota(root)
    if quota is not None:
        cores = min(cores, max(1, int(quota)))
    return max(1, cores)


def default_threads(root: Path | None = None) -> int:
    """The thread count of training, evaluation and the benchmarks when none is given: ``OMP_NUM_THREADS`` where it
    is set to a positive whole number (the usual way to cap a process's threads, which torch's own default reads
    too; e.g. the test suite's workers, or two jobs side by side on one machine), else ``usable_cores``."""
    return omp_threads() or usable_cores(root)


def render_threads(requested: int) -> int:
    """Cycles threads of a render: ``requested`` when positive, else ``OMP_NUM_THREADS`` where set (the rule of
    ``default_threads``: two renders side by side, or the test suite's workers, each take their share), else 0,
    Blender's automatic count (all cores)."""
    return requested if requested > 0 else (omp_threads() or 0)


def omp_threads() -> int | None:
    """``OMP_NUM_THREADS`` when it is a positive whole number, else None."""
    v = os.environ.get("OMP_NUM_THREADS", "").strip()
    return int(v) if v.isdigit() and int(v) > 0 else None


#: How long ``idle_cores`` watches the machine before deciding, seconds.
IDLE_SAMPLE_S = 0.5


def _affinity() -> list[int]:
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return list(range(os.cpu_count() or 1))


def idle_cores(sample_s: float = IDLE_SAMPLE_S, root: Path | None = None) -> tuple[int, float]:
    """(threads to use, cores other work keeps busy): ``OMP_NUM_THREADS`` where set (``omp_threads``); else the
    CPUs of this process's affinity that stayed idle over ``sample_s`` seconds (psutil's per-CPU use, rounded),
    within [1, ``usable_cores``] (so a container's 2-core quota on a busy 64-core host still gets its 2). On a 2-core
    machine with two busy processes beside it, the demo's fine-tune ran 0.18 steps/s with 2 threads and 1.43 with 1
    (idle: 3.35 and 2.38; ``benchmarks/demo_speed.py``, docs/bench/demo_speed): torch's threads wait for each other
    when another process holds a core. Without psutil: all usable cores, 0 busy."""
    capped = omp_threads()
    if capped:
        return capped, 0.0
    cores = usable_cores(root)
    try:
        import psutil
    except ImportError:
        return cores, 0.0
    per_cpu = psutil.cpu_percent(interval=sample_s, percpu=True)
    mine = [per_cpu[i] for i in _affinity() if i < len(per_cpu)] or per_cpu
    busy = sum(mine) / 100.0
    return max(1, min(cores, int(round(len(mine) - busy)))), busy


def free_disk(path: Path) -> int | None:
    """Free bytes on the file system that holds ``path`` (its nearest existing ancestor)."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        return shutil.disk_usage(p).free
    except OSError:
        return None


def check_memory(need: int, what: str, fix: str, *, memory: int | None = None) -> None:
    """Raise ResourceError ('WHAT needs about N of memory and M is available; FIX') when an allocation of ``need``
    bytes exceeds the available memory (``available_memory``), before it is made."""
    memory = available_memory() if memory is None else memory
    if memory is not None and need > memory:
        raise ResourceError(f"{what} needs about {human(need)} of memory and {human(memory)} is available; {fix}")


def check_render_resources(hr_size: tuple[int, int], scale, buffers, frames: int, output: Path,
                           *, available: tuple[int | None, int | None] = (None, None), scene_bytes: int = 0,
                           scene: str | None = None) -> RenderEstimate:
    """Raise ResourceError when the estimate (plus ``scene_bytes``, the scene's own geometry and textures in
    Cycles) exceeds the available memory or the free disk; return it. ``available``: (memory, disk) in bytes to
    check against instead of this machine's (None: measured)."""
    est = estimate_render(hr_size, scale, buffers, frames)
    w, h = hr_size
    memory, disk = available
    memory = available_memory() if memory is None else memory
    if memory is not None and est.memory_bytes > memory:
        raise ResourceError(f"--hr-size {w}x{h}: rendering needs about {human(est.memory_bytes)} of memory and "
                            f"{human(memory)} is available; lower --hr-size")
    if memory is not None and scene_bytes and est.memory_bytes + scene_bytes > memory:
        raise ResourceError(f"{scene or 'scene'}: its geometry and textures need about {human(scene_bytes)} in "
                            f"Cycles, the frames {human(est.memory_bytes)}, and {human(memory)} is available; render "
                            "it on a machine with more memory or hide objects from rendering")
    disk = free_disk(output) if disk is None else disk
    if disk is not None and est.disk_bytes > disk:
        raise ResourceError(f"{output}: {frames} frame(s) of {w}x{h} with {len(list(buffers))} buffers need up to "
                            f"{human(est.disk_bytes)} of disk and {human(disk)} is free; lower --hr-size, --frames or "
                            "--buffers")
    return est
