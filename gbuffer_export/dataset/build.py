"""Render a dataset from a spec, resumably, on local worker processes or a Ray cluster (pure Python; the clips
are rendered by ``python -m gbuffer_export.blender.dataset_job`` processes).

Layout::

    DATASET/dataset.json          the index: every clip with split, source, seed, licence, settings and state
    DATASET/clips/<id>/           one BlendSR clip per job (docs/clip-format.md)
    DATASET/jobs/<id>.json        the job a worker renders (the explicit ClipJob)
    DATASET/logs/<id>.log         the worker's stderr of its last run

Only this coordinator writes ``dataset.json`` (atomically, after every clip); a second coordinator on the same
folder is refused. Every run recomputes each clip's state from its folder, so a run killed at any moment (kill -9
included) resumes: finished clips are skipped, partial clips resume at their first missing frame, and at most the
frames in flight are rendered again. Worker processes die with the coordinator (Linux parent-death signal). Ctrl-C
(SIGINT to the process group or to the coordinator alone) starts no further clip, stops the clip processes in
flight (``ChildProcesses.stop``; Ray tasks are cancelled) and exits within seconds; the rerun resumes.
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path

from ..clip import Clip, ClipError, check_no_links, open_clip, open_nofollow, resolve_inside, write_json_atomic
from ..errors import BlendSRError
from ..locks import FolderLock
from .spec import LEGACY_RENDER_KEYS, SPLITS, ClipJob, DatasetSpec, SpecError, expand, mixed_rank

log = logging.getLogger(__name__)

INDEX = "dataset.json"
SCHEMA = "blendsr-dataset"
SCHEMA_VERSION = 1
STATES = ("pending", "partial", "done", "failed")
EXECUTORS = ("local", "ray")
#: The orders a run renders its clips in (RunOptions.order, --order).
ORDERS = ("spec", "mixed", "train-first")
#: Seconds a clip process has to stop after Ctrl-C before it is killed (``ChildProcesses.stop``).
STOP_GRACE_S = 4.0


class DatasetError(BlendSRError):
    """A dataset folder that cannot be used as asked; one line naming the path."""


@dataclass(frozen=True)
class RunOptions:
    """How to execute: ``workers`` clips at a time (local) or as many as the Ray cluster schedules, each clip's
    Cycles render on ``threads`` threads (0: locally the machine's cores divided by ``workers``; on Ray 1, so that
    the cluster runs one clip per CPU it has: see ``clip_threads``)."""

    executor: str = "local"
    workers: int = 1
    threads: int = 0
    address: str | None = None      # Ray: cluster address ("auto", "ray://host:10001", ...); None starts one
    buffers_for: tuple[str, ...] = ()  # --for-models: the models whose buffers are rendered (recorded)
    progress: bool = True
    limit: int | None = None        # render at most this many clips in this run (tests, smoke runs)
    clips: tuple[str, ...] = ()     # --clips: render only the clips these ids or shell patterns name (all: empty)
    splits: tuple[str, ...] = ()    # --split: render only the clips of these splits (all: empty)
    order: str = "spec"             # the order clips render in: the spec's, "mixed" (spec.mixed_rank), "train-first"
    device: str = "auto"            # Cycles device of every clip (auto: a GPU when Cycles sees one)
    blender: str = ""               # a Blender executable to render each clip with (local executor; see job_command)

    def __post_init__(self) -> None:  # lists (a JSON job file's, the add-on worker's) as the tuples they stand for
        for name in ("buffers_for", "clips", "splits"):
            value = getattr(self, name)
            object.__setattr__(self, name, () if value is None else (value,) if isinstance(value, str)
                               else tuple(value))

    def validate(self) -> None:
        if self.executor not in EXECUTORS:
            raise SpecError(f"--executor {self.executor!r}: choose one of {', '.join(EXECUTORS)}")
        if self.order not in ORDERS:
            raise SpecError(f"--order {self.order!r}: choose one of {', '.join(ORDERS)}")
        bad = [s for s in self.splits if s not in SPLITS]
        if bad:
            raise SpecError(f"--split {bad[0]!r}: choose from {', '.join(SPLITS)}")
        if self.workers < 1:
            raise SpecError(f"--workers {self.workers}: must be at least 1")
        if self.threads < 0:
            raise SpecError(f"--threads {self.threads}: must be >= 0")
        if self.blender and self.executor != "local":
            raise SpecError(f"a Blender executable ({self.blender}) renders clips on the local executor only")
        if self.executor == "ray" and self.address is not None:  # its form, before anything is written
            from .ray_cluster import check_address
            try:
                check_address(self.address)
            except ImportError:  # no Ray: _ray_map names the extra
                pass

    def clip_threads(self) -> int:
        """Cycles threads of each clip. ``threads`` 0 means: locally, this machine's cores divided by ``workers``;
        on Ray, 1 (each task asks Ray for ``num_cpus=1``, and Ray runs as many at once as the cluster's nodes have
        CPUs; the submitting machine's cores say nothing about the nodes')."""
        if self.threads:
            return self.threads
        if self.executor == "ray":
            return 1
        return max(1, (os.cpu_count() or 1) // self.workers)


# ----------------------------------------------------------------------------------------------
# Index
# ----------------------------------------------------------------------------------------------

def clip_state(path: Path, planned: int) -> tuple[str, int]:
    """(state, finished frames) of a clip folder: pending (nothing finished), partial, or done."""
    state, n, _ = opened_state(path, planned)
    return state, n


def opened_state(path: Path, planned: int) -> tuple[str, int, Clip | None]:
    """``clip_state`` and the opened clip (None when there is no readable manifest), for readers of its frames."""
    if not (path / "manifest.json").is_file():
        return "pending", 0, None
    try:
        clip = open_clip(path)
    except ClipError:
        return "partial", 0, None
    n = len(clip.frames)
    if clip.complete and n >= planned:
        return "done", n, clip
    return ("partial" if n else "pending"), n, clip


def quick_check(clip_dir: Path) -> str:
    """'' when a finished clip passes ``validate_clip(quick=True)`` (headers of every frame, pixels of the first and
    last), else its first error line: a black frame, a NaN, motion that disagrees, as ``blendsr validate`` says."""
    from ..validate.runner import validate_clip
    report = validate_clip(clip_dir, quick=True)
    return "" if report.ok else report.errors[0].line()


def spec_digest(spec_path: Path | None) -> str | None:
    if spec_path is None:
        return None
    return hashlib.sha256(Path(spec_path).read_bytes()).hexdigest()


def make_index(spec: DatasetSpec, jobs: list[ClipJob], root: Path, old: dict | None, opts: RunOptions) -> dict:
    entries = []
    old_err = {c["id"]: c.get("error") for c in (old or {}).get("clips", [])}
    old_invalid = {c["id"]: c.get("invalid") for c in (old or {}).get("clips", [])}
    for j in jobs:
        path = root / "clips" / j.id
        state, n = clip_state(path, j.render["frames"])
        e = {**j.to_json(), "path": f"clips/{j.id}", "state": state, "frames_done": n,
             "frames_planned": j.render["frames"]}
        if state != "done" and old_err.get(j.id):
            e["error"] = old_err[j.id]
        if state == "done" and old_invalid.get(j.id):  # checked when it finished: still what validate reports
            e["invalid"] = old_invalid[j.id]
        entries.append(e)
    return {
        "schema": SCHEMA, "schema_version": SCHEMA_VERSION, "name": spec.name, "seed": spec.seed,
        "spec": {"file": str(spec.path) if spec.path else None, "sha256": spec_digest(spec.path),
                 "text": spec.path.read_text() if spec.path else None},
        "for_models": list(opts.buffers_for),
        "for_formats": list(spec.for_formats),
        "splits": {s: [e["id"] for e in entries if e["split"] == s] for s in SPLITS},
        "clips": entries,
    }


def read_index(root: str | os.PathLike) -> dict:
    """``DATASET/dataset.json`` as a dict; DatasetError (one line) when missing or malformed."""
    p = Path(root) / INDEX
    if not p.is_file():
        raise DatasetError(f"{Path(root)}: no {INDEX} (not a BlendSR dataset)")
    try:
        d = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{p}: not valid JSON ({exc})") from None
    if not isinstance(d, dict) or d.get("schema") != SCHEMA:
        raise DatasetError(f"{p}: not a BlendSR dataset index (schema is not {SCHEMA!r})")
    if not isinstance(d.get("schema_version"), int) or d["schema_version"] > SCHEMA_VERSION:
        raise DatasetError(f"{p}: schema_version {d.get('schema_version')!r} is newer than this blendsr reads")
    if not isinstance(d.get("clips"), list):
        raise DatasetError(f"{p}: index lacks its 'clips' list")
    check_index_entries(p, d["clips"])
    return d


def clip_dir(root: str | os.PathLike, entry) -> Path:
    """The folder of one ``clips`` entry of ``root/dataset.json``, by the one rule for index paths
    (``clip.resolve_inside``): its ``path`` is relative and, links resolved, inside the dataset folder; a one-line
    error naming dataset.json and the entry otherwise. Every reader of the index goes through here."""
    root = Path(root)
    if not isinstance(entry, dict):
        raise DatasetError(f"{root / INDEX}: a clips entry is not an object ({entry!r:.60})")
    return resolve_inside(root, entry.get("path"), source=root / INDEX, entry=f"clip {entry.get('id', '?')!r}")


def check_index_entries(p: Path, clips: list) -> None:
    """Every clip entry of an index has the keys its readers use, of the right type; DatasetError naming the
    index file, the entry and the key otherwise (never a KeyError)."""
    for i, c in enumerate(clips):
        if not isinstance(c, dict):
            raise DatasetError(f"{p}: clips[{i}] is not an object")
        name = f"clips[{i}]" + (f" ({c['id']})" if isinstance(c.get("id"), str) else "")
        for key in ("id", "path", "split"):
            if not isinstance(c.get(key), str) or not c[key]:
                what = "lacks" if key not in c else f"has {key} = {c[key]!r}, not a string:"
                raise DatasetError(f"{p}: {name} {what} {key!r}" if key not in c else f"{p}: {name} {what}")
        if c["split"] not in SPLITS:
            raise DatasetError(f"{p}: {name}: split {c['split']!r} is not one of {', '.join(SPLITS)}")
        fp = c.get("frames_planned", 0)
        if not isinstance(fp, int) or isinstance(fp, bool) or fp < 0:
            raise DatasetError(f"{p}: {name}: frames_planned = {fp!r} is not an integer >= 0")


def is_dataset(path: str | os.PathLike) -> bool:
    return (Path(path) / INDEX).is_file()


def split_clips(root: str | os.PathLike, split: str, done_only: bool = True) -> list[Path]:
    """The clip folders of one split of a dataset (finished clips only, unless ``done_only`` is False). A finished
    clip that failed its check (``invalid`` in the index, ``quick_check``) is left out with a warning: nothing trains
    on or is scored against a black or broken clip."""
    if split not in SPLITS:
        raise DatasetError(f"split {split!r}: choose one of {', '.join(SPLITS)}")
    root = Path(root)
    idx = read_index(root)
    out = []
    for c in idx["clips"]:
        if not isinstance(c, dict) or c.get("split") != split:
            continue
        path = clip_dir(root, c)
        if done_only and clip_state(path, int(c.get("frames_planned", 0)))[0] != "done":
            continue
        if done_only and c.get("invalid"):
            log.warning(f"{root}: clip {c.get('id')} left out of the {split} split: {c['invalid']}")
            continue
        out.append(path)
    return out


def whole_split(root: str | os.PathLike, split: str) -> list[Path]:
    """The clip folders of one split, only when every clip the index plans there is finished and valid (a score of
    part of a split would pass for the whole); DatasetError (one line) when any is not, or when none is planned."""
    done = split_clips(root, split)
    planned = sum(isinstance(c, dict) and c.get("split") == split for c in read_index(Path(root))["clips"])
    if not planned:
        raise DatasetError(f"{root}: its index plans no {split} clip")
    if len(done) < planned:
        raise DatasetError(f"{root}: {planned - len(done)} of its {planned} {split} clips are not finished (or not "
                           f"valid); the whole {split} split is read or none of it")
    return done


def expand_data_paths(paths, split: str) -> list[Path]:
    """``--data`` arguments: clip folders stay, a dataset folder becomes the finished clips of ``split``
    (DatasetError when it has none)."""
    out: list[Path] = []
    for p in paths:
        p = Path(p)
        if is_dataset(p):
            clips = split_clips(p, split)
            if not clips:
                raise DatasetError(f"{p}: the dataset has no finished clips in its {split!r} split")
            out += clips
        else:
            out.append(p)
    return out


# ----------------------------------------------------------------------------------------------
# Execution
# ----------------------------------------------------------------------------------------------

def _die_with_parent() -> None:  # runs in the child before exec (Linux): SIGKILL when the coordinator dies
    try:
        import ctypes
        ctypes.CDLL("libc.so.6").prctl(1, signal.SIGKILL)
    except OSError:
        pass


def job_command(job_path: Path, clip_dir: Path, threads: int, device: str = "auto", blender: str = "") -> list[str]:
    """One clip's worker command: this Python with bpy as a module (``-m gbuffer_export.blender.dataset_job``), or,
    with ``blender`` (the Blender application's executable: inside Blender ``sys.executable`` is its bundled Python,
    which cannot import bpy), Blender in background mode running ``blender/dataset_job_script.py``."""
    args = [str(job_path), str(clip_dir), "--threads", str(threads), "--device", device]
    if blender:
        script = Path(__file__).resolve().parents[1] / "blender" / "dataset_job_script.py"
        return [blender, "--background", "--factory-startup", "--python-exit-code", "2", "--python", str(script),
                "--", *args]
    return [sys.executable, "-m", "gbuffer_export.blender.dataset_job", *args]


class ChildProcesses:
    """The clip processes this coordinator runs, so that Ctrl-C stops them: ``stop`` refuses new ones and ends the
    running ones (SIGINT, which a worker answers by stopping after its render pass, or at once when it had one
    from the terminal already; SIGKILL for any still running ``grace`` seconds later). Frames are written
    atomically, so a killed worker loses at most its frame in flight, as after kill -9."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._procs: set[subprocess.Popen] = set()
        self.stopping = False

    def run(self, cmd: list[str], **kw) -> int | None:
        """Run ``cmd`` to its end and return its exit code; None (nothing started) once ``stop`` was called."""
        with self._lock:
            if self.stopping:
                return None
            proc = subprocess.Popen(cmd, **kw)
            self._procs.add(proc)
        try:
            return proc.wait()
        finally:
            with self._lock:
                self._procs.discard(proc)

    def stop(self, grace: float = STOP_GRACE_S) -> None:
        """Start no more processes and end the running ones within about ``grace`` seconds (a second Ctrl-C
        meanwhile kills them at once)."""
        with self._lock:
            self.stopping = True
            procs = list(self._procs)
        hurry = threading.Event()
        previous = None
        if threading.current_thread() is threading.main_thread():
            previous = signal.signal(signal.SIGINT, lambda *_: hurry.set())
        try:
            for p in procs:
                with contextlib.suppress(ProcessLookupError):
                    p.send_signal(signal.SIGINT)
            deadline = time.monotonic() + grace
            while any(p.poll() is None for p in procs) and time.monotonic() < deadline and not hurry.is_set():
                time.sleep(0.05)
            for p in procs:
                if p.poll() is None:
                    with contextlib.suppress(ProcessLookupError):
                        p.kill()
                    p.wait()
        finally:
            if previous is not None:
                signal.signal(signal.SIGINT, previous)

    def reset(self) -> None:
        with self._lock:
            self.stopping = False


