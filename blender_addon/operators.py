"""``blendsr.export_dataset`` and ``blendsr.preview_upscale``.

Both render through a worker process (``jobs.RenderJob`` running ``worker.py``, which calls the library's
``render_clip``), never in the user's session: the renderer changes the scene it renders (render settings, AOV
nodes, pass indices). In the Blender application the operators are modal: a timer polls the worker, the status bar
shows the frames done, Esc kills the worker (finished frames stay; running it again resumes). In the bpy module
(no event loop: timers never fire, ``bpy.app.binary_path`` is empty) and in background mode they wait for the
worker.
"""
from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import bpy

from . import images, jobs, library, mapping, render_keys
from .prefs import Prefs
from .props import store_preview_results

#: Running jobs by kind ("export", "preview"); one of each at a time. Read by the panels for their progress line.
ACTIVE: dict[str, jobs.RenderJob] = {}

EXTERNAL_INFER = Path(__file__).with_name("external_infer.py")
#: The ONNX graphs of the shipped networks and non-learned models (``python -m blender_addon.build`` puts them in).
GRAPHS_DIR = Path(__file__).with_name("onnx")


def interactive() -> bool:
    """True in the Blender application with a UI (modal operators and timers work)."""
    return bool(bpy.app.binary_path) and not bpy.app.background


def scene_file_for_job(job_dir: Path) -> Path:
    """The .blend the preview's worker opens: the saved file itself when it has no unsaved changes, else a copy of
    the current state (``save_scene_copy``) named like the file, in ``job_dir``."""
    if bpy.data.filepath and not bpy.data.is_dirty:
        return Path(bpy.data.filepath)
    name = Path(bpy.data.filepath).name if bpy.data.filepath else "untitled.blend"
    path = Path(job_dir) / name
    save_scene_copy(path)
    return path


#: Inside a clip's folder (a dot folder: the clip writer and validation leave it alone): the .blend the export's
#: worker opens and its fingerprint.
CLIP_SCENE_DIR = ".blendsr_scene"


def scene_file_for_clip(scene, output: Path, job_dir: Path) -> Path:
    """The .blend a clip export renders: ``OUTPUT/.blendsr_scene/<name>.blend``, a copy of the open scene kept with
    its ``scene_fingerprint``. While the fingerprint is the same, the copy is reused (same file, same sha256 in the
    clip's manifest: the export resumes after changes that do not affect the render, e.g. the selection or a save).
    A different fingerprint replaces the copy before the clip has a manifest, and is refused (ClipError naming the
    folder, the copy kept) once it has one."""
    import json

    from gbuffer_export.clip import MANIFEST, ClipError
    name = Path(bpy.data.filepath).name if bpy.data.filepath else "untitled.blend"
    dest = Path(output) / CLIP_SCENE_DIR / name
    meta = dest.with_suffix(".json")
    fingerprint = scene_fingerprint(scene)
    try:
        same = dest.is_file() and json.loads(meta.read_text()).get("fingerprint") == fingerprint
    except (OSError, ValueError, AttributeError):
        same = False
    if same:
        return dest
    if dest.is_file() and (Path(output) / MANIFEST).is_file():
        raise ClipError(f"{output}: the open scene differs from the copy this clip was rendered from "
                        f"({CLIP_SCENE_DIR}/{name}: moved, added or edited objects, materials, lights or camera); "
                        "choose another output folder, or delete the clip to start again")
    return publish_scene_copy(dest, Path(job_dir), fingerprint)


def publish_scene_copy(dest: Path, job_dir: Path, fingerprint: str) -> Path:
    """Save the open scene to ``job_dir``, then move it to ``dest`` atomically (a sibling ``.part`` file renamed),
    with ``dest``'s ``.json`` holding its fingerprint and the file it came from; returns ``dest``."""
    from gbuffer_export.clip import write_json_atomic
    tmp = job_dir / dest.name
    save_scene_copy(tmp)
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = dest.with_name(f".{dest.name}.part{os.getpid()}")
    shutil.copyfile(tmp, part)
    os.replace(part, dest)
    write_json_atomic(dest.with_suffix(".json"), {"fingerprint": fingerprint, "source": bpy.data.filepath or None})
    return dest


