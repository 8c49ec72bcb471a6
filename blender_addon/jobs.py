"""Render jobs of the add-on: one worker process (``worker.py``) per export or preview, its progress read from the
clip's ``frames/`` records, cancellation by killing the process (a rerun resumes: the renderer skips finished
frames). No bpy here: the caller says which executable runs the worker.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

WORKER = Path(__file__).with_name("worker.py")


def worker_command(job_file: Path, blender_binary: str = "", python: str = "") -> list[str]:
    """The worker's command line: the Blender application in background mode when ``blender_binary`` is set
    (inside the Blender app), else a Python that has bpy as a module (``python``, default ``sys.executable``)."""
    if blender_binary:
        return [blender_binary, "--background", "--factory-startup", "--python-exit-code", "2",
                "--python", str(WORKER), "--", str(job_file)]
    return [python or sys.executable, str(WORKER), str(job_file)]


@dataclass
class JobResult:
    """Outcome of a finished job. ``error`` is a one-line message when not ``ok``; ``valid`` is None when the clip
    was not validated."""

    ok: bool
    returncode: int
    error: str = ""
    output: str = ""
    valid: bool | None = None
    validation: str = ""
    seconds: float = 0.0
    log: str = ""
    summary: str = ""


class RenderJob:
    """A worker process rendering one clip. ``frames`` is the list of frames it must finish (for progress).
    The job file holds ``config_json`` under ``payload_key`` (``worker.py`` dispatches on it)."""

    payload_key = "config"

    def __init__(self, config_json: dict, frames: list[int], *, job_dir: Path, library_paths: dict,
                 validate: str = "", blender_binary: str = "", python: str = ""):
        self.config = config_json
        self.output = Path(config_json["output"])
        self.frames = list(frames)
        self.job_dir = Path(job_dir)
        self.job_dir.mkdir(parents=True, exist_ok=True)
        self.job_file = self.job_dir / "job.json"
        self.result_file = self.job_dir / "result.json"
        self.log_file = self.job_dir / "log.txt"
        if self.result_file.exists():
            self.result_file.unlink()
        job = {self.payload_key: config_json, **library_paths, "validate": validate, "result": str(self.result_file)}
        self.job_file.write_text(json.dumps(job, indent=1))
        self.command = worker_command(self.job_file, blender_binary, python)
        self.done_at_start = self.frames_done()
        self.started = time.monotonic()
        self._log = open(self.log_file, "w")
        kw = {"start_new_session": True} if os.name == "posix" else {}
        self.proc = subprocess.Popen(self.command, stdout=self._log, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, cwd=str(self.job_dir), **kw)
        self.cancelled = False

    # -- progress --------------------------------------------------------------------------------------------
    def frames_done(self) -> int:
        """Frames of this job whose record ``frames/NNNNNN.json`` exists (a record is written last)."""
        d = self.output / "frames"
        if not d.is_dir():
            return 0
        names = {p.name for p in d.glob("*.json")}
        return sum(f"{f:06d}.json" in names for f in self.frames)

    def progress(self) -> tuple[int, int, float | None]:
        """(frames done, frames planned, estimated seconds left or None before the first new frame)."""
        done, total = self.frames_done(), len(self.frames)
        new = done - self.done_at_start
        left = None
        if new > 0:
            per = (time.monotonic() - self.started) / new
            left = per * (total - done)
        return done, total, left

    def status_line(self) -> str:
        done, total, left = self.progress()
        eta = f", about {format_seconds(left)} left" if left is not None else ""
        return f"{done}/{total} frames{eta} (Esc cancels)"

    # -- process ---------------------------------------------------------------------------------------------
    def poll(self) -> int | None:
        return self.proc.poll()

    def wait(self, timeout: float | None = None) -> int:
        return self.proc.wait(timeout)

    def cancel(self, grace_s: float = 3.0) -> None:
        """Stop the worker (its whole process group on POSIX); finished frames stay and a rerun resumes."""
        self.cancelled = True
        if self.proc.poll() is not None:
            return
        try:
            if os.name == "posix":
                os.killpg(self.proc.pid, signal.SIGTERM)
            else:
                self.proc.terminate()
            self.proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            if os.name == "posix":
                os.killpg(self.proc.pid, signal.SIGKILL)
            else:
                self.proc.kill()
            self.proc.wait()
        except ProcessLookupError:
            pass

    def result(self) -> JobResult:
        """The outcome once the process has ended (reads the worker's result file)."""
        rc = self.proc.wait()
        self._log.close()
        log = self.log_file.read_text(errors="replace") if self.log_file.is_file() else ""
        seconds = time.monotonic() - self.started
        if self.cancelled:
            return JobResult(False, rc, "cancelled; run it again to resume", seconds=seconds, log=log)
        try:
            r = json.loads(self.result_file.read_text())
        except (OSError, json.JSONDecodeError):
            last = [ln for ln in log.splitlines() if ln.strip()]
            msg = last[-1] if last else "no output"
            return JobResult(False, rc, f"worker exited with code {rc} without a result: {msg}", seconds=seconds,
                             log=log)
        return JobResult(bool(r.get("ok")) and rc == 0, rc, r.get("error", ""), r.get("output", ""),
                         r.get("valid"), r.get("validation", ""), seconds, log, r.get("summary", ""))


class DatasetJob(RenderJob):
    """A worker process building a dataset (``worker.run_dataset``: ``build_dataset`` then ``validate_dataset``).
    ``payload`` holds ``output`` (the dataset folder); ``planned`` maps each clip id to its frames (for progress,
    counted from ``clips/<id>/frames/`` records)."""

    payload_key = "dataset"

    def __init__(self, payload: dict, planned: dict[str, int], **kw):
        self.planned = dict(planned)
        super().__init__(payload, list(range(sum(self.planned.values()))), **kw)

    def clip_frames(self) -> dict[str, int]:
        """Clip id -> frames finished (records written), at most its planned frames."""
        out = {}
        for cid, total in self.planned.items():
            d = self.output / "clips" / cid / "frames"
            out[cid] = min(total, sum(1 for _ in d.glob("*.json"))) if d.is_dir() else 0
        return out

    def frames_done(self) -> int:
        return sum(self.clip_frames().values())

    def status_line(self) -> str:
        done_by_clip = self.clip_frames()
        clips = sum(done_by_clip[c] >= n for c, n in self.planned.items())
        done, total, left = self.progress()
        eta = f", about {format_seconds(left)} left" if left is not None else ""
        return f"{clips}/{len(self.planned)} clips, {done}/{total} frames{eta} (Esc cancels)"


def new_job_dir(prefix: str = "blendsr-job-") -> Path:
    return Path(tempfile.mkdtemp(prefix=prefix))


def format_seconds(s: float) -> str:
    s = max(0.0, float(s))
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"