#: The clip processes of this coordinator (``run_job_process``).
CHILDREN = ChildProcesses()


def run_job_process(job_path: str, clip_dir: str, log_path: str, threads: int,
                    cpu: int | None = None, device: str = "auto", blender: str = "") -> tuple[int, str]:
    """Render one clip in a child process (on core ``cpu`` when given and ``threads`` is 1; with Blender's
    executable ``blender`` when given: ``job_command``); returns (exit code, the last line of its stderr): exit
    code 130 without starting it once the coordinator is stopping (``CHILDREN.stop``)."""
    Path(log_path).parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    if cpu is not None:
        env["BLENDSR_CPU"] = str(cpu)
    repo = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = repo + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    if CHILDREN.stopping:
        return 130, "interrupted"
    with open(log_path, "w") as log:
        rc = CHILDREN.run(job_command(Path(job_path), Path(clip_dir), threads, device, blender),
                          stdout=subprocess.DEVNULL, stderr=log, env=env,
                          preexec_fn=_die_with_parent if sys.platform == "linux" else None)
    if rc is None:
        return 130, "interrupted"
    lines = [ln for ln in Path(log_path).read_text(errors="replace").splitlines()
             if ln.strip() and not ln.startswith(("render:", "\r"))]
    err = next((ln for ln in reversed(lines) if "error" in ln.lower()), lines[-1] if lines else "")
    return rc, err.strip()


