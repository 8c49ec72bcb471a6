"""``Scene.blendsr``: the panel's settings, one property per option of ``blendsr render`` (same defaults as the
CLI), the preview's inputs, and the last preview's read-only results. The render keys are derived from
``RenderConfig``'s fields (``render_keys``: added to each class below); the settings written here are the ones
the add-on parses itself (frames, size, scale, camera path, buffers) or that are not render keys."""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty

from .render_keys import CHOICES, CLIP_PANEL, DATASET_PANEL, properties, render_property

#: Help of each camera path (the paths themselves: ``config.CAMERA_PATHS`` through choices.json).
CAMERA_HELP = {
    "scene": "The file's own (animated) scene camera",
    "orbit": "A generated, seeded orbit framed from the scene bounds",
    "walk": "A generated, seeded walk through the level (eye 1.6 m above the floor)",
    "fly": "A generated, seeded free flight through the level",
    "scene:*": "Each clip the next of the file's own cameras",
}


def _label(name: str) -> str:
    return "Scene cameras" if name == "scene:*" else name.replace("-", " ").capitalize()


#: Dataset cameras (checkboxes; clip k uses the k-th ticked kind, cycling) and the clip's one camera path (a menu).
CAMERA_ITEMS = tuple((c, _label(c), CAMERA_HELP.get(c, c)) for c in CHOICES["camera_paths"])
CAMERA_PATH_ITEMS = tuple(i for i in CAMERA_ITEMS if ":" not in i[0])
#: Buffers (``conventions.BUFFERS``) as checkboxes; radiance is always written.
BUFFER_ITEMS = tuple((b["name"], b["name"].replace("_", " ").capitalize(), b["help"]) for b in CHOICES["buffers"])
BUFFER_PRESET_ITEMS = (
    ("default", "Default", "The default buffers: " + ", ".join(CHOICES["default_buffers"])),
    ("all", "All", "Every buffer BlendSR writes"),
    ("custom", "Choose", "The buffers ticked below (radiance is always written)"),
)
#: Models of *For models* (the model-buffer table's), and the scales the models take.
MODEL_ITEMS = tuple((m, m, f"Render the buffers {m} reads") for m in CHOICES["models"])
SCALE_ITEMS = tuple((str(k), f"{k}x", f"An LR level at 1/{k} of the HR size") for k in CHOICES["scales"])
#: Export formats of *For formats* (``format_limits`` through choices.json), each with what it needs.
FORMAT_ITEMS = tuple((f["name"], f["title"], f"Render what {f['title']} needs: {f['needs']}")
                     for f in CHOICES["formats"])
FORMAT_NEEDS = "; ".join(f"{f['title']}: {f['needs']}" for f in CHOICES["formats"])


def buffer_properties(default_set) -> dict:
    """The Buffers menu (default, all, choose) and its checkboxes (``mapping.buffers_value`` reads both)."""
    return {
        "buffers": EnumProperty(name="Buffers", items=BUFFER_PRESET_ITEMS, default="default",
                                description="Buffers to write: the default set, all, or the ones ticked below"),
        "buffer_set": EnumProperty(name="Buffer set", items=BUFFER_ITEMS, options={"ENUM_FLAG"},
                                   default=set(default_set), description="Buffers to write (Buffers: Choose)"),
    }


