"""``Scene.blendsr``: the panel's settings, one property per option of ``blendsr render`` (same defaults as the
CLI), the preview's inputs, and the last preview's read-only results."""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty

CAMERA_PATH_ITEMS = (
    ("scene", "Scene", "The file's own (animated) scene camera"),
    ("orbit", "Orbit", "A generated, seeded orbit framed from the scene bounds"),
    ("walk", "Walk", "A generated, seeded walk through the level (eye 1.6 m above the floor)"),
    ("fly", "Fly", "A generated, seeded free flight through the level"),
)
LIGHT_ITEMS = (
    ("auto", "Auto", "The file's own lights where they light what the cameras see, else an added sun and sky "
                     "and/or lamps under the ceilings (measured; recorded in the manifest)"),
    ("scene", "Scene", "The file's own lights (refused when the scene is unlit)"),
    ("sky", "Sky", "Add a seeded sun and sky"),
)
DEVICE_ITEMS = tuple((d, d.upper() if d != "auto" else "Auto", f"Cycles device {d}")
                     for d in ("auto", "cpu", "cuda", "optix", "hip", "metal", "oneapi"))
JITTER_ITEMS = (
    ("none", "None", "LR frames are not jittered"),
    ("halton", "Halton", "Sub-pixel jitter of the LR frames, Halton(2, 3) with period 16, in LR pixels"),
)
FBETA_ITEMS = (
    ("cycles", "Cycles", "Pre-integrated BRDF from Cycles' Diffuse + Glossy + Transmission Color passes"),
    ("lut", "Split-sum table", "Split-sum table (image-based-lighting convention)"),
    ("lut-paper", "Papers' table", "The papers' literal table convention"),
    ("model", "Model", "A model of Cycles' Principled BSDF"),
)
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
    cameras: StringProperty(name="Cameras", default="walk,fly",
                            description="Camera kinds, comma-separated: walk, fly, orbit, scene (the active "
                                        "camera), scene:* (each clip the next of the file's cameras), scene:NAME")
    frames: IntProperty(name="Frames", default=12, min=1, description="Frames per clip (scene frames 1..N)")
    hr_width: IntProperty(name="HR width", default=256, min=1, subtype="PIXEL",
                          description="HR (target) width in pixels; divisible by every scale")
    hr_height: IntProperty(name="HR height", default=144, min=1, subtype="PIXEL",
                           description="HR (target) height in pixels; divisible by every scale")
    scales: StringProperty(name="Scales", default="4",
                           description="Integer upscaling factors, comma-separated; each scale is a source of "
                                       "its own (its own clips, one LR level each)")
    hr_spp: IntProperty(name="HR samples", default=64, min=1, description="Samples per pixel of the HR ground truth")
    lr_spp: IntProperty(name="LR samples", default=4, min=1, description="Samples per pixel of the LR render")
    gbuffer_spp: IntProperty(name="G-buffer samples", default=4, min=1,
                             description="Samples per pixel of the HR G-buffer pass")
    hr_denoise: BoolProperty(name="Denoise HR", default=False,
                             description="Denoise the HR ground truth with OpenImageDenoise")
    lr_denoise: BoolProperty(name="Denoise LR", default=False,
                             description="Denoise the LR render with OpenImageDenoise")
    jitter: EnumProperty(name="Jitter", items=JITTER_ITEMS, default="halton", description="Sub-pixel jitter of LR")
    buffers: StringProperty(name="Buffers", default="default",
                            description="Comma-separated buffers, 'default' or 'all' (For models overrides it)")
    fbeta_source: EnumProperty(name="F_beta source", items=FBETA_ITEMS, default="cycles",
                               description="Source of the pre-integrated BRDF")
    light: EnumProperty(name="Light", items=LIGHT_ITEMS, default="auto", description="Lighting of every clip")
    device: EnumProperty(name="Device", items=DEVICE_ITEMS, default="auto", description="Cycles render device")
    for_models: StringProperty(name="For models", default="",
                               description="Render only the buffers these models read (comma-separated model "
                                           "names, as --for-models); empty: the Buffers setting")
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
    hr_spp: IntProperty(name="HR samples", default=64, min=1, description="Samples per pixel of the HR ground truth")
    lr_spp: IntProperty(name="LR samples", default=4, min=1, description="Samples per pixel of the LR render")
    gbuffer_spp: IntProperty(name="G-buffer samples", default=4, min=1,
                             description="Samples per pixel of the HR G-buffer pass (within 0.01 px of the centre)")
    hr_denoise: BoolProperty(name="Denoise HR", default=False,
                             description="Denoise the HR ground truth with OpenImageDenoise")
    lr_denoise: BoolProperty(name="Denoise LR", default=False,
                             description="Denoise the LR render with OpenImageDenoise")
    adaptive: BoolProperty(name="Adaptive HR", default=False,
                           description="Adaptive sampling for the HR ground truth (HR samples become the maximum)")
    adaptive_threshold: FloatProperty(name="Noise threshold", default=0.01, min=0.0, max=0.999, precision=4,
                                      description="Cycles' adaptive noise threshold")
    adaptive_min_samples: IntProperty(name="Min samples", default=0, min=0,
                                      description="Adaptive minimum samples (0 = automatic)")
    use_max_bounces: BoolProperty(name="Override bounces", default=False,
                                  description="Override the scene's total light bounces")
    max_bounces: IntProperty(name="Max bounces", default=12, min=0, description="Total light bounces")
    seed: IntProperty(name="Seed", default=0, min=0, description="Seed of camera paths and Cycles noise")
    threads: IntProperty(name="Threads", default=0, min=0, description="Render threads (0 = all cores)")
    # -- buffers and camera --------------------------------------------------------------------------------------
    light: EnumProperty(name="Light", items=LIGHT_ITEMS, default="auto", description="Lighting of the export")
    device: EnumProperty(name="Device", items=DEVICE_ITEMS, default="auto", description="Cycles render device")
    camera_path: EnumProperty(name="Camera path", items=CAMERA_PATH_ITEMS, default="scene",
                              description="Camera of the clip")
    jitter: EnumProperty(name="Jitter", items=JITTER_ITEMS, default="halton", description="Sub-pixel jitter of LR")
    buffers: StringProperty(name="Buffers", default="default",
                            description="Comma-separated buffers to write, 'default' or 'all'; radiance is always "
                                        "written")
    fbeta_source: EnumProperty(name="F_beta source", items=FBETA_ITEMS, default="cycles",
                               description="Source of the pre-integrated BRDF")
    # -- preview -------------------------------------------------------------------------------------------------
    checkpoint: StringProperty(name="Checkpoint", subtype="FILE_PATH", default="",
                               description="Trained model checkpoint; empty: the non-learned model below")
    preview_model: EnumProperty(name="Model", items=PREVIEW_MODEL_ITEMS, default="pretrained:fusesr-l",
                                description="Model used when no checkpoint is chosen: shipped pretrained weights "
                                            "or a non-learned model")
    with_reference: BoolProperty(name="With reference", default=False,
                                 description="Also render the HR ground truth (HR samples) and report PSNR")
    # -- results of the last preview (read-only) -----------------------------------------------------------------
    preview_ms: FloatProperty(name="Inference time", get=_result("_preview_ms", 0.0), unit="NONE",
                              description="Inference time of the last preview in milliseconds")
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


def store_preview_results(settings, *, ms: float, psnr: float | None, metric: str, info: str, clip: str) -> None:
    """Set the read-only results (ID properties behind the getters)."""
    settings["_preview_ms"] = float(ms)
    settings["_preview_psnr"] = float(psnr) if psnr is not None else 0.0
    settings["_preview_metric"] = metric if psnr is not None else ""
    settings["_preview_info"] = info
    settings["_preview_clip"] = clip


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