def _values(v):
    """A property value as plain, rounded Python (floats to 5 decimals; arrays as tuples; IDs by name)."""
    if isinstance(v, float):
        return round(v, 5)
    if isinstance(v, (bool, int, str)) or v is None:
        return v
    if hasattr(v, "name") and hasattr(v, "rna_type"):  # an ID (image, object, ...)
        return v.name
    try:
        return tuple(_values(x) for x in v)
    except TypeError:
        return repr(type(v).__name__)


def _tree_signature(tree) -> tuple:
    """What a node tree renders: each node's type, name, input values and image, and the links."""
    if tree is None:
        return ()
    nodes = []
    for n in sorted(tree.nodes, key=lambda n: n.name):
        inputs = tuple(_values(getattr(s, "default_value", None)) for s in n.inputs)
        extra = tuple(_values(getattr(n, a)) for a in ("image", "node_tree", "operation", "blend_type", "data_type")
                      if hasattr(n, a))
        nodes.append((n.bl_idname, n.name, inputs, extra, n.mute))
    links = sorted((lk.from_node.name, lk.from_socket.identifier, lk.to_node.name, lk.to_socket.identifier)
                   for lk in tree.links)
    return tuple(nodes), tuple(links)


def _action_signature(action) -> tuple:
    """An action's keys: every F-curve's data path, index and keyframes (layered actions of Blender 4.4+ and the
    older flat ones)."""
    if action is None:
        return ()
    curves = list(getattr(action, "fcurves", None) or [])
    for layer in getattr(action, "layers", ()):
        for strip in layer.strips:
            for bag in getattr(strip, "channelbags", ()):
                curves += list(bag.fcurves)
    return tuple((fc.data_path, fc.array_index, tuple(_values((k.co, k.handle_left, k.handle_right, k.interpolation))
                                                      for k in fc.keyframe_points)) for fc in curves)


TRANSFORM_CHANNELS = ("location", "rotation_euler", "rotation_quaternion", "scale")


def _moves(ob) -> bool:
    """Whether the object's world matrix depends on the frame: it, or an object it hangs from, is animated or
    constrained."""
    while ob is not None:
        if (ob.animation_data and ob.animation_data.action) or len(ob.constraints):
            return True
        ob = ob.parent
    return False


def scene_fingerprint(scene) -> str:
    """sha256 of what a render of ``scene`` depends on, as far as cheaply read: the frame range, fps, unit scale,
    colour management, the world and its nodes; every object's name, type, visibility in renders, world matrix,
    modifiers, material slots (their node trees' values and links) and animation; mesh vertex positions and face
    counts; lamps' type, energy and colour; cameras' lens, sensor and clipping. Not the selection, the active
    object, the UI or anything else a render does not read. A saved .blend cannot be compared byte for byte: it
    stores memory addresses, different in every Blender session."""
    import hashlib

    import numpy as np
    h = hashlib.sha256()
    r, vs = scene.render, scene.view_settings
    h.update(repr((scene.frame_start, scene.frame_end, r.fps, r.fps_base, scene.unit_settings.scale_length,
                   scene.world.name if scene.world else None, scene.camera.name if scene.camera else None,
                   vs.view_transform, vs.look, round(vs.exposure, 5), round(vs.gamma, 5),
                   scene.display_settings.display_device, r.film_transparent)).encode())
    if scene.world is not None:
        h.update(repr(_tree_signature(scene.world.node_tree)).encode())
    materials = {}
    for ob in sorted(scene.objects, key=lambda o: o.name):
        action = ob.animation_data.action if ob.animation_data else None
        keys = _action_signature(action)
        act = (ob.parent.name if ob.parent else None, [c.type for c in ob.constraints], keys)
        if _moves(ob):  # its matrix at the current frame changes with the frame: its keys and unkeyed channels
            keyed = {(k[0], k[1]) for k in keys}
            m = np.array([round(v, 5) for attr in TRANSFORM_CHANNELS for i, v in enumerate(getattr(ob, attr))
                          if (attr, i) not in keyed])
        else:
            m = np.round(np.array(ob.matrix_world, dtype=np.float64), 5)
        slots = [sl.material.name if sl.material else None for sl in ob.material_slots]
        materials.update({sl.material.name: sl.material for sl in ob.material_slots if sl.material})
        h.update(repr((ob.name, ob.type, ob.hide_render, m.tobytes().hex(), act, slots,
                       [(md.type, md.show_render) for md in ob.modifiers])).encode())
        data = ob.data
        if ob.type == "MESH" and data is not None:
            co = np.empty(len(data.vertices) * 3, dtype=np.float32)
            data.vertices.foreach_get("co", co)
            h.update(np.round(co, 5).tobytes() + repr(len(data.polygons)).encode())
        elif ob.type == "LIGHT" and data is not None:
            h.update(repr((data.type, round(data.energy, 5), tuple(round(c, 5) for c in data.color))).encode())
        elif ob.type == "CAMERA" and data is not None:
            h.update(repr(_values((data.type, data.lens, data.sensor_width, data.sensor_height, data.clip_start,
                                   data.clip_end, data.shift_x, data.shift_y))).encode())
    for name in sorted(materials):
        mat = materials[name]
        h.update(repr((name, _tree_signature(mat.node_tree) if mat.node_tree else _values(mat.diffuse_color)))
                 .encode())
    return h.hexdigest()