def _local_map(todo, run_one, workers: int, on_done) -> None:
    """Run ``run_one(job, slot)`` for every job on ``workers`` threads, each holding one slot 0..workers-1. On
    Ctrl-C (KeyboardInterrupt in this thread) no further job starts, the running clip processes are stopped
    (``CHILDREN.stop``) and the KeyboardInterrupt goes on."""
    import queue
    slots: queue.Queue = queue.Queue()
    for k in range(workers):
        slots.put(k)

    def with_slot(job):
        k = slots.get()
        try:
            return run_one(job, k)
        finally:
            slots.put(k)

    CHILDREN.reset()
    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        futures = {pool.submit(with_slot, j): j for j in todo}
        pending = set(futures)
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in done:
                on_done(futures[fut], *fut.result())
    except BaseException:
        CHILDREN.stop()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def fit_ray_threads(nodes: list, threads: int, explicit: bool, address: str | None) -> int:
    """The threads (= CPUs) one clip's Ray task asks for, checked against the cluster's alive nodes (``ray.nodes()``)
    before anything is submitted: a task asking for more CPUs than any node has would wait forever (Ray's
    'infeasible' task). An explicit ``--threads`` that no node can hold is refused (DatasetError, one line); the
    automatic choice is lowered to the largest node's CPUs."""
    cpus = [float((n.get("Resources") or {}).get("CPU", 0)) for n in nodes if isinstance(n, dict) and n.get("Alive")]
    largest = int(max(cpus, default=0))
    where = f"the Ray cluster at {address}" if address else "the local Ray cluster"
    if largest < 1:
        raise DatasetError(f"{where}: no alive node offers a CPU, so no clip could ever run")
    if max(1, threads) > largest:
        if explicit:
            raise DatasetError(f"--threads {threads}: no node of {where} has {threads} CPUs (the largest has "
                               f"{largest}), so its tasks could never run; pass --threads {largest} or fewer")
        log.info(f"blendsr: {threads} threads per clip lowered to {largest}, the CPUs of the largest node of {where}")
        return largest
    return threads


