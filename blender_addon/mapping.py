"""The one place where the panel's settings (``Scene.blendsr``) become a ``gbuffer_export.config.RenderConfig``.

The library is imported when called, never at add-on import. The scene's own frame range and resolution are
resolved here (when the settings say to use them), so the summary and the worker see the same explicit values.
"""
from __future__ import annotations

from pathlib import Path

from . import render_keys


def scene_resolution(scene) -> tuple[int, int]:
    """The scene's render size in pixels (resolution x percentage), as the renderer resolves it."""
    pct = scene.render.resolution_percentage / 100.0
    return int(scene.render.resolution_x * pct), int(scene.render.resolution_y * pct)


def _folder(text: str, what: str, holds: str) -> Path:
    """Absolute folder of a panel's folder setting (``//`` is relative to the saved .blend); ConfigError naming
    ``what`` when it is empty or relative to an unsaved file."""
    import bpy
    from gbuffer_export.config import ConfigError
    text = text.strip()
    if not text:
        raise ConfigError(f"{what}: choose a folder for the {holds}")
    if text.startswith("//") and not bpy.data.filepath:
        raise ConfigError(f"{what} {text!r} is relative to the .blend file: save the file first "
                          "or choose an absolute folder")
    return Path(bpy.path.abspath(text))


def output_path(settings) -> Path:
    """Absolute output folder of the clip settings."""
    return _folder(settings.output_dir, "output folder", "clip")


def render_config(settings, scene, *, scene_path: str | Path | None = None, output: str | Path | None = None):
    """``RenderConfig`` of the settings for ``scene``. ``scene_path`` is the .blend the worker opens (None while
    only checking or summarising); ``output`` overrides the settings' folder. Raises ``ConfigError`` (a
    ``ValueError``) naming the option on invalid settings."""
    from gbuffer_export.config import RenderConfig
    if settings.use_scene_frames:
        frames = (scene.frame_start, scene.frame_end)
    else:
        frames = (settings.frame_start, settings.frame_end)
    if settings.use_scene_resolution:
        hr_size = scene_resolution(scene)
    else:
        hr_size = (settings.hr_width, settings.hr_height)
    return RenderConfig(
        output=Path(output) if output is not None else output_path(settings),
        scene=Path(scene_path) if scene_path is not None else None,
        frames=_frames(frames),
        hr_size=hr_size,
        scale=settings.scale,
        camera_path=settings.camera_path,
        buffers=buffers_value(settings),
        max_bounces=settings.max_bounces if settings.use_max_bounces else None,
        progress=False,
        **render_keys.values(settings, render_keys.CLIP_PANEL),  # the keys derived from RenderConfig's fields
    )


def buffers_value(settings) -> str:
    """The Buffers menu and checkboxes as ``RenderConfig.buffers`` takes them: 'default', 'all', or the ticked
    buffers in the conventions' order, radiance first (always written)."""
    if settings.buffers != "custom":
        return settings.buffers
    order = [b["name"] for b in render_keys.CHOICES["buffers"]]
    return ",".join(render_keys.flag_list({"radiance", *settings.buffer_set}, order))


def _float32_decimal(v: float) -> float:
    """A Blender float property (float32) as the shortest decimal it came from: 0.01, not 0.009999999776."""
    return float(f"{v:.7g}")


def _frames(frames: tuple[int, int]) -> tuple[int, int]:
    from gbuffer_export.config import ConfigError
    a, b = int(frames[0]), int(frames[1])
    if b < a:
        raise ConfigError(f"frames {a}:{b}: end {b} is before start {a}")
    return a, b


# ----------------------------------------------------------------------------------------------------------------
# Dataset of the open scene (Scene.blendsr.dataset -> a dataset spec and run options)
# ----------------------------------------------------------------------------------------------------------------

#: Where the dataset keeps its copy of the open scene, relative to the dataset folder (the workers open this file).
SCENE_DIR = "scene"
SPEC_FILE = "spec.toml"


def slug(text: str) -> str:
    """A file and clip-id safe name: letters, digits, - and _ (others become _); 'untitled' when empty."""
    out = "".join(c if c.isalnum() or c in "-_" else "_" for c in text.strip())
    return out or "untitled"


def scene_stem(blend_path: str) -> str:
    """The name of the dataset's scene copy (``scene/<stem>.blend``): the open file's name, or 'untitled'."""
    return slug(Path(blend_path).stem) if blend_path else "untitled"


def parse_scales(value) -> list[int]:
    """The ticked Scales (a set of '2', '4', ...; or text '2,4' as a spec writes them) -> [2, 4], ascending;
    ConfigError naming the setting when none is ticked or one is not an integer >= 1."""
    from gbuffer_export.config import ConfigError
    parts = [p.strip() for p in (str(value).split(",") if isinstance(value, str) else value) if p.strip()]
    try:
        scales = [int(p) for p in parts]
    except ValueError:
        scales = []
    if not scales or any(k < 1 for k in scales) or len(set(scales)) != len(scales):
        raise ConfigError(f"dataset Scales {_shown(value)}: tick at least one scale (distinct integers >= 1)")
    return sorted(scales) if not isinstance(value, str) else scales


def _shown(value) -> str:
    return repr(value) if isinstance(value, str) else repr(",".join(sorted(value)))