def save_scene_copy(path: Path) -> None:
    """Write the current state to ``path`` with ``save_as_mainfile(copy=True)`` (relative paths remapped),
    without a thumbnail so that equal states give equal files and the renderer can resume."""
    prefs = bpy.context.preferences
    fp = prefs.filepaths
    old_preview, old_dirty = getattr(fp, "file_preview_type", None), prefs.is_dirty
    try:
        if old_preview is not None:
            fp.file_preview_type = "NONE"
        bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True, check_existing=False)
    finally:
        if old_preview is not None:
            fp.file_preview_type = old_preview
            prefs.is_dirty = old_dirty


def _tag_redraw() -> None:
    wm = bpy.context.window_manager
    for win in getattr(wm, "windows", []):
        for area in win.screen.areas:
            if area.type in ("PROPERTIES", "VIEW_3D"):
                area.tag_redraw()


def _set_status(context, text: str | None) -> None:
    ws = getattr(context, "workspace", None)
    if ws is not None and interactive():
        ws.status_text_set(text)


class _JobOperator:
    """Runs ``self.start(context) -> RenderJob`` then ``self.finish(context, job)``: modal in the application,
    synchronous otherwise."""

    job_key = ""
    label = ""

    @classmethod
    def poll(cls, context):
        return context.scene is not None and cls.job_key not in ACTIVE

    def execute(self, context):
        job = self._start(context)
        if job is None:
            return {"CANCELLED"}
        try:
            job.wait()
        except BaseException:
            job.cancel()
            ACTIVE.pop(self.job_key, None)
            raise
        return self._finish(context, job)

    def invoke(self, context, event):
        if not interactive() or context.window is None:
            return self.execute(context)
        job = self._start(context)
        if job is None:
            return {"CANCELLED"}
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.5, window=context.window)
        wm.modal_handler_add(self)
        _set_status(context, f"BlendSR {self.label}: starting (Esc cancels)")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = ACTIVE.get(self.job_key)
        if job is None:
            self._stop_timer(context)
            return {"CANCELLED"}
        if event.type == "ESC" and event.value == "PRESS":
            job.cancel()
            self._stop_timer(context)
            done, total, _ = job.progress()
            ACTIVE.pop(self.job_key, None)
            job.result()
            shutil.rmtree(job.job_dir, ignore_errors=True)
            self.report({"WARNING"}, f"BlendSR {self.label} cancelled: {done}/{total} frames done; "
                                     "run it again to resume")
            _tag_redraw()
            return {"CANCELLED"}
        if event.type == "TIMER":
            if job.poll() is None:
                _set_status(context, f"BlendSR {self.label}: {job.status_line()}")
                _tag_redraw()
                return {"PASS_THROUGH"}
            self._stop_timer(context)
            return self._finish(context, job)
        return {"PASS_THROUGH"}

    def _stop_timer(self, context) -> None:
        timer = getattr(self, "_timer", None)
        if timer is not None:
            context.window_manager.event_timer_remove(timer)
            self._timer = None
        _set_status(context, None)

    def _start(self, context):
        st = library.status(Prefs(context).library_path)
        if not st.ok:
            self.report({"ERROR"}, f"{st.message}; see the BlendSR panel for how to install it")
            return None
        try:
            job = self.start(context, st)
        except Exception as exc:  # bad settings or files: one line in the report area, never a traceback
            self.report({"ERROR"}, f"BlendSR {self.label}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}")
            return None
        if job is not None:
            ACTIVE[self.job_key] = job
        return job

    def _finish(self, context, job):
        ACTIVE.pop(self.job_key, None)
        try:
            return self.finish(context, job)
        finally:
            _tag_redraw()


