"""Render one clip of a dataset (bpy layer): build its scene from the job (built-in seed, or asset in a generated
environment) and hand it to ``render.render_loaded_scene``. Run as a process of its own::

    python -m gbuffer_export.blender.dataset_job JOB.json CLIP_DIR [--threads N]

(one clip per process: Blender's state does not leak from one clip into the next, and a crash loses one clip's
frames in flight only). Rerunning it resumes the clip.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from ..config import RenderConfig
from ..dataset.spec import LEGACY_RENDER_KEYS, RENDER_DEFAULTS, RENDER_KEYS, ClipJob


def render_config(job: ClipJob, clip_dir: Path, threads: int = 0, progress: bool = False,
                  device: str = "auto") -> RenderConfig:
    """The clip's render configuration: the job's render keys (``RENDER_KEYS``, those written before a key read as
    ``LEGACY_RENDER_KEYS``) as ``RenderConfig`` keys; a ``kind = "scene"`` job renders its file as it is
    (``render_clip``)."""
    r = {**LEGACY_RENDER_KEYS, **job.render}  # a job written before a key renders as it did then
    scene_kw = {}
    if job.kind == "scene":
        scene_kw = dict(scene=Path(job.asset), camera_path=job.camera, light=job.light or RENDER_DEFAULTS["light"],
                        extra={"region": job.region, "camera_index": job.camera_index or 0,
                               "variation": job.variation})
    keys = {k: tuple(v) if isinstance(v, list) else v for k, v in r.items() if k in RENDER_KEYS[1:]}
    keys.update(hr_size=tuple(r["hr_size"]), scales=tuple(r["scales"]) if r["scales"] else None,
                threads=int(r.get("threads") or threads))
    return RenderConfig(output=clip_dir, **{"scene": None, "camera_path": "scene", **scene_kw},
                        frames=(1, int(r["frames"])), device=device, seed=int(job.seed), progress=progress, **keys)


def render_job(job: ClipJob, clip_dir: Path, threads: int = 0, progress: bool = False, device: str = "auto") -> Path:
    """Render (or resume) ``job`` into ``clip_dir``."""
    from .render import render_clip, render_loaded_scene
    cfg = render_config(job, Path(clip_dir), threads, progress, device)
    if job.kind == "scene":
        return render_clip(cfg, {"dataset_clip": job.id, "licence": job.licence, "region": job.region,
                                 "scene_id": job.scene_id, "families": job.families,
                                 "family_group": job.family_group})
    frames = cfg.frames
    world = {"hdri": job.hdri, "rotation_deg": job.hdri_rotation_deg, "strength": job.hdri_strength}
    if job.kind == "builtin":
        from .default_scene import LEFT_OUT, build_default_scene
        scene = build_default_scene(seed=job.seed, frames=(1, max(frames[1], 48)), resolution=cfg.hr_size,
                                    world=world, sun=job.sun, props=tuple(job.props or ()), shown=tuple(frames))
        info = {"file": None, "sha256": None, "builtin": "default", "seed": job.seed, "camera_path": job.camera,
                "hdri": job.hdri, "hdri_rotation_deg": job.hdri_rotation_deg, "hdri_strength": job.hdri_strength,
                "props": list(job.props or ()),
                # only when a family found no room for something it drew: other clips keep their identity
                **({"left_out": list(scene[LEFT_OUT])} if scene.get(LEFT_OUT) else {})}
        if job.camera in ("orbit", "walk"):
            from .camera_paths import make_camera_path
            make_camera_path(scene, job.camera, frames, job.seed)
    else:
        from .assets import build_asset_scene
        from .render import file_sha256
        scene, extra = build_asset_scene(job, frames=frames, resolution=cfg.hr_size)
        info = {"file": Path(job.asset).name, "sha256": file_sha256(Path(job.asset)), "builtin": None, **extra}
    info["dataset_clip"] = job.id
    info["licence"] = job.licence
    info["families"], info["family_group"] = job.families, job.family_group  # docs/dataset.md, "Held-out families"
    return render_loaded_scene(cfg, scene, info)


def prepare_process(threads: int) -> None:
    """Before bpy is imported (``gbuffer_export.reproducible``): with one thread, pin this worker to the core of its
    executor slot ($BLENDSR_CPU) so that Blender builds the scene on one thread; then re-execute once without address
    randomisation and with a fixed string-hash seed. The same job rendered again into the same path then gives
    bit-identical EXRs (a resumed clip's frames are another noise realisation of the same images)."""
    from ..reproducible import MALLOC_TUNING, reexec_with_fixed_layout
    cpu = os.environ.get("BLENDSR_CPU")
    if threads == 1 and cpu is not None and hasattr(os, "sched_setaffinity"):
        try:
            os.sched_setaffinity(0, {int(cpu)})
        except (OSError, ValueError):
            pass
    reexec_with_fixed_layout(drop_env=MALLOC_TUNING if threads == 1 else ())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="render one dataset clip (used by 'blendsr dataset')")
    p.add_argument("job", type=Path, help="JSON file holding one ClipJob")
    p.add_argument("clip_dir", type=Path)
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--progress", action="store_true")
    p.add_argument("--device", default="auto")
    a = p.parse_args(argv)
    from ..logs import configure_logging
    configure_logging(0)  # the library's notes into the clip's log (the process's stderr)
    if argv is None:
        prepare_process(a.threads)
    job = ClipJob.from_json(json.loads(a.job.read_text()))
    from ..interrupt import stop_on_sigint
    try:
        with stop_on_sigint():
            render_job(job, a.clip_dir, a.threads, a.progress, a.device)
    except KeyboardInterrupt:  # Ctrl-C: the render stopped between passes; finished frames stay
        print(f"blendsr: {job.id}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the worker's error boundary, as the CLI's (gbuffer_export.errors)
        from ..errors import EXIT_INTERNAL, bad_input_line, first_line
        line = bad_input_line(exc)
        if line is None:
            import traceback
            traceback.print_exc()
            print(f"blendsr: internal error (a bug, please report it with the traceback above): {job.id}: "
                  f"{type(exc).__name__}: {first_line(exc)}", file=sys.stderr)
            return EXIT_INTERNAL
        print(f"blendsr: error: {job.id}: {line}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