def _ray_map(todo, root: Path, threads: int, address: str | None, on_done, explicit: bool = True,
             device: str = "auto") -> None:
    """Render ``todo`` as Ray tasks, one clip each, on the cluster at ``address`` (None: a local one started here).

    On Ctrl-C a driver that this call connected (or a local cluster it started) leaves the cluster
    (``ray.shutdown``) instead of cancelling its tasks: Ray ends a job's workers when its driver goes, and their clip
    processes die with them (parent-death signal). ``ray.cancel`` races with a task's completion reply in Ray's core
    worker (2.60: "Check failed: ... Tried to complete task that was not pending", an abort that loses the exit
    code; ray-project/ray#54846), measured 1 run in 24 under load. In a Ray session the caller opened before (the
    Python API), which is not this call's to end, the tasks are cancelled as before."""
    if not todo:
        return
    from .ray_cluster import bound_gcs_connection, connect
    bound_gcs_connection(address)
    try:
        import ray
    except ImportError:
        from ..extras import install_hint
        raise SpecError(f"--executor ray needs the 'ray' package: {install_hint('cluster')}") from None
    started = connect(address, {"env_vars": {"PYTHONPATH": str(Path(__file__).resolve().parents[2])}})
    refs: dict = {}
    try:
        threads = fit_ray_threads(ray.nodes(), threads, explicit, address)
        remote = ray.remote(num_cpus=max(1, threads))(run_job_process)
        refs = {remote.remote(str(root / "jobs" / f"{j.id}.json"), str(root / "clips" / j.id),
                              str(root / "logs" / f"{j.id}.log"), threads, None, device): j for j in todo}
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            for r in ready:
                try:
                    rc, err = ray.get(r)
                except Exception as exc:  # noqa: BLE001 - a lost worker node: record and go on
                    rc, err = 1, f"ray task failed: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
                on_done(refs[r], rc, err)
    except KeyboardInterrupt:  # Ctrl-C: a driver of this call's leaves the cluster below, which ends its job
        if not started:        # the caller's own session: cancel this call's tasks
            for r in refs:
                with contextlib.suppress(Exception):
                    ray.cancel(r, force=True)
        raise
    finally:
        if started:
            ray.shutdown()


