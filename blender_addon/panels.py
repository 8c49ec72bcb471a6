"""The BlendSR panel, drawn in the Properties editor's Output tab and in the 3D viewport's sidebar (tab 'BlendSR'):
the settings, what the export will write and roughly how long it takes, the export and preview buttons, and the
last preview's numbers."""
from __future__ import annotations

from pathlib import Path

import bpy

from . import estimate, jobs, library, mapping, render_keys
from .prefs import Prefs


def format_mb(mb: float) -> str:
    return f"{mb:.2f} MB" if mb < 10 else f"{mb:,.0f} MB"


def summary(context) -> tuple[list[str], str]:
    """(lines describing the export of the current settings, error message or '')."""
    scene = context.scene
    s = scene.blendsr
    error = ""
    try:
        output = mapping.output_path(s)
    except ValueError as exc:
        output, error = None, str(exc)
    try:
        cfg = mapping.render_config(s, scene, output=output if output is not None else "unset")
    except ValueError as exc:
        return [], str(exc).splitlines()[0]
    done = estimate.frames_done_in(cfg.output, cfg.frames) if output is not None else 0
    est = estimate.estimate_export(cfg, done)
    (w, h), k = cfg.hr_size, cfg.scale
    lines = [
        f"{est.buffers} buffers x {est.levels} levels x {est.frames} frames = {est.files} EXR files",
        f"HR {w}x{h}, LR {w // k}x{h // k}: at most {format_mb(est.megabytes)} (uncompressed float32)",
        f"Time: about {jobs.format_seconds(est.seconds_left)} ({est.seconds_per_frame:.1f} s/frame, "
        "rough CPU cost model)",
    ]
    if est.frames_done:
        lines.append(f"{est.frames_done} of {est.frames} frames already in the folder: export resumes")
    return lines, error


def draw_blendsr(layout, context) -> None:
    """Draw the whole panel into ``layout`` (shared by both panels)."""
    s = context.scene.blendsr
    prefs = Prefs(context)
    st = library.status(prefs.library_path)
    if not st.ok:
        box = layout.box()
        box.alert = True
        box.label(text=st.message, icon="ERROR")
        for line in st.hint:
            box.label(text=line)
    layout.prop(s, "output_dir")
    _draw_frames(layout.box(), s)
    _draw_sampling(layout.box(), s)
    box = layout.box()
    box.label(text="Camera and buffers", icon="CAMERA_DATA")
    for key in CLIP_CAMERA_KEYS:
        box.prop(s, key)
    _draw_more(layout, s, render_keys.CLIP_PANEL, CLIP_PLACED)
    _draw_summary(layout.box(), "Export summary", st, lambda: summary(context))
    _draw_job(layout, st, "export", "Exporting", "blendsr.export_dataset", "EXPORT")
    row = layout.row()
    row.enabled = st.ok
    row.operator("blendsr.create_camera_paths", icon="CAMERA_DATA")
    if s.last_export:
        layout.label(text=f"Last export: {s.last_export}")
    _draw_preview(layout.box(), s, st, prefs)


#: Where the clip settings' render keys are drawn; a key derived from RenderConfig that none of these places is drawn
#: under "More render settings" (``_draw_more``), so a new key shows up before it is given a place.
SPP_KEYS = ("hr_spp", "lr_spp", "gbuffer_spp", "hr_denoise", "lr_denoise")
CLIP_CAMERA_KEYS = ("camera_path", "light", "device", "jitter", "buffers", "fbeta_source", "hr_fbeta")
CLIP_PLACED = {*SPP_KEYS, *CLIP_CAMERA_KEYS, "adaptive", "adaptive_threshold", "adaptive_min_samples", "seed",
               "threads"}
DATASET_BUFFER_KEYS = ("jitter", "fbeta_source", "hr_fbeta", "buffers", "for_models")
DATASET_PLACED = {*SPP_KEYS, *DATASET_BUFFER_KEYS, "light", "device", "threads"}


def _draw_more(layout, s, shell: str, placed) -> None:
    """The render keys ``shell`` derives that the panel does not place (none: nothing drawn)."""
    rest = [render_keys.prop_name(k) for k in render_keys.keys(shell) if render_keys.prop_name(k) not in placed]
    if rest:
        box = layout.box()
        box.label(text="More render settings", icon="PREFERENCES")
        for key in rest:
            box.prop(s, key)


def _draw_frames(box, s) -> None:
    box.label(text="Frames and size", icon="RENDER_ANIMATION")
    for switch, keys in (("use_scene_frames", ("frame_start", "frame_end")),
                         ("use_scene_resolution", ("hr_width", "hr_height"))):
        box.prop(s, switch)
        row = box.row(align=True)
        row.active = not getattr(s, switch)
        for key in keys:
            row.prop(s, key)
    box.prop(s, "scale")