class BLENDSR_OT_export_dataset(_JobOperator, bpy.types.Operator):
    bl_idname = "blendsr.export_dataset"
    bl_label = "Export Dataset"
    bl_description = ("Render the clip with these settings in a background process and validate it "
                      "(Esc cancels; running it again resumes)")
    bl_options = {"REGISTER"}
    job_key = "export"
    label = "export"

    def start(self, context, st):
        scene = context.scene
        cfg = mapping.render_config(scene.blendsr, scene)
        job_dir = jobs.new_job_dir("blendsr-export-")
        cfg = dataclasses.replace(cfg, scene=scene_file_for_clip(scene, cfg.output, job_dir))
        a, b = cfg.frames
        return jobs.RenderJob(cfg.to_json(), list(range(a, b + 1)), job_dir=job_dir,
                              library_paths=library.worker_paths(st), validate="quick",
                              blender_binary=bpy.app.binary_path)

    def finish(self, context, job):
        res = job.result()
        settings = context.scene.blendsr
        if not res.ok:
            settings["_last_export"] = f"failed: {res.error}"
            self.report({"ERROR"}, f"BlendSR export failed: {res.error} (log: {job.log_file})")
            return {"CANCELLED"}
        shutil.rmtree(job.job_dir, ignore_errors=True)
        text = f"{res.output}: {len(job.frames)} frames in {jobs.format_seconds(res.seconds)}; {res.validation}"
        settings["_last_export"] = text
        self.report({"INFO"} if res.valid is not False else {"WARNING"}, f"BlendSR export: {text}")
        return {"FINISHED"}


def preview_dir() -> Path:
    """Folder of the preview's one-frame clip (inside Blender's session temporary folder)."""
    return Path(bpy.app.tempdir or tempfile.gettempdir()) / "blendsr_preview"


def model_spec(settings) -> str:
    """The checkpoint path when one is chosen, else the non-learned model's name."""
    if settings.checkpoint.strip():
        path = bpy.path.abspath(settings.checkpoint.strip())
        if not os.path.isfile(path):
            raise ValueError(f"checkpoint {path}: file not found")
        return path
    return settings.preview_model


def onnx_graph(st: library.LibraryStatus, spec: str, scale: int) -> str:
    """The zip's ONNX graph folder when ONNX Runtime imports and it holds ``spec``'s graph for ``scale``, else ''."""
    if not (st.onnxruntime and GRAPHS_DIR.is_dir()):
        return ""
    from training.inference.onnx_infer import find_graph
    return str(GRAPHS_DIR) if find_graph(GRAPHS_DIR, spec, scale) is not None else ""


def inference_runner(st: library.LibraryStatus, prefs: Prefs, spec: str = "", scale: int = 4) -> tuple[str, str]:
    """(kind, where): ('torch', '') in Blender's Python, ('onnx', graphs folder) through ONNX Runtime in Blender's
    Python, ('external', the external Python's path); ValueError saying what to install or set. Automatic: torch
    when it imports here, else ONNX Runtime when the zip has the model's graph, else the external Python."""
    internal_ok = st.torch and st.training
    onnx = onnx_graph(st, spec, scale) if spec else ""
    if prefs.inference == "ONNX":
        if not onnx:
            raise ValueError(f"ONNX Runtime cannot run {os.path.basename(spec)} at scale {scale}: "
                             + ("no ONNX graph of it in the extension (checkpoints need torch)" if st.onnxruntime
                                else "onnxruntime is not importable from Blender's Python (reinstall the zip)"))
        return "onnx", onnx
    if prefs.inference == "INTERNAL" or (prefs.inference == "AUTO" and internal_ok):
        if not internal_ok:
            raise ValueError("torch (or the training package) is not importable from Blender's Python; install "
                             "blendsr[train] there or choose the external Python in the add-on preferences")
        return "torch", ""
    if prefs.inference == "AUTO" and onnx:
        return "onnx", onnx
    py = bpy.path.abspath(prefs.python_path.strip()) if prefs.python_path.strip() else ""
    if not py:
        raise ValueError("torch is not importable from Blender's Python and the extension has no ONNX graph of "
                         f"{os.path.basename(spec) or 'the model'}: install torch there, or set 'External Python' in "
                         "the add-on preferences to a Python with torch and blendsr[train]")
    if not os.path.isfile(py):
        raise ValueError(f"external Python {py}: file not found")
    return "external", py


