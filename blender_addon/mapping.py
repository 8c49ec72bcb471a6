"""The one place where the panel's settings (``Scene.blendsr``) become a ``gbuffer_export.config.RenderConfig``.

The library is imported when called, never at add-on import. The scene's own frame range and resolution are
resolved here (when the settings say to use them), so the summary and the worker see the same explicit values.
"""
from __future__ import annotations

from pathlib import Path


def scene_resolution(scene) -> tuple[int, int]:
    """The scene's render size in pixels (resolution x percentage), as the renderer resolves it."""
    pct = scene.render.resolution_percentage / 100.0
    return int(scene.render.resolution_x * pct), int(scene.render.resolution_y * pct)


def output_path(settings) -> Path:
    """Absolute output folder of the settings (``//`` is relative to the saved .blend)."""
    import bpy
    from gbuffer_export.config import ConfigError
    text = settings.output_dir.strip()
    if not text:
        raise ConfigError("output folder: choose a folder for the clip")
    if text.startswith("//") and not bpy.data.filepath:
        raise ConfigError(f"output folder {text!r} is relative to the .blend file: save the file first "
                          "or choose an absolute folder")
    return Path(bpy.path.abspath(text))


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
        hr_spp=settings.hr_spp,
        lr_spp=settings.lr_spp,
        gbuffer_spp=settings.gbuffer_spp,
        hr_denoise=settings.hr_denoise,
        lr_denoise=settings.lr_denoise,
        adaptive=settings.adaptive,
        adaptive_threshold=_float32_decimal(settings.adaptive_threshold),
        adaptive_min_samples=settings.adaptive_min_samples,
        camera_path=settings.camera_path,
        light=settings.light,
        device=settings.device,
        seed=settings.seed,
        jitter=settings.jitter,
        buffers=settings.buffers,
        fbeta=settings.fbeta_source,
        max_bounces=settings.max_bounces if settings.use_max_bounces else None,
        threads=settings.threads,
        progress=False,
    )


def _float32_decimal(v: float) -> float:
    """A Blender float property (float32) as the shortest decimal it came from: 0.01, not 0.009999999776."""
    return float(f"{v:.7g}")


def _frames(frames: tuple[int, int]) -> tuple[int, int]:
    from gbuffer_export.config import ConfigError
    a, b = int(frames[0]), int(frames[1])
    if b < a:
        raise ConfigError(f"frames {a}:{b}: end {b} is before start {a}")
    return a, b