def _draw_spp(box, s) -> None:
    """Samples and denoising: the clip settings and the Dataset settings share these keys."""
    col = box.column(align=True)
    for key in SPP_KEYS[:3]:
        col.prop(s, key)
    row = box.row()
    for key in SPP_KEYS[3:]:
        row.prop(s, key)


def _draw_sampling(box, s) -> None:
    box.label(text="Sampling", icon="RENDER_STILL")
    _draw_spp(box, s)
    box.prop(s, "adaptive")
    row = box.row(align=True)
    row.active = s.adaptive
    row.prop(s, "adaptive_threshold")
    row.prop(s, "adaptive_min_samples")
    row = box.row(align=True)
    row.prop(s, "use_max_bounces")
    sub = row.row()
    sub.active = s.use_max_bounces
    sub.prop(s, "max_bounces")
    row = box.row(align=True)
    row.prop(s, "seed")
    row.prop(s, "threads")


def _draw_summary(box, title: str, st, make_lines) -> None:
    """A summary box: ``make_lines() -> (lines, first error or '')`` when the library is importable."""
    box.label(text=title, icon="INFO")
    if not st.ok:
        box.label(text="Needs the BlendSR library (see above)")
        return
    lines, error = make_lines()
    for line in lines:
        box.label(text=line)
    if error:
        row = box.row()
        row.alert = True
        row.label(text=error, icon="ERROR")


def _draw_job(layout, st, key: str, busy: str, operator: str, icon: str) -> None:
    """The running job's status line, or the big button that starts ``operator``."""
    from .operators import ACTIVE
    job = ACTIVE.get(key)
    if job is not None:
        layout.label(text=f"{busy}: {job.status_line()}", icon="TIME")
        return
    row = layout.row()
    row.enabled = st.ok
    row.scale_y = 1.4
    row.operator(operator, icon=icon)


def _draw_preview_scale(box, s, st) -> None:
    """The Scale field beside an arbitrary-scale model; a warning when a fixed-scale model cannot use Scale."""
    if not st.ok:
        return
    any_scale, problem = mapping.preview_scale(s)
    if any_scale:
        box.prop(s, "scale", text="Preview scale")
    if problem:
        col = box.column()
        col.alert = True
        col.label(text=problem, icon="ERROR")


def _draw_preview(box, s, st, prefs) -> None:
    box.label(text="Preview upscaling (current frame)", icon="IMAGE_DATA")
    box.prop(s, "checkpoint")
    row = box.row()
    row.active = not s.checkpoint.strip()
    row.prop(s, "preview_model")
    _draw_preview_scale(box, s, st)
    box.prop(s, "with_reference")
    if st.ok and not (st.torch and st.training) and prefs.inference != "EXTERNAL":
        col = box.column()
        if prefs.python_path.strip():
            col.label(text=f"torch is not in Blender's Python: inference runs with {prefs.python_path}")
        else:
            col.alert = True
            col.label(text="torch is not importable from Blender's Python.", icon="ERROR")
            col.label(text="Install blendsr[train] into it, or set 'External Python'")
            col.label(text="in Preferences > Add-ons > BlendSR to a Python with torch.")
    from .operators import ACTIVE
    pjob = ACTIVE.get("preview")
    if pjob is not None:
        box.label(text=f"Rendering preview: {pjob.status_line()}", icon="TIME")
    else:
        row = box.row()
        row.enabled = st.ok
        row.operator("blendsr.preview_upscale", icon="ZOOM_IN")
    if s.preview_info:
        col = box.column(align=True)
        col.label(text=f"Last preview: {s.preview_info}")
        col.label(text=f"Inference: {s.preview_ms:.1f} ms")
        if s.preview_metric:
            col.label(text=f"PSNR: {s.preview_psnr:.2f} dB")
            col.label(text=f"({s.preview_metric})")
        else:
            col.label(text="PSNR: no reference rendered")