class BLENDSR_OT_preview_upscale(_JobOperator, bpy.types.Operator):
    bl_idname = "blendsr.preview_upscale"
    bl_label = "Preview Upscaling"
    bl_description = ("Render the current frame's LR radiance and HR G-buffers (and the reference when asked), "
                      "upscale it with the chosen model and show the images 'BlendSR SR', 'BlendSR bilinear' "
                      "and 'BlendSR reference'")
    bl_options = {"REGISTER"}
    job_key = "preview"
    label = "preview"

    def start(self, context, st):
        scene = context.scene
        settings = scene.blendsr
        prefs = Prefs(context)
        self.spec = model_spec(settings)
        problem = mapping.preview_scale(settings)[1]
        if problem:
            raise ValueError(f"{problem}: set Scale to it, or choose a model that takes any scale")
        self.runner, self.where = inference_runner(st, prefs, self.spec, int(settings.scale))
        self.status = st
        self.with_reference = bool(settings.with_reference)
        frame = scene.frame_current
        root = preview_dir()
        clip_dir = root / "clip"
        cfg = mapping.render_config(settings, scene, output=clip_dir)
        a, b = cfg.frames
        # Only `frame` of the export's range: the export's generated camera path and jitter index for it.
        frames = (a, b) if a <= frame <= b else (frame, frame)
        hr = {} if self.with_reference else {"hr_spp": 1, "hr_denoise": False, "adaptive": False}
        if clip_dir.exists():
            shutil.rmtree(clip_dir)
        root.mkdir(parents=True, exist_ok=True)
        job_dir = Path(tempfile.mkdtemp(prefix="job-", dir=root))
        from gbuffer_export.conventions import ALL_BUFFERS  # one frame: every buffer, so any shipped model runs
        cfg = dataclasses.replace(cfg, scene=scene_file_for_job(job_dir), frames=frames,
                                  only_frames=(frame,), buffers=ALL_BUFFERS, **hr)
        self.frame = frame
        return jobs.RenderJob(cfg.to_json(), [frame], job_dir=job_dir, library_paths=library.worker_paths(st),
                              validate="", blender_binary=bpy.app.binary_path)

    def finish(self, context, job):
        res = job.result()
        if not res.ok:
            self.report({"ERROR"}, f"BlendSR preview failed: {res.error} (log: {job.log_file})")
            return {"CANCELLED"}
        shutil.rmtree(job.job_dir, ignore_errors=True)
        clip_dir = str(job.output)
        try:
            out = self.infer(clip_dir, job.job_dir.parent / "inference")
        except Exception as exc:  # the model or the external process failed: say so, keep Blender running
            self.report({"ERROR"}, f"BlendSR preview inference failed: {str(exc).splitlines()[0]}")
            return {"CANCELLED"}
        sr = images.set_image(images.SR_IMAGE, out["sr"])
        images.set_image(images.BILINEAR_IMAGE, out["bilinear"])
        if "reference" in out:
            images.set_image(images.REFERENCE_IMAGE, out["reference"])
        elif images.REFERENCE_IMAGE in bpy.data.images:
            bpy.data.images.remove(bpy.data.images[images.REFERENCE_IMAGE])  # a stale one would mislead
        images.show_in_image_editors(sr, context)
        h, w = out["sr"].shape[:2]
        name = os.path.basename(self.spec)
        info = f"frame {self.frame}, {name}, {w}x{h}"
        psnr = out.get("psnr")
        runtime = out.get("runtime", "")
        store_preview_results(context.scene.blendsr, ms=out["ms"], psnr=psnr, metric=out.get("metric", ""),
                              info=info, clip=clip_dir, warmup_ms=out.get("warmup_ms", 0.0), runtime=runtime)
        path = (out.get("inference") or {}).get("path")  # training.inference.fastpath: the inference path that ran
        msg = (f"BlendSR preview: {info}, {runtime}" + (f" ({path} path)" if path else "")
               + f": {out['ms']:.1f} ms per frame (median of {out.get('repeats', 1)}), "
               f"warm-up {out.get('warmup_ms', 0.0):.0f} ms")
        if psnr is not None:
            msg += f", PSNR {psnr:.2f} dB"
        self.report({"INFO"}, msg)
        return {"FINISHED"}

    def infer(self, clip_dir: str, out_dir: Path) -> dict:
        """Run the model on the preview clip: in Blender's Python (torch or ONNX Runtime), or with the external
        Python."""
        from . import external_infer
        if self.runner == "torch":
            return external_infer.run_inference(clip_dir, self.frame, self.spec, self.with_reference)
        if self.runner == "onnx":
            return external_infer.run_onnx_inference(clip_dir, self.frame, self.spec, self.with_reference, self.where)
        return run_external_inference(self.where, clip_dir, self.frame, self.spec, self.with_reference,
                                      self.status, out_dir)


