"""``blendsr.render_dataset``: a dataset of the open scene, as ``blendsr dataset DATASET/spec.toml -o DATASET``.

The operator checks the settings and the folder, saves a copy of the open scene into ``DATASET/scene/<name>.blend``
(the clip workers open a file), writes ``DATASET/spec.toml`` (a ``kind = "scene"`` source of that copy per scale)
and starts one worker process (``worker.py``) that calls ``build_dataset`` on that spec and then
``validate_dataset``. Progress, Esc and the synchronous bpy-module path are the export's (``operators._JobOperator``).
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import bpy

from . import jobs, library, mapping
from .operators import _JobOperator, publish_scene_copy, scene_fingerprint

#: What may lie in a dataset folder before its first index is written (a start that stopped early).
OWN_ENTRIES = {mapping.SPEC_FILE, mapping.SCENE_DIR, "dataset.json", "clips", "jobs", "logs", ".lock"}


def check_foreign(root: Path) -> None:
    """Refuse a non-empty folder that is neither a BlendSR dataset nor one this operator started."""
    from gbuffer_export.dataset.build import INDEX, DatasetError
    if not root.is_dir() or (root / INDEX).is_file():
        return
    other = sorted(p.name for p in root.iterdir() if p.name not in OWN_ENTRIES)
    if other:
        raise DatasetError(f"{root}: not empty and not a BlendSR dataset (holds {', '.join(other[:3])}); choose "
                           "a new or empty folder")


def place_scene_copy(root: Path, stem: str, job_dir: Path, fingerprint: str) -> Path:
    """``root/scene/<stem>.blend``: a copy of the open scene, with ``<stem>.json`` holding its fingerprint. Once a
    clip of the dataset has started, the copy stays (its clips' manifests name its sha256) and the open scene must
    have the same fingerprint (DatasetError otherwise); before, it is replaced by the current state."""
    import json

    from gbuffer_export.dataset.build import DatasetError
    dest = root / mapping.SCENE_DIR / f"{stem}.blend"
    meta = dest.with_suffix(".json")
    if dest.is_file() and any((root / "clips").glob("*/manifest.json")):
        try:
            old = json.loads(meta.read_text()).get("fingerprint")
        except (OSError, ValueError, AttributeError):
            old = None
        if old != fingerprint:
            raise DatasetError(f"{dest}: the open scene differs from the copy this dataset's clips were rendered "
                               "from; render into another folder (or delete the dataset to start again)")
        return dest
    return publish_scene_copy(dest, Path(job_dir), fingerprint)


def write_spec(spec, path: Path) -> None:
    """``DATASET/spec.toml`` (atomically), checked to read back as ``spec``."""
    from gbuffer_export.dataset.spec import load_spec
    from gbuffer_export.dataset.writer import spec_to_toml
    text = spec_to_toml(spec, header=f"Dataset {spec.name!r} of {bpy.data.filepath or 'an unsaved scene'}, "
                                     "written by the BlendSR add-on.\nRe-run or extend: blendsr dataset "
                                     f"{path.name} -o . (from this folder; docs/dataset.md)")
    part = path.with_name(f".{path.name}.part{os.getpid()}")
    part.write_text(text)
    os.replace(part, path)
    if load_spec(path) != spec:
        raise RuntimeError(f"{path}: the written spec does not read back as the panel's (a bug, please report)")


class BLENDSR_OT_render_dataset(_JobOperator, bpy.types.Operator):
    bl_idname = "blendsr.render_dataset"
    bl_label = "Render Dataset"
    bl_description = ("Render a dataset of the open scene with the Dataset settings in a background process, write "
                      "its spec.toml and validate it (Esc cancels; running it again resumes)")
    bl_options = {"REGISTER"}
    job_key = "dataset"
    label = "dataset"

    def start(self, context, st):
        from gbuffer_export.dataset.build import check_clip_resources, check_folder, planned_jobs
        ds = context.scene.blendsr.dataset
        root = mapping.dataset_output(ds)
        stem = mapping.scene_stem(bpy.data.filepath)
        spec_path = root / mapping.SPEC_FILE
        spec = mapping.dataset_spec(ds, stem, spec_path)  # every setting checked before anything is written
        opts = mapping.dataset_run_options(ds, blender=bpy.app.binary_path)
        check_folder(root, spec, [])
        check_foreign(root)
        job_dir = jobs.new_job_dir("blendsr-dataset-")
        try:
            place_scene_copy(root, stem, job_dir, scene_fingerprint(context.scene))
            planned = planned_jobs(spec, opts)
            check_folder(root, spec, planned)
            check_clip_resources(planned, root, spec_path)
            write_spec(spec, spec_path)
            payload = {"spec": str(spec_path), "output": str(root), "options": mapping.run_options_json(opts)}
            return jobs.DatasetJob(payload, {j.id: j.render["frames"] for j in planned}, job_dir=job_dir,
                                   library_paths=library.worker_paths(st), validate="quick",
                                   blender_binary=bpy.app.binary_path)
        except BaseException:
            shutil.rmtree(job_dir, ignore_errors=True)
            raise

    def finish(self, context, job):
        res = job.result()
        ds = context.scene.blendsr.dataset
        if not res.ok:
            extra = f"; {res.validation}" if res.validation else ""
            ds["_last_dataset"] = f"failed: {res.error}{extra}"
            ds["_last_dataset_ok"] = False
            log = "" if "(log: " in res.error else f" (log: {job.log_file})"
            self.report({"ERROR"}, f"BlendSR dataset failed: {res.error}{log}")
            return {"CANCELLED"}
        shutil.rmtree(job.job_dir, ignore_errors=True)
        text = f"{res.validation} ({res.summary}; {jobs.format_seconds(res.seconds)})"
        ds["_last_dataset"] = text
        ds["_last_dataset_ok"] = res.valid is True
        self.report({"INFO"} if res.valid is not False else {"WARNING"}, f"BlendSR dataset: {text}")
        return {"FINISHED"}


CLASSES = (BLENDSR_OT_render_dataset,)


register, unregister = bpy.utils.register_classes_factory(CLASSES)
