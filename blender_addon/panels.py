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
    """The clip panel's head: the library's state, the output folder, what the export writes, the export button and
    the buttons that open its folder and contact sheet. The settings are in the subpanels (``SECTIONS``)."""
    s = context.scene.blendsr
    st = library.status(Prefs(context).library_path)
    if not st.ok:
        box = layout.box()
        box.alert = True
        box.label(text=st.message, icon="ERROR")
        for line in st.hint:
            box.label(text=line)
    layout.prop(s, "output_dir")
    _draw_summary(layout.box(), "Export summary", st, lambda: summary(context))
    _draw_job(layout, st, "export", "Exporting", "blendsr.export_dataset", "EXPORT")
    _draw_open_buttons(layout, st, "clip")
    if s.last_export:
        layout.label(text=f"Last export: {s.last_export}")


def _draw_open_buttons(layout, st, target: str) -> None:
    """'Open output' and 'Contact sheet' of the clip or the dataset (``operators.BLENDSR_OT_open_output``, ...)."""
    row = layout.row(align=True)
    row.enabled = st.ok
    row.operator("blendsr.open_output", icon="FILEBROWSER").target = target
    row.operator("blendsr.contact_sheet", icon="IMAGE_DATA").target = target


#: Where the clip settings' render keys are drawn; a key derived from RenderConfig that none of these places is drawn
#: under "More render settings" (``_draw_more``), so a new key shows up before it is given a place.
SPP_KEYS = ("hr_spp", "lr_spp", "gbuffer_spp", "hr_denoise", "lr_denoise")
CLIP_CAMERA_KEYS = ("camera_path", "light", "device", "jitter", "fbeta_source", "hr_fbeta")
BUFFER_KEYS = ("buffers", "buffer_set")
CLIP_PLACED = {*SPP_KEYS, *CLIP_CAMERA_KEYS, *BUFFER_KEYS, "adaptive", "adaptive_threshold", "adaptive_min_samples",
               "seed", "threads"}
DATASET_BUFFER_KEYS = ("jitter", "fbeta_source", "hr_fbeta")
DATASET_PLACED = {*SPP_KEYS, *DATASET_BUFFER_KEYS, *BUFFER_KEYS, "for_models", "light", "device", "threads"}


def _more_keys(shell: str, placed) -> list[str]:
    return [render_keys.prop_name(k) for k in render_keys.keys(shell) if render_keys.prop_name(k) not in placed]


def _draw_more(layout, s, shell: str, placed) -> None:
    """The render keys ``shell`` derives that the panel does not place (none: nothing drawn)."""
    for key in _more_keys(shell, placed):
        layout.prop(s, key)


def _draw_buffers(layout, s, active: bool = True) -> None:
    """The Buffers menu, and its checkboxes when it says Choose."""
    col = layout.column()
    col.active = active
    col.prop(s, "buffers")
    if s.buffers == "custom":
        grid = col.column(align=True)
        grid.prop(s, "buffer_set", expand=True)


def _draw_frames(box, s) -> None:
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


def _draw_camera(layout, context) -> None:
    s = context.scene.blendsr
    for key in CLIP_CAMERA_KEYS:
        layout.prop(s, key)
    _draw_buffers(layout, s)
    row = layout.row()
    row.enabled = library.status(Prefs(context).library_path).ok
    row.operator("blendsr.create_camera_paths", icon="CAMERA_DATA")


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


#: The preview's models need torch or, for the shipped ones, the zip's ONNX Runtime: one line when neither is there.
TORCH_MISSING = ("The preview needs torch (blendsr[train]) or the extension zip's ONNX Runtime: install torch into "
                 "Blender's Python or set External Python in the add-on preferences")