def check_clip_resources(jobs, root: Path, spec_path) -> None:
    """Refuse, before anything starts, render settings of which one clip alone exceeds the free disk under
    ``root`` (``frames = 1000000``, say): ResourceError naming the spec. Memory is the workers' to check (a Ray
    cluster's nodes are not this machine)."""
    from ..resources import ResourceError, check_render_resources
    seen = set()
    for j in jobs:
        r = j.render
        scales = tuple(r.get("scales") or (r["scale"],))  # every LR level of the clip
        key = (tuple(r["hr_size"]), scales, tuple(r["buffers"]), r["frames"])
        if key in seen:
            continue
        seen.add(key)
        try:
            check_render_resources(tuple(r["hr_size"]), scales, r["buffers"], r["frames"], root,
                                   available=(1 << 62, None))
        except ResourceError as exc:
            raise ResourceError(f"{spec_path}: clip {j.id}: {exc}") from None


def planned_jobs(spec: DatasetSpec, opts: RunOptions = RunOptions()) -> list[ClipJob]:
    """Every clip job of ``spec`` as the run renders it (``expand``, with the buffers of ``opts.buffers_for``)."""
    jobs = expand(spec)
    if opts.buffers_for:
        from .buffers import buffers_for_models
        need = buffers_for_models(opts.buffers_for)
        jobs = [dataclasses.replace(j, render={**j.render, "buffers": list(need)}) for j in jobs]
    return jobs