def run_external_inference(python: str, clip_dir: str, frame: int, spec: str, with_reference: bool,
                           st: library.LibraryStatus, out_dir: Path, timeout_s: float = 600.0) -> dict:
    """``external_infer.py`` with another Python; reads back its EXRs and result.json (same keys as
    ``external_infer.run_inference``)."""
    import json

    from gbuffer_export.exr import read_exr
    if out_dir.exists():
        shutil.rmtree(out_dir)
    cmd = [python, str(EXTERNAL_INFER), "--clip", clip_dir, "--frame", str(frame), "--model", spec,
           "--out", str(out_dir)]
    if with_reference:
        cmd.append("--reference")
    if st.root and Path(st.root).name not in ("site-packages", "dist-packages"):
        cmd += ["--sys-path", st.root]  # a source checkout; an installed library is the external Python's own
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, stdin=subprocess.DEVNULL)
    try:
        r = json.loads((out_dir / "result.json").read_text())
    except (OSError, json.JSONDecodeError):
        tail = (proc.stderr or proc.stdout).strip().splitlines()
        raise RuntimeError(f"{python} exited {proc.returncode}: {tail[-1] if tail else 'no output'}") from None
    if not r.get("ok"):
        raise RuntimeError(r.get("error", "external inference failed"))
    out = {"sr": read_exr(out_dir / "sr.exr", ("R", "G", "B")),
           "bilinear": read_exr(out_dir / "bilinear.exr", ("R", "G", "B")), "ms": float(r["ms"]),
           "warmup_ms": float(r.get("warmup_ms", 0.0)), "repeats": int(r.get("repeats", 1)),
           "runtime": f"{r.get('runtime', 'torch')} in {python}", "inference": r.get("inference")}
    if with_reference and (out_dir / "reference.exr").is_file():
        out["reference"] = read_exr(out_dir / "reference.exr", ("R", "G", "B"))
        if r.get("psnr") is not None:
            out["psnr"] = float(r["psnr"])
            out["metric"] = r.get("metric", "")
    return out

class BLENDSR_OT_create_camera_paths(bpy.types.Operator):
    """Key the library's generated walk/fly paths (``scene_setup.make_level_camera``) as animated cameras named
    "BlendSR <kind> NN", one per clip, so that they can be seen and edited before rendering (camera_path
    "scene:NAME" renders from one)."""
    bl_idname = "blendsr.create_camera_paths"
    bl_label = "Create camera paths"
    bl_options = {"REGISTER", "UNDO"}

    kinds: bpy.props.EnumProperty(name="Kinds", options={"ENUM_FLAG"}, default={"walk", "fly"},
                                  items=tuple((k, k.capitalize(), f"A generated {k} path") for k in
                                              render_keys.CHOICES["level_camera_paths"]),
                                  description="Path kinds, cycling over the clips")
    clips: bpy.props.IntProperty(name="Clips", default=2, min=1, max=64)
    seed: bpy.props.IntProperty(name="Seed", default=0, min=0)

    def execute(self, context):
        from gbuffer_export.blender.scene_setup import make_level_camera

        scene = context.scene
        kinds = render_keys.flag_list(self.kinds, render_keys.CHOICES["level_camera_paths"]) or ["walk"]
        old_camera = scene.camera
        frames = (scene.frame_start, scene.frame_end)
        made = []
        for i in range(self.clips):
            kind = kinds[i % len(kinds)]
            cam, _ = make_level_camera(scene, kind, frames, self.seed + i)
            name = f"BlendSR {kind} {i:02d}"
            stale = bpy.data.objects.get(name)
            if stale is not None and stale is not cam:
                bpy.data.objects.remove(stale, do_unlink=True)
            cam.name = name
            cam.data.name = name
            made.append(name)
        scene.camera = old_camera or bpy.data.objects.get(made[0])
        self.report({"INFO"}, f"created {', '.join(made)}")
        return {"FINISHED"}