def _runner_line(s, st, prefs) -> tuple[str, bool]:
    """(the line saying what will run the preview's model when it is not torch in Blender's Python, alert)."""
    from .operators import inference_runner
    spec = s.checkpoint.strip() or s.preview_model
    try:
        kind, where = inference_runner(st, prefs, spec, int(s.scale))
    except ValueError:
        return TORCH_MISSING, True
    if kind == "onnx":
        return ("The preview runs the extension's ONNX graph through ONNX Runtime" if prefs.inference == "ONNX"
                else "torch is not in Blender's Python: the preview runs the extension's ONNX graph (ONNX Runtime)",
                False)
    if kind == "external":
        return f"torch is not in Blender's Python: inference runs with {where}", False
    return "", False


def _draw_preview(box, s, st, prefs) -> None:
    box.prop(s, "checkpoint")
    row = box.row()
    row.active = not s.checkpoint.strip()
    row.prop(s, "preview_model")
    _draw_preview_scale(box, s, st)
    box.prop(s, "with_reference")
    if st.ok and prefs.inference != "EXTERNAL":
        line, alert = _runner_line(s, st, prefs)
        if line:
            col = box.column()
            col.alert = alert
            col.label(text=line, icon="ERROR" if alert else "NONE")
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
        col.label(text=f"Inference: {s.preview_ms:.1f} ms per frame, warm-up {s.preview_warmup_ms:.0f} ms")
        if s.preview_runtime:
            col.label(text=f"Runtime: {s.preview_runtime}")
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
    """The Dataset subpanel's head: folder, name, what it makes, the button, the last outcome, open buttons."""
    ds = context.scene.blendsr.dataset
    st = library.status(Prefs(context).library_path)
    layout.prop(ds, "output_dir")
    row = layout.row(align=True)
    row.prop(ds, "dataset_name")
    row.prop(ds, "seed")
    _draw_summary(layout.box(), "Dataset summary", st, lambda: dataset_summary(context))
    _draw_job(layout, st, "dataset", "Rendering dataset", "blendsr.render_dataset", "RENDER_ANIMATION")
    _draw_open_buttons(layout, st, "dataset")
    if ds.last_dataset:
        row = layout.row()
        row.alert = not ds.last_dataset_ok
        row.label(text=f"Last dataset: {ds.last_dataset}")


def _draw_dataset_clips(layout, context) -> None:
    ds = context.scene.blendsr.dataset
    row = layout.row(align=True)
    row.prop(ds, "clips")
    row.prop(ds, "frames")
    layout.label(text="Cameras (clip k: the k-th ticked, cycling)")
    layout.row(align=True).prop(ds, "cameras", expand=True)
    row = layout.row(align=True)
    row.prop(ds, "hr_width")
    row.prop(ds, "hr_height")
    layout.label(text="Scales (an LR level each)")
    layout.row(align=True).prop(ds, "scales", expand=True)
    layout.label(text="For formats (what each export needs is added)")
    layout.row(align=True).prop(ds, "for_formats", expand=True)
    layout.prop(ds, "light")


def _draw_dataset_sampling(layout, context) -> None:
    ds = context.scene.blendsr.dataset
    _draw_spp(layout, ds)
    for key in DATASET_BUFFER_KEYS:
        layout.prop(ds, key)
    layout.label(text="For models (their buffers; none: Buffers below)")
    layout.column_flow(columns=3, align=True).prop(ds, "for_models", expand=True)
    _draw_buffers(layout, ds, active=not ds.for_models)
    _draw_more(layout, ds, render_keys.DATASET_PANEL, DATASET_PLACED)


def _draw_dataset_light(layout, context) -> None:
    ds = context.scene.blendsr.dataset
    for switch, lo, hi in (("vary_world", "world_strength_min", "world_strength_max"),
                           ("vary_lights", "light_strength_min", "light_strength_max"),
                           ("vary_sun", "sun_elevation_min", "sun_elevation_max")):
        row = layout.row(align=True)
        row.prop(ds, switch)
        sub = row.row(align=True)
        sub.active = getattr(ds, switch)
        sub.prop(ds, lo)
        sub.prop(ds, hi)


def _draw_dataset_regions(layout, context) -> None:
    ds = context.scene.blendsr.dataset
    row = layout.row(align=True)
    for key in ("regions_x", "regions_y", "region_val", "region_test"):
        row.prop(ds, key)
    row = layout.row(align=True)
    for key in ("workers", "threads", "device"):
        row.prop(ds, key)