#: Job keys derived from the others (what a clip holds, by the spec's family lists): an index written before them,
#: or under other held-out lists, holds the same renders.
DERIVED_JOB_KEYS = ("families", "family_group")


def check_folder(out: str | os.PathLike, spec: DatasetSpec, jobs: list[ClipJob]) -> dict | None:
    """Whether ``jobs`` of ``spec`` may be rendered into ``out``, checked before anything is written: DatasetError
    (one line naming the folder) when it is a file, holds another dataset (name or seed), or holds a clip rendered
    from different settings. Returns the folder's index (None for a new dataset)."""
    root = Path(out)
    if root.exists() and not root.is_dir():
        raise DatasetError(f"{root}: exists and is not a folder")
    if not (root / INDEX).is_file():
        return None
    old = read_index(root)
    if old.get("name") != spec.name or old.get("seed") != spec.seed:
        raise DatasetError(f"{root}: holds dataset {old.get('name')!r} (seed {old.get('seed')}); choose "
                           "another folder or delete it")
    old_jobs = {c["id"]: _legacy_render_keys(c) for c in old["clips"]}
    for j in jobs:
        o, new = old_jobs.get(j.id), {k: v for k, v in j.to_json().items() if k not in DERIVED_JOB_KEYS}
        if o is not None and {k: o.get(k) for k in new} != new and \
                (root / "clips" / j.id / "manifest.json").is_file():
            changed = sorted(k for k in new if o.get(k) != new[k])
            if changed == ["light"] and o.get("light") == "scene" and j.to_json()["light"] == "auto":
                raise DatasetError(f"{root}: clip {j.id} was rendered with light = \"scene\", before \"auto\" became "
                                   "the default; set light = \"scene\" in its [[source]] to keep these clips, or "
                                   "render the spec into another folder")
            raise DatasetError(f"{root}: clip {j.id} was rendered from a different spec ({', '.join(changed)}); "
                               "render the changed "
                               "spec into another folder")
    return old


def _legacy_render_keys(clip: dict) -> dict:
    """An index entry with the render keys added after it was written (``LEGACY_RENDER_KEYS``) set to what it was
    rendered with."""
    if isinstance(clip.get("render"), dict):
        return {**clip, "render": {**LEGACY_RENDER_KEYS, **clip["render"]}}
    return clip