#: Models the preview runs when no checkpoint is chosen: the weights shipped with blendsr (training/pretrained.py;
#: their datasets in training/weights/*.json) and the non-learned models of training.models.MODELS.
PREVIEW_MODEL_ITEMS = (
    ("pretrained:fusesr-l", "FuseSR-l (pretrained)",
     "FuseSR-l with the weights shipped in blendsr (trained on a BlendSR dataset; see training/weights/*.json)"),
    ("pretrained:fusesr", "FuseSR (pretrained)",
     "FuseSR with the weights shipped in blendsr (two history frames; slower than FuseSR-l)"),
    ("pretrained:fusesr-fast", "FuseSR-fast (pretrained)",
     "FuseSR-fast with the weights shipped in blendsr (68 K parameters; the fastest network)"),
    ("pretrained:rdg-s", "RDG-s (pretrained)",
     "RDG-s (recurrent, LR G-buffer guidance) with the weights shipped in blendsr; runs the clip from its start"),
    ("pretrained:nsrd", "NSRD (pretrained)",
     "NSRD (recurrent, demodulated irradiance) with the weights shipped in blendsr; runs the clip from its start"),
    ("pretrained:nsrr-fec", "NSRR-fec (pretrained)",
     "NSRR with feature caching (recurrent) with the weights shipped in blendsr; runs the clip from its start"),
    ("pretrained:fourier-sr", "Fourier-SR (pretrained)",
     "Fourier arbitrary-scale SR (recurrent) with the weights shipped in blendsr, trained at 4x; runs the clip from "
     "its start"),
    ("demod-bilinear", "Demodulated bilinear",
     "Bilinear upsampling of LR demodulated irradiance, remodulated with HR F_beta and emission"),
    ("demod-jbu", "Demodulated joint bilateral",
     "Joint bilateral upsampling of LR demodulated irradiance guided by HR depth and normals, remodulated"),
    ("bilinear", "Bilinear", "Bilinear upsampling of LR radiance"),
    ("bicubic", "Bicubic", "Bicubic upsampling of LR radiance, clamped at 0"),
)


_MODEL_ITEMS: list = []  # Blender keeps no reference to a callback's strings: the list lives here


def preview_model_items(self, context):
    """The model menu's items: ``PREVIEW_MODEL_ITEMS`` with the library's marks (``library.pretrained_notes``)."""
    from .library import marked_items, pretrained_notes
    _MODEL_ITEMS[:] = marked_items(PREVIEW_MODEL_ITEMS, pretrained_notes())
    return _MODEL_ITEMS


def _result(key: str, default):
    """Getter of a read-only result stored as an ID property (set by the preview operator)."""
    return lambda self: self.get(key, default)