def _draw_preview_panel(layout, context) -> None:
    prefs = Prefs(context)
    _draw_preview(layout, context.scene.blendsr, library.status(prefs.library_path), prefs)


#: Where each panel lives: the Properties editor's Output tab and the 3D viewport's sidebar (tab 'BlendSR').
SPACES = {
    "output": {"bl_space_type": "PROPERTIES", "bl_region_type": "WINDOW", "bl_context": "output"},
    "view3d": {"bl_space_type": "VIEW_3D", "bl_region_type": "UI", "bl_category": "BlendSR"},
}
#: (id suffix, label, draw(layout, context), parent's suffix or None for the head, closed at first), in drawing
#: order: the head, its collapsible subpanels, the Dataset subpanel and its own.
SECTIONS = (
    ("", "BlendSR", draw_blendsr, None, False),
    ("_frames", "Frames and size", lambda lay, ctx: _draw_frames(lay, ctx.scene.blendsr), "", True),
    ("_sampling", "Sampling", lambda lay, ctx: _draw_sampling(lay, ctx.scene.blendsr), "", True),
    ("_camera", "Camera and buffers", _draw_camera, "", True),
    ("_more", "More render settings",
     lambda lay, ctx: _draw_more(lay, ctx.scene.blendsr, render_keys.CLIP_PANEL, CLIP_PLACED), "", True),
    ("_preview", "Preview upscaling (current frame)", _draw_preview_panel, "", True),
    ("_dataset", "Dataset", draw_dataset, "", True),
    ("_dataset_clips", "Clips and cameras", _draw_dataset_clips, "_dataset", True),
    ("_dataset_sampling", "Sampling and buffers", _draw_dataset_sampling, "_dataset", True),
    ("_dataset_light", "Light variation (per clip, recorded)", _draw_dataset_light, "_dataset", True),
    ("_dataset_regions", "Split regions and workers", _draw_dataset_regions, "_dataset", True),
)
#: The head panels' labels (the Output tab's is closed at first: it sits among Blender's own output panels).
HEAD_LABELS = {"output": "BlendSR Dataset", "view3d": "BlendSR"}


def _panel(space: str, suffix: str, label: str, draw, parent, closed: bool) -> type:
    attrs = {"bl_idname": f"BLENDSR_PT_{space}{suffix}", "bl_label": HEAD_LABELS[space] if parent is None else label,
             **SPACES[space], "draw": lambda self, context: draw(self.layout, context)}
    if parent is not None:
        attrs["bl_parent_id"] = f"BLENDSR_PT_{space}{parent}"
    if closed or (parent is None and space == "output"):
        attrs["bl_options"] = {"DEFAULT_CLOSED"}
    if suffix == "_more":
        attrs["poll"] = classmethod(lambda cls, context: bool(_more_keys(render_keys.CLIP_PANEL, CLIP_PLACED)))
    return type(attrs["bl_idname"], (bpy.types.Panel,), attrs)


#: Every panel class, a subpanel after its parent.
CLASSES = tuple(_panel(space, *sec) for space in SPACES for sec in SECTIONS)
_BY_ID = {c.bl_idname: c for c in CLASSES}
BLENDSR_PT_output, BLENDSR_PT_view3d = _BY_ID["BLENDSR_PT_output"], _BY_ID["BLENDSR_PT_view3d"]
MAIN_PANELS = (BLENDSR_PT_output, BLENDSR_PT_view3d)
DATASET_PANELS = (_BY_ID["BLENDSR_PT_output_dataset"], _BY_ID["BLENDSR_PT_view3d_dataset"])


def subtree(cls, skip=()) -> list[type]:
    """``cls`` and the panels below it (in drawing order), without the subtrees of ``skip``."""
    out = [cls]
    for c in CLASSES:
        if getattr(c, "bl_parent_id", None) == cls.bl_idname and c not in skip:
            out += subtree(c, skip)
    return out


register, unregister = bpy.utils.register_classes_factory(CLASSES)