def cameras(ds) -> list[str]:
    """The ticked Cameras in the menu's order; ConfigError when none is."""
    from gbuffer_export.config import ConfigError
    names = render_keys.flag_list(ds.cameras, render_keys.CHOICES["camera_paths"])
    if not names:
        raise ConfigError("dataset Cameras: tick at least one camera path")
    return names


def for_models(ds) -> list[str]:
    """The ticked *For models*, in the model table's order."""
    return render_keys.flag_list(ds.for_models, render_keys.CHOICES["models"])


def for_formats(ds) -> list[str]:
    """The ticked *For formats*, in the format table's order (written as the spec's ``[dataset] for_formats``)."""
    return render_keys.flag_list(getattr(ds, "for_formats", set()),
                                 [f["name"] for f in render_keys.CHOICES["formats"]])


def preview_scale(settings) -> tuple[bool, str]:
    """(whether the preview's model takes any scale, the one-line problem with the settings' Scale or ''), for the
    chosen preview model (``gbuffer_export.dataset.buffers.scale_problem``); a checkpoint file is checked when it
    loads."""
    if settings.checkpoint.strip():
        return False, ""
    from gbuffer_export.dataset.buffers import MODEL_SCALES, scale_problem
    spec = settings.preview_model
    return spec in MODEL_SCALES and MODEL_SCALES[spec] is None, scale_problem(spec, settings.scale)


def model_buffers(ds) -> tuple[str, ...]:
    """The buffers the models of *For models* read (``buffers_for_models``; empty when none is ticked)."""
    names = for_models(ds)
    if not names:
        return ()
    from gbuffer_export.config import ConfigError
    from gbuffer_export.dataset.buffers import buffers_for_models
    from gbuffer_export.errors import BlendSRError
    try:
        return buffers_for_models(names)
    except BlendSRError as exc:
        raise ConfigError(f"dataset For models {','.join(names)!r}: "
                          f"{str(exc).removeprefix('--for-models: ')}") from None


def dataset_spec_dict(ds, stem: str) -> dict:
    """The TOML document of the dataset spec for the settings ``ds`` (``Scene.blendsr.dataset``, or any object
    with its attributes): one ``kind = "scene"`` source of ``scene/<stem>.blend``, every clip with one LR level per
    scale (``scale`` the first, ``scales`` all of them when several; *For models* written as the buffers they
    read, so that the spec alone renders the same clips).
    What it renders is checked by ``parse_spec`` (one-line errors naming the key)."""
    scales = parse_scales(ds.scales)
    models = model_buffers(ds)
    render = {"frames": ds.frames, "hr_size": f"{ds.hr_width}x{ds.hr_height}", "scale": scales[0],
              "buffers": list(models) if models else buffers_value(ds),
              **render_keys.values(ds, render_keys.DATASET_PANEL)}  # the keys derived from RenderConfig's fields
    if len(scales) > 1:
        render["scales"] = scales
    src = {"name": "scene", "kind": "scene", "paths": [f"{SCENE_DIR}/{stem}.blend"], "clips_per_scene": ds.clips,
           "cameras": cameras(ds), "light": ds.light, "regions": [ds.regions_x, ds.regions_y],
           "region_val": ds.region_val, "region_test": ds.region_test, **variation_keys(ds)}
    head = {"name": ds.dataset_name.strip() or stem, "seed": ds.seed}
    if for_formats(ds):  # parse_spec adds what they need (levels, size, buffers) to every clip
        head["for_formats"] = for_formats(ds)
    return {"dataset": head, "render": render, "source": [src]}


def variation_keys(ds) -> dict:
    """The opt-in light variation of a scene source (``world_strength``, ``light_strength``: multiplier ranges,
    ``sun_elevation_deg``: degrees), for the switches that are on."""
    out = {}
    for switch, key, lo, hi in (("vary_world", "world_strength", "world_strength_min", "world_strength_max"),
                                ("vary_lights", "light_strength", "light_strength_min", "light_strength_max"),
                                ("vary_sun", "sun_elevation_deg", "sun_elevation_min", "sun_elevation_max")):
        if getattr(ds, switch):
            out[key] = [_float32_decimal(getattr(ds, lo)), _float32_decimal(getattr(ds, hi))]
    return out


def dataset_spec(ds, stem: str, spec_path: str | Path):
    """The validated ``DatasetSpec`` of the settings, as if read from ``spec_path`` (``DATASET/spec.toml``)."""
    from gbuffer_export.dataset.spec import parse_spec
    return parse_spec(dataset_spec_dict(ds, stem), Path(spec_path))


def dataset_run_options(ds, blender: str = ""):
    """``RunOptions`` of the settings (local executor; ``blender``: the Blender executable that renders each clip,
    '' for this Python with bpy as a module)."""
    from gbuffer_export.dataset.build import RunOptions
    opts = RunOptions(executor="local", workers=ds.workers, threads=ds.threads,
                      buffers_for=tuple(for_models(ds)), progress=False, device=ds.device, blender=blender)
    opts.validate()
    model_buffers(ds)
    return opts


def run_options_json(opts) -> dict:
    """``RunOptions`` as the worker's job file holds it (``worker.run_dataset`` reads it back)."""
    import dataclasses
    return dataclasses.asdict(opts)


def dataset_output(ds) -> Path:
    """Absolute dataset folder of the Dataset settings."""
    return _folder(ds.output_dir, "dataset folder", "dataset")