class BlendSRDatasetSettings(bpy.types.PropertyGroup):
    """``Scene.blendsr.dataset``: a dataset of the open scene, one property per key of a ``kind = "scene"`` source
    and of ``blendsr dataset`` (defaults as the spec's and the CLI's; mapping.dataset_spec_dict)."""

    output_dir: StringProperty(name="Dataset folder", subtype="DIR_PATH", default="//blendsr_dataset/",
                               description="Dataset folder to create or extend (// is relative to the .blend)")
    dataset_name: StringProperty(name="Name", default="",
                         description="Dataset name (recorded in dataset.json); empty: the .blend's name")
    seed: IntProperty(name="Seed", default=0, min=0, description="Dataset seed: every clip's seed derives from it")
    clips: IntProperty(name="Clips", default=4, min=1, max=1000,
                       description="Clips of the scene (per scale); clip k uses camera kind k (cycling)")
    cameras: EnumProperty(name="Cameras", items=CAMERA_ITEMS, options={"ENUM_FLAG"}, default={"walk", "fly"},
                          description="Camera kinds of the clips: clip k uses the k-th ticked kind (cycling)")
    frames: IntProperty(name="Frames", default=12, min=1, description="Frames per clip (scene frames 1..N)")
    hr_width: IntProperty(name="HR width", default=256, min=1, subtype="PIXEL",
                          description="HR (target) width in pixels; divisible by every scale")
    hr_height: IntProperty(name="HR height", default=144, min=1, subtype="PIXEL",
                           description="HR (target) height in pixels; divisible by every scale")
    scales: EnumProperty(name="Scales", items=SCALE_ITEMS, options={"ENUM_FLAG"}, default={"4"},
                         description="Upscaling factors: every clip gets one LR level per ticked scale (the "
                                     "smallest is the level 'lr'). Exports need: " + FORMAT_NEEDS)
    light: render_property("light")  # the source's light (a [[source]] key), RenderConfig's choices and default
    device: render_property("device")  # the run's device (blendsr dataset --device)
    for_models: EnumProperty(name="For models", items=MODEL_ITEMS, options={"ENUM_FLAG"}, default=set(),
                             description="Render only the buffers the ticked models read (as --for-models); "
                                         "none ticked: the Buffers setting")
    for_formats: EnumProperty(name="For formats", items=FORMAT_ITEMS, options={"ENUM_FLAG"}, default=set(),
                              description="Also render what the ticked export formats need (as --for-formats: "
                                          "their LR levels, size and buffers; blendsr export-dataset checks them). "
                                          + FORMAT_NEEDS)
    vary_world: BoolProperty(name="Vary world strength", default=False,
                             description="Multiply the world's background strength per clip (log-uniform in the range)")
    world_strength_min: FloatProperty(name="Min", default=0.5, min=0.001, description="Smallest world multiplier")
    world_strength_max: FloatProperty(name="Max", default=2.0, min=0.001, description="Largest world multiplier")
    vary_lights: BoolProperty(name="Vary light strength", default=False,
                              description="Multiply every lamp's energy per clip (log-uniform in the range)")
    light_strength_min: FloatProperty(name="Min", default=0.5, min=0.001, description="Smallest lamp multiplier")
    light_strength_max: FloatProperty(name="Max", default=2.0, min=0.001, description="Largest lamp multiplier")
    vary_sun: BoolProperty(name="Vary sun (time of day)", default=False,
                           description="Draw the sun lamps' (and an added sky's) elevation per clip, azimuth uniform")
    sun_elevation_min: FloatProperty(name="Min elevation", default=20.0, min=0.001, max=90.0,
                                     description="Lowest sun elevation in degrees")
    sun_elevation_max: FloatProperty(name="Max elevation", default=70.0, min=0.001, max=90.0,
                                     description="Highest sun elevation in degrees")
    regions_x: IntProperty(name="Regions X", default=1, min=1, max=16,
                           description="Split regions: columns of the grid over the level's content box")
    regions_y: IntProperty(name="Regions Y", default=1, min=1, max=16,
                           description="Split regions: rows of the grid over the level's content box")
    region_val: IntProperty(name="Val cells", default=0, min=0, description="Grid cells whose clips are val")
    region_test: IntProperty(name="Test cells", default=0, min=0, description="Grid cells whose clips are test")
    workers: IntProperty(name="Workers", default=1, min=1, max=64, description="Clips rendered at once")
    threads: IntProperty(name="Threads", default=0, min=0,
                         description="Cycles threads per clip (0: the machine's cores divided by the workers)")
    last_dataset: StringProperty(name="Last dataset", get=_result("_last_dataset", ""),
                                 description="Outcome of the last dataset render and its validation")
    last_dataset_ok: BoolProperty(name="Last dataset valid", get=_result("_last_dataset_ok", False),
                                  description="The last dataset render finished every clip and validated")