def selected_jobs(jobs: list[ClipJob], opts: RunOptions) -> list[ClipJob]:
    """The jobs of ``opts.splits`` (all when empty) whose id ``opts.clips`` names (an exact id or a shell pattern,
    ``fnmatch``; all when empty). SpecError naming an entry that matches no clip of the spec, or a selection that
    keeps none (a typo would otherwise render nothing and report success); a selection whose clips are all done is
    a finished resume, not an error."""
    from fnmatch import fnmatchcase
    ids = [j.id for j in jobs]
    hint = f"blendsr dataset SPEC -o DATASET --dry-run --no-plan lists the {len(ids)} clip ids"
    for pat in opts.clips:
        if not any(fnmatchcase(i, pat) for i in ids):
            raise SpecError(f"--clips {pat!r}: names no clip of the spec ({hint})")
    kept = [j for j in jobs if (not opts.clips or any(fnmatchcase(j.id, pat) for pat in opts.clips))
            and (not opts.splits or j.split in opts.splits)]
    if not kept and jobs:
        what = "--clips and --split: no clip named is" if opts.clips else "--split: the spec has no clip"
        raise SpecError(f"{what} in split {', '.join(opts.splits)} ({hint})")
    return kept


def clips_to_render(jobs: list[ClipJob], index: dict, opts: RunOptions) -> list[ClipJob]:
    """The jobs ``selected_jobs`` keeps whose clip is not done, in ``opts.order`` (the spec's;
    ``spec.mixed_rank``'s; or the train split's in that order before the others'), the first ``opts.limit`` of
    them."""
    chosen = {j.id for j in selected_jobs(jobs, opts)}
    todo = [j for j, e in zip(jobs, index["clips"]) if e["state"] != "done" and j.id in chosen]
    if opts.order == "mixed":
        todo.sort(key=lambda j: mixed_rank(j.id))
    elif opts.order == "train-first":  # the train split in the mixed order, then val and test in it
        todo.sort(key=lambda j: (j.split != "train", mixed_rank(j.id)))
    return todo if opts.limit is None else todo[:opts.limit]


def build_dataset(spec: DatasetSpec, out: str | os.PathLike, opts: RunOptions = RunOptions()) -> dict:
    """Render every missing or partial clip of ``spec`` into ``out`` and return the final index."""
    opts.validate()
    root = Path(out)
    jobs = planned_jobs(spec, opts)
    chosen = selected_jobs(jobs, opts)  # a --clips entry that names no clip is refused before anything is written
    old = check_folder(root, spec, jobs)
    check_clip_resources(jobs, root, spec.path)
    root.mkdir(parents=True, exist_ok=True)
    lock = FolderLock(root, "another 'blendsr dataset' is running on this folder")
    try:
        _prepare_folder(root, jobs)
        index = make_index(spec, jobs, root, old, opts)
        write_json_atomic(root / INDEX, index)
        todo = clips_to_render(jobs, index, opts)
        threads = opts.clip_threads()
        n_done = len(jobs) - len([e for e in index["clips"] if e["state"] != "done"])
        picked = f" of the {len(chosen)} --clips/--split select" if len(chosen) < len(jobs) else ""
        log.info(f"blendsr: dataset {spec.name!r}: {len(jobs)} clips, {n_done} done, {len(todo)} to render{picked} "
              f"({opts.executor}, " + (f"{opts.workers} workers, {threads} threads each)" if opts.executor == "local"
                                       else f"{threads} thread(s) and CPU(s) per task, as many tasks at once as "
                                            f"the cluster has CPUs)"))
        t0 = time.perf_counter()
        _render_todo(root, jobs, index, todo, opts)
        index["last_run"] = {"executor": opts.executor, "workers": opts.workers, "threads": threads,
                             "clips_rendered": len(todo), "seconds": round(time.perf_counter() - t0, 1),
                             **({"selection": {"clips": list(opts.clips), "splits": list(opts.splits)}}
                                if opts.clips or opts.splits else {})}
        write_json_atomic(root / INDEX, index)
        return index
    finally:
        lock.close()


def _prepare_folder(root: Path, jobs: list[ClipJob]) -> None:
    """Remove stale temporaries, refuse links out of the folder (nothing is rendered, logged or written through
    one) and write each clip's job file where it changed."""
    remove_stale_temporaries(root)
    for j in jobs:
        for sub in (f"clips/{j.id}", f"jobs/{j.id}.json", f"logs/{j.id}.log"):
            check_no_links(root, root / sub)
        jp = root / "jobs" / f"{j.id}.json"
        if not jp.is_file() or json.loads(jp.read_text()) != j.to_json():
            write_json_atomic(jp, j.to_json())


