"""Scene files imported in a child process with a memory and a time limit (core: no bpy; starts
``python -m gbuffer_export.blender.import_job``).

``import_in_child(scene, allow_read, out_dir)`` runs the importer of ``scene``'s format in a child process that
checks its references first (``scene_refs``), imports it, makes its paths absolute and saves it as
``out_dir/level.blend`` plus ``out_dir/result.json`` (the manifest's ``scene`` report); the renderer then opens that
.blend. The child:

- may use ``import_memory_limit()`` bytes of address space (``RLIMIT_AS`` where the OS has it; everywhere a
  ``psutil`` watchdog in the parent kills it above that resident size), ``BLENDSR_IMPORT_MEMORY_GB`` overrides;
- is killed after ``import_time_limit()`` seconds (``BLENDSR_IMPORT_TIME_S`` overrides);
- runs in its own session with the scene's folder as its working directory, and dies with its parent;
- a crash (SIGABRT, SIGSEGV), a limit or a refusal becomes one ``ConfigError`` line naming the file and the format.

Ctrl-C (``gbuffer_export.interrupt``) is checked while waiting: the child is killed and KeyboardInterrupt raised.
"""
from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from .errors import BlendSRError

log = logging.getLogger(__name__)

#: Default memory limit: this share of the machine's memory, within [MIN, MAX] GiB.
MEMORY_SHARE, MIN_MEMORY_GB, MAX_MEMORY_GB = 0.5, 4.0, 64.0
#: Default time limit of one import, seconds.
IMPORT_TIME_S = 900.0
POLL_S = 0.05


class ImportSandboxError(BlendSRError):
    """The importer crashed, hit a limit or refused the file (one line naming the file and the format)."""


def _env_float(name: str, default: float) -> float:
    v = os.environ.get(name)
    if not v:
        return default
    try:
        x = float(v)
    except ValueError:
        raise ImportSandboxError(f"{name}={v!r}: not a number") from None
    if not x > 0:
        raise ImportSandboxError(f"{name}={v!r}: must be > 0")
    return x


def import_memory_limit() -> int:
    """Bytes of memory the importer may use (module doc)."""
    import psutil
    total = psutil.virtual_memory().total / 2**30
    default = min(MAX_MEMORY_GB, max(MIN_MEMORY_GB, MEMORY_SHARE * total))
    return int(_env_float("BLENDSR_IMPORT_MEMORY_GB", default) * 2**30)


def import_time_limit() -> float:
    return _env_float("BLENDSR_IMPORT_TIME_S", IMPORT_TIME_S)


def set_memory_limit(limit: int) -> bool:
    """Cap this process's address space at ``limit`` bytes (RLIMIT_AS); False where the OS has no such limit."""
    try:
        import resource
        soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        resource.setrlimit(resource.RLIMIT_AS, (limit if hard < 0 else min(limit, hard), hard))
        return True
    except (ImportError, AttributeError, ValueError, OSError):
        return False


def _gb(n: float) -> str:
    return f"{n / 2**30:.3g} GiB"


def _signal_name(rc: int) -> str:
    try:
        return signal.Signals(-rc).name
    except ValueError:
        return f"signal {-rc}"


def _kill(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait()


def _wait(proc: subprocess.Popen, limit_s: float, memory: int) -> str | None:
    """Wait for the child; returns why it was killed ("time", "memory") or None. KeyboardInterrupt on Ctrl-C."""
    from .interrupt import check_interrupt
    try:
        import psutil
        watched = psutil.Process(proc.pid)
    except Exception:  # psutil missing or the child already gone
        watched = None
    t0 = time.monotonic()
    while proc.poll() is None:
        try:
            check_interrupt()
        except KeyboardInterrupt:
            _kill(proc)
            raise
        if time.monotonic() - t0 > limit_s:
            _kill(proc)
            return "time"
        if watched is not None:
            try:
                if watched.memory_info().rss > memory:
                    _kill(proc)
                    return "memory"
            except Exception:  # the child ended between the two calls
                pass
        time.sleep(POLL_S)
    return None


def _run_child(cmd: list[str], cwd: Path, out_dir: Path, memory: int, limit_s: float) -> tuple[int, str, str | None]:
    """Run ``cmd`` with the limits (module doc), its output in ``out_dir/import.log``: (exit code, output, why it
    was killed or None)."""
    env = dict(os.environ)
    repo = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = repo + os.pathsep + env.get("PYTHONPATH", "") if env.get("PYTHONPATH") else repo
    with open(out_dir / "import.log", "wb") as logf:
        proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=logf,
                                stderr=subprocess.STDOUT, start_new_session=True)
        killed = _wait(proc, limit_s, memory)
    return proc.returncode, (out_dir / "import.log").read_text(errors="replace").strip(), killed