class BlendSRSettings(bpy.types.PropertyGroup):
    # -- output ----------------------------------------------------------------------------------------------
    output_dir: StringProperty(name="Output folder", subtype="DIR_PATH", default="//blendsr_clip/",
                               description="Clip directory to create or resume (// is relative to the .blend)")
    # -- frames and size ---------------------------------------------------------------------------------------
    use_scene_frames: BoolProperty(name="Scene frame range", default=True,
                                   description="Render the scene's frame range (the CLI's default)")
    frame_start: IntProperty(name="Start", default=1, description="First frame (inclusive)")
    frame_end: IntProperty(name="End", default=48, description="Last frame (inclusive)")
    use_scene_resolution: BoolProperty(name="Scene resolution", default=True,
                                       description="HR size = the scene's render resolution (the CLI's default)")
    hr_width: IntProperty(name="HR width", default=640, min=1, subtype="PIXEL",
                          description="HR (target) width in pixels; divisible by the scale")
    hr_height: IntProperty(name="HR height", default=360, min=1, subtype="PIXEL",
                           description="HR (target) height in pixels; divisible by the scale")
    scale: IntProperty(name="Scale", default=4, min=1, max=16, description="Integer upscaling factor; LR = HR / scale")
    # -- sampling ----------------------------------------------------------------------------------------------
    use_max_bounces: BoolProperty(name="Override bounces", default=False,
                                  description="Override the scene's total light bounces")
    max_bounces: IntProperty(name="Max bounces", default=12, min=0, description="Total light bounces")
    # -- buffers and camera --------------------------------------------------------------------------------------
    camera_path: EnumProperty(name="Camera path", items=CAMERA_PATH_ITEMS, default="scene",
                              description="Camera of the clip")
    # -- preview -------------------------------------------------------------------------------------------------
    checkpoint: StringProperty(name="Checkpoint", subtype="FILE_PATH", default="",
                               description="Trained model checkpoint; empty: the non-learned model below")
    preview_model: EnumProperty(name="Model", items=preview_model_items, default=0,  # pretrained:fusesr-l
                                description="Model used when no checkpoint is chosen: shipped pretrained weights "
                                            "or a non-learned model")
    with_reference: BoolProperty(name="With reference", default=False,
                                 description="Also render the HR ground truth (HR samples) and report PSNR")
    # -- results of the last preview (read-only) -----------------------------------------------------------------
    preview_ms: FloatProperty(name="Inference time", get=_result("_preview_ms", 0.0), unit="NONE",
                              description="The last preview's model time per frame in milliseconds: the median of "
                                          "the calls after the first (the warm-up)")
    preview_warmup_ms: FloatProperty(name="Warm-up", get=_result("_preview_warmup_ms", 0.0), unit="NONE",
                                     description="The last preview's first call with the model's loading or the "
                                                 "ONNX Runtime session's creation, in milliseconds")
    preview_runtime: StringProperty(name="Runtime", get=_result("_preview_runtime", ""),
                                    description="What ran the last preview's model (torch, ONNX Runtime)")
    preview_psnr: FloatProperty(name="PSNR", get=_result("_preview_psnr", 0.0),
                                description="PSNR of the last preview against the reference in dB (0: none)")
    preview_metric: StringProperty(name="Metric", get=_result("_preview_metric", ""),
                                   description="How the last preview's PSNR was computed")
    preview_info: StringProperty(name="Preview", get=_result("_preview_info", ""),
                                 description="Frame and model of the last preview")
    preview_clip: StringProperty(name="Preview clip", get=_result("_preview_clip", ""),
                                 description="Folder of the last preview's one-frame clip")
    last_export: StringProperty(name="Last export", get=_result("_last_export", ""),
                                description="Outcome of the last export")
    # -- dataset of the open scene (the Dataset subpanel) ---------------------------------------------------------
    dataset: bpy.props.PointerProperty(type=BlendSRDatasetSettings, name="Dataset")


#: The render keys of RenderConfig each group derives (types, defaults, ranges, labels, help: render_keys.json).
BlendSRSettings.__annotations__.update(properties(CLIP_PANEL))
BlendSRDatasetSettings.__annotations__.update(properties(DATASET_PANEL))
for _cls in (BlendSRSettings, BlendSRDatasetSettings):
    _cls.__annotations__.update(buffer_properties(CHOICES["default_buffers"]))


def store_preview_results(settings, *, ms: float, psnr: float | None, metric: str, info: str, clip: str,
                          warmup_ms: float = 0.0, runtime: str = "") -> None:
    """Set the read-only results (ID properties behind the getters)."""
    settings["_preview_ms"] = float(ms)
    settings["_preview_psnr"] = float(psnr) if psnr is not None else 0.0
    settings["_preview_metric"] = metric if psnr is not None else ""
    settings["_preview_info"] = info
    settings["_preview_clip"] = clip
    settings["_preview_warmup_ms"] = float(warmup_ms)
    settings["_preview_runtime"] = runtime


CLASSES = (BlendSRDatasetSettings, BlendSRSettings)


def register() -> None:
    for c in CLASSES:
        bpy.utils.register_class(c)
    bpy.types.Scene.blendsr = bpy.props.PointerProperty(type=BlendSRSettings, name="BlendSR")


def unregister() -> None:
    if hasattr(bpy.types.Scene, "blendsr"):
        del bpy.types.Scene.blendsr
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)