def dataset_summary(context) -> tuple[list[str], str]:
    """(lines describing the dataset the Dataset settings make, the first error or '')."""
    ds = context.scene.blendsr.dataset
    stem = mapping.scene_stem(bpy.data.filepath)
    error = ""
    try:
        root = mapping.dataset_output(ds)
    except ValueError as exc:
        root, error = None, str(exc).splitlines()[0]
    try:
        spec = mapping.dataset_spec(ds, stem, (root or Path("DATASET")) / mapping.SPEC_FILE)
        mapping.dataset_run_options(ds)
    except ValueError as exc:
        return [], str(exc).splitlines()[0]
    r, src = spec.sources[0].render, spec.sources[0]
    scales = [f"{k:g}" for k in (r.scales or (r.scale,))]
    n = sum(s.clips_per_scene for s in spec.sources)
    lines = [f"{n} clips x {r.frames} frames, HR {r.hr_size[0]}x{r.hr_size[1]}, "
             f"scale{'s' if len(scales) > 1 else ''} {', '.join(scales)}",
             f"cameras {', '.join(src.cameras)} (clip k: kind k), light {src.light}"]
    if root is not None:
        lines.append(f"writes {root / mapping.SPEC_FILE}, scene/{stem}.blend, clips/")
        if (root / "dataset.json").is_file():
            lines.append("the folder holds a dataset: the render resumes or extends it")
    return lines, error


def draw_dataset(layout, context) -> None:
    """The Dataset subpanel: ``Scene.blendsr.dataset``, what it makes, the button and the last outcome."""
    ds = context.scene.blendsr.dataset
    st = library.status(Prefs(context).library_path)
    layout.prop(ds, "output_dir")
    row = layout.row(align=True)
    row.prop(ds, "dataset_name")
    row.prop(ds, "seed")
    box = layout.box()
    box.label(text="Clips", icon="RENDER_ANIMATION")
    row = box.row(align=True)
    row.prop(ds, "clips")
    row.prop(ds, "frames")
    box.prop(ds, "cameras")
    row = box.row(align=True)
    row.prop(ds, "hr_width")
    row.prop(ds, "hr_height")
    box.prop(ds, "scales")
    box.prop(ds, "light")
    box = layout.box()
    box.label(text="Sampling and buffers", icon="RENDER_STILL")
    _draw_spp(box, ds)
    for key in DATASET_BUFFER_KEYS:
        box.prop(ds, key)
    _draw_more(layout, ds, render_keys.DATASET_PANEL, DATASET_PLACED)
    box = layout.box()
    box.label(text="Light variation (per clip, recorded)", icon="LIGHT_SUN")
    for switch, lo, hi in (("vary_world", "world_strength_min", "world_strength_max"),
                           ("vary_lights", "light_strength_min", "light_strength_max"),
                           ("vary_sun", "sun_elevation_min", "sun_elevation_max")):
        row = box.row(align=True)
        row.prop(ds, switch)
        sub = row.row(align=True)
        sub.active = getattr(ds, switch)
        sub.prop(ds, lo)
        sub.prop(ds, hi)
    box = layout.box()
    box.label(text="Split regions and workers", icon="MOD_ARRAY")
    row = box.row(align=True)
    for key in ("regions_x", "regions_y", "region_val", "region_test"):
        row.prop(ds, key)
    row = box.row(align=True)
    for key in ("workers", "threads", "device"):
        row.prop(ds, key)
    _draw_summary(layout.box(), "Dataset summary", st, lambda: dataset_summary(context))
    _draw_job(layout, st, "dataset", "Rendering dataset", "blendsr.render_dataset", "RENDER_ANIMATION")
    if ds.last_dataset:
        row = layout.row()
        row.alert = not ds.last_dataset_ok
        row.label(text=f"Last dataset: {ds.last_dataset}")


class BLENDSR_PT_output(bpy.types.Panel):
    bl_idname = "BLENDSR_PT_output"
    bl_label = "BlendSR Dataset"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "output"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        draw_blendsr(self.layout, context)


class BLENDSR_PT_view3d(bpy.types.Panel):
    bl_idname = "BLENDSR_PT_view3d"
    bl_label = "BlendSR"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "BlendSR"

    def draw(self, context):
        draw_blendsr(self.layout, context)


class BLENDSR_PT_output_dataset(bpy.types.Panel):
    bl_idname = "BLENDSR_PT_output_dataset"
    bl_label = "Dataset"
    bl_parent_id = "BLENDSR_PT_output"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "output"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        draw_dataset(self.layout, context)


class BLENDSR_PT_view3d_dataset(bpy.types.Panel):
    bl_idname = "BLENDSR_PT_view3d_dataset"
    bl_label = "Dataset"
    bl_parent_id = "BLENDSR_PT_view3d"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "BlendSR"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        draw_dataset(self.layout, context)


#: The clip panels and their Dataset subpanels (a subpanel after its parent).
CLASSES = (BLENDSR_PT_output, BLENDSR_PT_view3d, BLENDSR_PT_output_dataset, BLENDSR_PT_view3d_dataset)
MAIN_PANELS = CLASSES[:2]
DATASET_PANELS = CLASSES[2:]


register, unregister = bpy.utils.register_classes_factory(CLASSES)