def _child_failure(scene: Path, what: str, kind: str, rc: int, said: str, killed: str | None, memory: int,
                   limit_s: float) -> ImportSandboxError | None:
    """The one-line error of a child that was killed, crashed or failed (None when it exited 0)."""
    if killed == "time":
        return ImportSandboxError(f"{scene}: the {what} took longer than {limit_s:g} s (the import time limit, "
                                  "BLENDSR_IMPORT_TIME_S); stopped")
    if killed == "memory":
        return ImportSandboxError(f"{scene}: the {what} used more than {_gb(memory)} of memory (the import memory "
                                  "limit, BLENDSR_IMPORT_MEMORY_GB); stopped")
    if rc < 0:
        return ImportSandboxError(f"{scene}: the {what} failed (it crashed: {_signal_name(rc)}): not a readable "
                                  f"{kind} file, or it needs more than the import memory limit ({_gb(memory)}, "
                                  "BLENDSR_IMPORT_MEMORY_GB)")
    if rc != 0:
        last = said.splitlines()[-1][:200] if said else "no output"
        return ImportSandboxError(f"{scene}: the {what} failed (exit {rc}: {last})")
    return None


def import_in_child(scene: Path, fmt_name: str, allow_read, out_dir: Path) -> dict:
    """Import ``scene`` in a child process (module doc); returns its report (``level``: the saved .blend)."""
    scene, out_dir = Path(scene).absolute(), Path(out_dir)
    memory, limit_s = import_memory_limit(), import_time_limit()
    result = out_dir / "result.json"
    cmd = [sys.executable, "-m", "gbuffer_export.blender.import_job", str(scene), str(out_dir), "--memory",
           str(memory), "--parent", str(os.getpid())]
    for d in allow_read or ():
        cmd += ["--allow-read", str(Path(d).absolute())]
    rc, said, killed = _run_child(cmd, scene.parent, out_dir, memory, limit_s)
    if said:
        log.debug("%s: the import process said:\n%s", scene.name, said[-4000:])
    report = json.loads(result.read_text()) if result.is_file() and not killed else None
    if report is not None and report.get("error"):
        raise ImportSandboxError(report["error"])
    failure = _child_failure(scene, f"{fmt_name} importer", fmt_name, rc, said, killed, memory, limit_s)
    if failure is None and report is None:
        failure = ImportSandboxError(f"{scene}: the {fmt_name} importer failed (exit 0 and no report)")
    if failure is not None:
        raise failure
    return report


def check_asset_in_child(asset: Path, out_dir: Path) -> int:
    """Import the dataset asset ``asset`` as a clip's job does (``assets.import_asset``) in a child process with the
    import limits (``python -m gbuffer_export.blender.import_job ASSET OUT_DIR --asset``); returns its top-level
    object count.
    Its refusal, a crash, a limit or an unexpected error: one ImportSandboxError line naming the file."""
    asset, out_dir = Path(asset).absolute(), Path(out_dir)
    memory, limit_s = import_memory_limit(), import_time_limit()
    result = out_dir / "result.json"
    result.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "gbuffer_export.blender.import_job", str(asset), str(out_dir), "--memory",
           str(memory), "--parent", str(os.getpid()), "--asset"]
    rc, said, killed = _run_child(cmd, asset.parent, out_dir, memory, limit_s)
    report = json.loads(result.read_text()) if result.is_file() and not killed else None
    if report is not None and report.get("error"):
        raise ImportSandboxError(report["error"])
    failure = _child_failure(asset, "asset import", asset.suffix.lstrip(".").upper() or "asset", rc, said, killed,
                             memory, limit_s)
    if failure is None and report is None:
        failure = ImportSandboxError(f"{asset}: the asset import failed (exit 0 and no report)")
    if failure is not None:
        raise failure
    return int(report["report"]["objects"])


__all__ = ["ImportSandboxError", "check_asset_in_child", "import_in_child", "import_memory_limit", "import_time_limit",
           "set_memory_limit"]