def _render_todo(root: Path, jobs: list[ClipJob], index: dict, todo: list[ClipJob], opts: RunOptions) -> None:
    """Render ``todo`` with the executor ``opts`` names, the index updated (and written) as each clip ends; on
    Ctrl-C the clip processes are stopped and the index says what is left."""
    threads = opts.clip_threads()
    bar = None
    if opts.progress and todo:
        from tqdm import tqdm
        bar = tqdm(total=len(todo), desc="dataset", unit="clip", file=sys.stderr, dynamic_ncols=True)
    on_done = _index_updater(root, index, bar)
    cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []

    def run_one(job: ClipJob, slot: int):
        cpu = cores[slot % len(cores)] if threads == 1 and cores else None  # one core per worker slot
        return run_job_process(str(root / "jobs" / f"{job.id}.json"), str(root / "clips" / job.id),
                               str(root / "logs" / f"{job.id}.log"), threads, cpu, opts.device,
                               opts.blender)
    try:
        if opts.executor == "local":
            _local_map(todo, run_one, opts.workers, on_done)
        else:
            _ray_map(todo, root, threads, opts.address, on_done, explicit=bool(opts.threads), device=opts.device)
    except KeyboardInterrupt:
        _record_states(root, jobs, index)
        raise
    finally:
        if bar is not None:
            bar.close()


def _index_updater(root: Path, index: dict, bar):
    """``on_done(job, rc, err)``: the clip's state, frames and error (a failed worker's message) and its quick check
    into ``index``, written atomically; thread-safe (the executors call it from their threads)."""
    by_id = {e["id"]: e for e in index["clips"]}
    mutex = threading.Lock()

    def on_done(job: ClipJob, rc: int, err: str) -> None:
        with mutex:
            e = by_id[job.id]
            state, n = clip_state(root / "clips" / job.id, job.render["frames"])
            e.update(state=state if rc == 0 else ("failed" if state != "done" else state), frames_done=n)
            if rc != 0 and state != "done":
                e["error"] = err or f"worker exited with code {rc}"
            else:
                e.pop("error", None)
            e.pop("invalid", None)
            problem = quick_check(root / "clips" / job.id) if e["state"] == "done" else ""
            if problem:
                e["invalid"] = problem
            write_json_atomic(root / INDEX, index)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(last=job.id[-24:], failed=sum(c["state"] == "failed" for c in index["clips"]))
    return on_done


def _record_states(root: Path, jobs: list[ClipJob], index: dict) -> None:
    """After an interrupted run: each clip's state and finished frames as its folder has them, in the index
    (another Ctrl-C meanwhile leaves the previous index, which the next run recomputes anyway)."""
    by_id = {e["id"]: e for e in index["clips"]}
    for j in jobs:
        state, n = clip_state(root / "clips" / j.id, j.render["frames"])
        e = by_id[j.id]
        if e["state"] != "failed" or state == "done":
            e.update(state=state, frames_done=n)
    write_json_atomic(root / INDEX, index)


def remove_stale_temporaries(root: Path) -> None:
    """The temporary files of an earlier coordinator that was killed or met a full disk while writing the index
    or a job (``.NAME.tmpPID``; ``write_json_atomic``): removed, this run holding the folder's lock."""
    for folder in (root, root / "jobs"):
        if not folder.is_dir() or folder.is_symlink():
            continue
        for tmp in folder.glob(".*.json.tmp*"):
            if tmp.name.rsplit(".tmp", 1)[1].isdigit() and (tmp.is_file() or tmp.is_symlink()):
                with contextlib.suppress(FileNotFoundError):
                    tmp.unlink()


def summary(index: dict) -> str:
    """One line: clips per state (and how many finished ones failed their quick check) and per split."""
    states = {s: sum(c["state"] == s for c in index["clips"]) for s in STATES}
    splits = {s: len(v) for s, v in index["splits"].items()}
    invalid = sum(bool(c.get("invalid")) for c in index["clips"])
    return (f"{len(index['clips'])} clips: " + ", ".join(f"{v} {k}" for k, v in states.items() if v)
            + (f" ({invalid} invalid)" if invalid else "")
            + " | splits: " + ", ".join(f"{k} {v}" for k, v in splits.items()))
