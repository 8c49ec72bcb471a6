"""Worker script of the add-on's render jobs, run in a separate process so that the renderer never touches the
user's open scene.

    blender --background --factory-startup --python worker.py -- JOB.json   (inside the Blender application)
    python worker.py JOB.json                                             (Python with bpy as a module)

JOB.json: ``config`` (``RenderConfig.to_json()``) or ``dataset`` (``spec``: the dataset's spec.toml, ``output``,
``options``: ``RunOptions`` fields), ``site_dirs`` and ``sys_path`` (where the library lives), ``validate``
("quick", "full" or "") and ``result`` (path of the result JSON). The worker calls the library functions the CLI
calls: ``render_clip(RenderConfig(...))`` and ``validate_clip``, or ``build_dataset(load_spec(...))`` and
``validate_dataset``. It writes the result JSON {ok, output, error, valid, validation} and exits 0 (ok) or 2
(error). Standard library only until the paths are set.
"""
from __future__ import annotations

import json
import os
import site
import sys
import traceback

TUPLE_KEYS = ("frames", "hr_size", "shard", "only_frames", "buffers")


def config_kwargs(config: dict) -> dict:
    """``RenderConfig.to_json()`` read back from JSON -> keyword arguments of ``RenderConfig``."""
    kw = dict(config)
    for k in TUPLE_KEYS:
        if kw.get(k) is not None:
            kw[k] = tuple(kw[k])
    return kw


def _write_json(path: str, obj: dict) -> None:
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1)
    os.replace(tmp, path)


def drop_script_dir() -> None:
    """Remove this script's folder from ``sys.path`` (it holds add-on modules whose names could shadow others)."""
    here = os.path.dirname(os.path.abspath(__file__))
    sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != here]


def add_paths(job: dict) -> None:
    """Put the library on ``sys.path`` as the add-on found it, and hand the same folders to the processes this
    one starts (``$BLENDSR_SITE_DIRS`` for Blender-run dataset clips, ``$PYTHONPATH`` for Python-run ones)."""
    for d in job.get("site_dirs", []):
        site.addsitedir(d)
    for d in reversed(job.get("sys_path", [])):
        if d not in sys.path:
            sys.path.insert(0, d)
    dirs = [*job.get("sys_path", []), *job.get("site_dirs", [])]
    if dirs:
        os.environ["BLENDSR_SITE_DIRS"] = os.pathsep.join(dirs)
        old = os.environ.get("PYTHONPATH")
        os.environ["PYTHONPATH"] = os.pathsep.join(dirs + ([old] if old else []))


def error_line(exc: BaseException) -> str:
    """One line for the add-on: the message of bad input (a ValueError), else the exception's type and message."""
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return text if isinstance(exc, ValueError) else f"{type(exc).__name__}: {text}"


def run_dataset(job: dict) -> dict:
    """Build the dataset of ``job["dataset"]`` (resuming), then validate it; ``ok`` when every clip is done."""
    from gbuffer_export.dataset.build import RunOptions, build_dataset, summary
    from gbuffer_export.dataset.check import validate_dataset
    from gbuffer_export.dataset.spec import load_spec
    d = job["dataset"]
    opts = RunOptions(**d["options"])  # its lists become tuples (RunOptions.__post_init__)
    index = build_dataset(load_spec(d["spec"]), d["output"], opts)
    failed = [c for c in index["clips"] if c["state"] != "done"]
    result = {"ok": not failed, "output": d["output"], "summary": summary(index)}
    if failed:
        c = failed[0]
        err = str(c.get("error") or c["state"]).removeprefix("blendsr: error: ").removeprefix(f"{c['id']}: ")
        result["error"] = (f"{len(failed)} of {len(index['clips'])} clips not done; {c['id']}: {err} "
                           f"(log: {d['output']}/logs/{c['id']}.log)")
    if job.get("validate"):
        rep = validate_dataset(d["output"], quick=job["validate"] == "quick", progress=False)
        result.update(valid=bool(rep.ok), validation=rep.summary_line())
    return result


def run_job(job: dict) -> dict:
    add_paths(job)
    if "dataset" in job:
        try:
            return run_dataset(job)
        except Exception as exc:  # reported through the result file; the traceback goes to the log
            traceback.print_exc()
            return {"ok": False, "error": error_line(exc)}
    result: dict = {"ok": False}
    try:
        from gbuffer_export.blender.render import render_clip
        from gbuffer_export.config import RenderConfig
        from gbuffer_export.logs import configure_logging
        configure_logging(0)  # the library's notes (resuming, ...) into this job's log
        out = render_clip(RenderConfig(**config_kwargs(job["config"])))
        result.update(ok=True, output=str(out))
        if job.get("validate"):
            from gbuffer_export.validate import validate_clip
            rep = validate_clip(out, quick=job["validate"] == "quick")
            result.update(valid=bool(rep.ok), validation=rep.summary_line())
    except Exception as exc:  # reported to the add-on through the result file; the traceback goes to the log
        traceback.print_exc()
        result["error"] = error_line(exc)
    return result


def main(argv: list[str]) -> int:
    drop_script_dir()
    job_path = argv[-1]
    with open(job_path) as f:
        job = json.load(f)
    result = run_job(job)
    _write_json(job["result"], result)
    sys.stdout.flush()
    sys.stderr.flush()
    return 0 if result["ok"] else 2


if __name__ == "__main__":
    code = main(sys.argv)
    if code:  # on success return normally: Blender in background mode then quits with status 0
        sys.exit(code)