OUTPUT_TARGETS = (("clip", "Clip", "The clip export's output folder"),
                  ("dataset", "Dataset", "The Dataset settings' folder"))


def target_folder(context, target: str) -> Path:
    """The clip's or the dataset's absolute folder, which must exist (ValueError saying to render first)."""
    s = context.scene.blendsr
    path = mapping.output_path(s) if target == "clip" else mapping.dataset_output(s.dataset)
    if not path.is_dir():
        what = "export the clip" if target == "clip" else "render the dataset"
        raise ValueError(f"{path}: no such folder yet; {what} first")
    return path


class BLENDSR_OT_open_output(bpy.types.Operator):
    """Open the clip's or the dataset's folder in the system's file browser"""
    bl_idname = "blendsr.open_output"
    bl_label = "Open output"
    bl_options = {"REGISTER"}

    target: bpy.props.EnumProperty(name="Target", items=OUTPUT_TARGETS, default="clip")

    def execute(self, context):
        try:
            path = target_folder(context, self.target)
        except ValueError as exc:
            self.report({"ERROR"}, f"BlendSR: {exc}")
            return {"CANCELLED"}
        return open_folder(path)


def open_folder(path: Path) -> set:
    """Open ``path`` in the system's file browser (``wm.path_open``)."""
    return bpy.ops.wm.path_open(filepath=str(path))


SHEET_IMAGE = "BlendSR contact sheet"


def make_contact_sheet(context, target: str) -> Path:
    """The clip's (``gbuffer_export.preview.contact_sheet``) or the dataset's (``dataset_sheet``) contact sheet,
    written as a PNG in Blender's temporary folder; returns its path. Library errors pass through (one line)."""
    from gbuffer_export import open_clip
    from gbuffer_export import preview
    folder = target_folder(context, target)
    out = Path(bpy.app.tempdir or tempfile.gettempdir()) / "blendsr_sheets"
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{target}-{mapping.slug(folder.name)}.png"
    if target == "clip":
        preview.contact_sheet(open_clip(folder), path)
    else:
        preview.dataset_sheet(folder, path)
    return path


def show_sheet(context, path: Path):
    """Load ``path`` as the image 'BlendSR contact sheet' (replacing the last one) and show it in the open Image
    Editors, or in a new window with one (in the Blender application)."""
    old = bpy.data.images.get(SHEET_IMAGE)
    if old is not None:
        bpy.data.images.remove(old)
    img = bpy.data.images.load(str(path), check_existing=False)
    img.name = SHEET_IMAGE
    if images.show_in_image_editors(img, context) == 0 and interactive():
        bpy.ops.wm.window_new()
        area = context.window_manager.windows[-1].screen.areas[0]
        area.type = "IMAGE_EDITOR"
        area.spaces.active.image = img
    return img


class BLENDSR_OT_contact_sheet(bpy.types.Operator):
    """Make the clip's or the dataset's contact sheet (every buffer of a few frames; a dataset's clips) and show it
    in the Image Editor"""
    bl_idname = "blendsr.contact_sheet"
    bl_label = "Contact sheet"
    bl_options = {"REGISTER"}

    target: bpy.props.EnumProperty(name="Target", items=OUTPUT_TARGETS, default="clip")

    def execute(self, context):
        st = library.status(Prefs(context).library_path)
        if not st.ok:
            self.report({"ERROR"}, f"{st.message}; see the BlendSR panel for how to install it")
            return {"CANCELLED"}
        try:
            path = make_contact_sheet(context, self.target)
        except Exception as exc:  # no clip yet, a broken folder: one line, never a traceback
            self.report({"ERROR"}, f"BlendSR contact sheet: {str(exc).splitlines()[0] if str(exc) else exc!r}")
            return {"CANCELLED"}
        img = show_sheet(context, path)
        self.report({"INFO"}, f"BlendSR contact sheet: {path} ({img.size[0]}x{img.size[1]})")
        return {"FINISHED"}


CLASSES = (BLENDSR_OT_export_dataset, BLENDSR_OT_preview_upscale, BLENDSR_OT_create_camera_paths,
           BLENDSR_OT_open_output, BLENDSR_OT_contact_sheet)


def register() -> None:
    for c in CLASSES:
        bpy.utils.register_class(c)


def unregister() -> None:
    for key, job in list(ACTIVE.items()):
        job.cancel()
        ACTIVE.pop(key, None)
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)
