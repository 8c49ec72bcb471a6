"""The render setup (bpy layer): what a clip's render derives from its configuration and the scene, settled once,
before anything is written (``resolve_render`` -> frozen ``ResolvedRender``). It is five stages, each a function of
the previous stage's frozen result, which it extends (each stage's dataclass adds its fields to the one before it):

1. ``scene_stage``: the scene as the configuration takes it: frames, HR size, renderable objects, untextured
   materials, and under ``light = "scene"`` its light sources (an unlit scene is refused here).
2. ``unit_stage``: the user's level: its geometry without sky meshes and the sky meshes found
   (``lighting.level_light``), and the level's unit (``level_scale``) where a level camera plans on it.
3. ``camera_stage``: the clip's camera and its report for the manifest.
4. ``light_stage``: the light, and its record for the manifest (``lighting.light_clip``).
5. ``pass_stage``: the frames this process renders (their resources checked), the view layer, materials, AOVs,
   pass plan, transmissive materials seen through, flag table and moving objects.

Each stage function's docstring says what it needs from the stages before it.
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any

import bpy
import numpy as np

from ..clip import FRAMES_DIR, frame_name, levels_header
from ..config import ConfigError, RenderConfig
from ..conventions import Flag, computed_buffers, material_flags_for_source
from ..resources import check_render_resources
from . import materials as mats
from .convert import PassPlan, plan_passes

log = logging.getLogger(__name__)

#: Object types Cycles renders as geometry.
RENDERABLE_TYPES = ("MESH", "CURVE", "SURFACE", "META", "FONT", "CURVES", "POINTCLOUD", "VOLUME")
#: ``light = "sky"``: the least fraction of the upper hemisphere a level camera's eye must see as sky (the sun and
#: sky are the only light; an eye under a roof renders black). 5 %: a street between buildings sees far more.
SKY_LIT_MIN_SKY = 0.05


def renderable_meshes(scene) -> list:
    return [ob for ob in scene.objects if ob.type in RENDERABLE_TYPES and not ob.hide_render]


def resolve_frames(cfg: RenderConfig, scene) -> list[int]:
    start, end = scene.frame_start, scene.frame_end
    if cfg.frames is None:
        cfg.check_frames_subset(range(start, end + 1))
        return list(range(start, end + 1))
    a, b = cfg.frames
    if cfg.scene is not None and cfg.camera_path.startswith("scene") and (a < start or b > end):
        raise ConfigError(f"frames {a}:{b} is outside the scene's range {start}:{end}", key="frames")
    return list(range(a, b + 1))


def resolve_size(cfg: RenderConfig, scene) -> tuple[int, int]:
    if cfg.hr_size is not None:
        return cfg.hr_size
    pct = scene.render.resolution_percentage / 100.0
    w, h = int(scene.render.resolution_x * pct), int(scene.render.resolution_y * pct)
    try:
        cfg.check_size((w, h), "scene resolution")
    except ConfigError as exc:
        raise ConfigError(f"{exc}; set hr_size", key="hr_size") from None
    return w, h


def uses_level_camera(cfg: RenderConfig) -> bool:
    """fly always, and walk in a user's scene file, move inside the level (``level_cameras``); orbit and the
    built-in scene's walk frame the scene's bounds (``camera_paths``)."""
    return cfg.camera_path == "fly" or (cfg.camera_path == "walk" and cfg.scene is not None)


def level_rules(cfg: RenderConfig):
    """The rules of ``cfg``'s level camera path (``level_cameras.PathRules``): a sky-lit level's eyes must see the
    sky."""
    from .level_cameras import PathRules
    return PathRules(min_sky_fraction=SKY_LIT_MIN_SKY) if cfg.light == "sky" else PathRules()


def built_by_blendsr(scene_info: dict) -> bool:
    """The built-in scene or an asset in a generated environment: BlendSR built it and its light (sun, HDRI)."""
    return bool(scene_info.get("builtin")) or "asset" in scene_info


def find_level(cfg: RenderConfig, scene, scene_info: dict, first_frame: int):
    """The level's geometry and its sky meshes (``lighting.level_light``) where a level camera plans on it or the
    light is measured (auto, sky) on a scene BlendSR did not build; None otherwise, or for a scene without
    triangles that needs no level camera."""
    if built_by_blendsr(scene_info) or not (uses_level_camera(cfg) or cfg.light in ("auto", "sky")):
        return None
    from ..errors import BlendSRError
    from .lighting import level_light
    try:
        return level_light(scene, first_frame)
    except BlendSRError as exc:  # no triangles (points, volumes): nothing to plan on or measure
        if uses_level_camera(cfg):
            raise ConfigError(f"{cfg.scene or 'scene'}: {exc}", key="camera_path") from None
        return None


def check_camera(cam, cfg: RenderConfig) -> None:
    if cam.type != "CAMERA":
        raise ConfigError(f"{cfg.scene or 'scene'}: scene camera {cam.name!r} is not a camera object")
    if cam.data.type != "PERSP":
        raise ConfigError(f"{cfg.scene or 'scene'}: camera {cam.name!r} is {cam.data.type.lower()}; only perspective "
                          "cameras are supported (Blender's motion vectors are wrong for orthographic ones)")


def _camera_path_error(cfg: RenderConfig, exc: Exception) -> ConfigError:
    """The one-line error of a level camera that has no path (or no geometry to plan on), with its fix."""
    from .level_cameras import ROOF, PathError
    if isinstance(exc, PathError) and ROOF in exc.reasons:  # a sky-lit walk stood under a roof on some try
        return ConfigError(f"{cfg.scene or 'scene'}: {exc}; set light auto (it lights a level under a roof with "
                           "lamps under its ceilings, and adds the sun and sky where the cameras see the sky)",
                           key="light")
    return ConfigError(f"{cfg.scene or 'scene'}: {exc}; blendsr dataset --dry-run names a fix that works for a level "
                       "(another camera kind, fewer regions, unit_scale); a single object (no floor, nothing around "
                       "it) is framed by camera_path orbit", key="camera_path")


# ----------------------------------------------------------------------------------------------
# The stages
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SceneStage:
    """1. The scene as ``cfg`` takes it: its frames, HR size and renderable objects; ``material_mode``, the
    manifest's record of ``materials = "untextured"`` (None for "keep"); ``sources``, its light sources under
    ``light = "scene"`` (None otherwise)."""

    cfg: RenderConfig
    scene: Any
    info: dict
    frames: tuple[int, ...]
    hr_size: tuple[int, int]
    meshes: tuple
    material_mode: dict | None
    sources: dict | None


def scene_stage(cfg: RenderConfig, scene, info: dict) -> SceneStage:
    """Stage 1 (needs the loaded scene and what loading recorded, ``info``). The materials are made untextured
    first: the light probe and the material inspection of later stages both see the materials that render."""
    meshes = tuple(renderable_meshes(scene))
    if not meshes:
        raise ConfigError(f"{cfg.scene or 'scene'}: the scene is empty (no renderable objects)")
    frames = tuple(resolve_frames(cfg, scene))
    material_mode = mats.make_untextured(scene) if cfg.materials == "untextured" else None
    sources = None
    if cfg.light == "scene":
        from .lighting import check_lit
        sources = check_lit(scene, cfg.scene or "scene", "scene")  # an unlit scene is refused before its camera
    return SceneStage(cfg, scene, info, frames, resolve_size(cfg, scene), meshes, material_mode, sources)


@dataclass(frozen=True)
class UnitStage(SceneStage):
    """2. The user's level: ``level`` (``lighting.LevelLight``: its geometry without sky meshes and the sky meshes
    found; None for a scene BlendSR built, or when neither a level camera nor a measured light needs it), and where
    a level camera plans: ``geom``, the geometry it plans on, and ``unit``, its unit's record
    (``level_scale.resolve_unit_scale``; the camera stage may still revise an "auto" unit by its views)."""

    level: Any
    geom: Any
    unit: dict | None


def unit_stage(s: SceneStage) -> UnitStage:
    """Stage 2 (needs the scene stage's first frame: the level's geometry is taken there)."""
    cfg = s.cfg
    level = find_level(cfg, s.scene, s.info, s.frames[0])
    if not uses_level_camera(cfg):
        return UnitStage(**vars(s), level=level, geom=None, unit=None)
    from .level_cameras import PathError
    from .level_geometry import LevelGeometryError, from_scene
    from .level_scale import resolve_unit_scale
    from .scene_setup import spawn_points
    try:  # a scene BlendSR built and a level camera (an asset's fly): its whole geometry
        geom = level.level if level is not None else from_scene(s.scene, s.frames[0])
        unit = resolve_unit_scale(geom, cfg.unit_scale, cfg.scene, spawn_points(s.scene))
    except (PathError, LevelGeometryError) as exc:
        raise _camera_path_error(cfg, exc) from None
    return UnitStage(**vars(s), level=level, geom=geom, unit=unit)


@dataclass(frozen=True)
class CameraStage(UnitStage):
    """3. The clip's camera (``scene.camera`` is set to it) and its report for the manifest."""

    cam: Any
    camera_report: dict


def camera_stage(u: UnitStage) -> CameraStage:
    """Stage 3 (needs the frames it is keyed on, and for a level camera the level's geometry without sky meshes
    and its unit: it plans inside them; under ``light = "scene"`` the scene was found lit first)."""
    cfg, scene, frames = u.cfg, u.scene, (u.frames[0], u.frames[-1])
    if u.geom is not None:
        from .level_cameras import PathError
        from .level_geometry import LevelGeometryError
        from .scene_setup import LevelUnit, make_level_camera
        try:
            cam, report = make_level_camera(scene, cfg.camera_path, frames, cfg.seed, region=cfg.extra.get("region"),
                                            rules=level_rules(cfg), geom=u.geom,
                                            unit=LevelUnit(cfg.unit_scale, cfg.scene, u.unit))
        except (PathError, LevelGeometryError) as exc:
            raise _camera_path_error(cfg, exc) from None
    elif cfg.camera_path in ("orbit", "walk"):
        from .camera_paths import make_camera_path
        cam, report = make_camera_path(scene, cfg.camera_path, frames, cfg.seed), {"kind": cfg.camera_path}
    else:
        from .scene_setup import pick_scene_camera
        cam = pick_scene_camera(scene, cfg.camera_path, cfg.scene or "scene", int(cfg.extra.get("camera_index", 0)))
        report = {"kind": "scene", "choice": cfg.camera_path, "name": cam.name}
    check_camera(cam, cfg)
    scene.camera = cam
    return CameraStage(**vars(u), cam=cam, camera_report=report)


@dataclass(frozen=True)
class LightStage(CameraStage):
    """4. ``light``: the manifest's light record (what was kept, added, measured, varied)."""

    light: dict


def light_stage(c: CameraStage) -> LightStage:
    """Stage 4 (needs the camera and the HR size: ``auto`` probes what the camera sees at the clip's aspect over
    its frames; the level and its sky meshes; the scene stage's light sources under ``light = "scene"``)."""
    from .lighting import light_clip
    return LightStage(**vars(c), light=light_clip(c.scene, c.cfg, c.cam, c.frames, c.hr_size, c.level, c.sources))


@dataclass(frozen=True)
class PassStage(LightStage):
    """5. ``my_frames``, the frames this process renders (shard, only_frames); the view layer; the materials,
    their flags (``flag_lut``: material pass index -> flag bits, uint32) and the pass plan; ``behind``, the
    transmissive materials the G-buffer renders see through; ``moving``, the names of the objects that move."""

    my_frames: tuple[int, ...]
    view_layer: Any
    materials: dict
    plan: PassPlan
    behind: tuple[str, ...]
    flag_lut: np.ndarray
    moving: tuple[str, ...]


def pass_stage(lt: LightStage) -> PassStage:
    """Stage 5 (needs everything the light added: the resources count its images, and the materials inspected are
    those that render: untextured, sky meshes drawn unlit)."""
    cfg, scene = lt.cfg, lt.scene
    my_frames = _check_resources(lt)
    view_layer, computed = _render_view_layer(scene), computed_buffers(cfg.buffers, cfg.fbeta)
    infos = mats.inspect_materials(scene)
    mats.raise_alpha_threshold(view_layer)  # a cut-out hole is never a G-buffer surface (the AOVs rely on it)
    aov_names = mats.install_aovs(scene, view_layer, infos, computed)
    moving = [ob for ob in lt.meshes if mats.object_is_moving(ob, scene, lt.frames[0])]
    for ob in lt.meshes:
        ob.pass_index = 1 if ob in moving else 0
    plan = plan_passes(cfg.buffers, cfg.fbeta, aov_names)
    behind = _resolve_behind(cfg, scene, view_layer, infos) if plan.any else ()
    if behind:
        plan = dataclasses.replace(plan, aovs=(*plan.aovs, mats.AOV_REACTIVE))
    flag_lut = np.zeros(len(infos) + 1, dtype=np.uint32)
    flag_lut[0] = int(Flag.NO_MATERIAL)
    for info in infos.values():
        flag_lut[info.index] = material_flags_for_source(info.flags, cfg.fbeta)
    return PassStage(**vars(lt), my_frames=my_frames, view_layer=view_layer, materials=infos, plan=plan, behind=behind,
                     flag_lut=flag_lut, moving=tuple(sorted(ob.name for ob in moving)))


def _check_resources(lt: LightStage) -> tuple[int, ...]:
    """The frames this process renders; refused (``resources``) when the ones not yet done would not fit."""
    from .scene_setup import scene_memory_bytes
    cfg = lt.cfg
    my_frames = tuple(cfg.my_frames(lt.frames))
    undone = [f for f in my_frames if not (cfg.output / FRAMES_DIR / f"{frame_name(f)}.json").is_file()]
    check_render_resources(lt.hr_size, cfg.scales, cfg.buffers, len(undone), cfg.output,
                           scene_bytes=scene_memory_bytes(lt.scene), scene=str(cfg.scene or "scene"))
    return my_frames


def _resolve_behind(cfg: RenderConfig, scene, view_layer, infos: dict) -> tuple[str, ...]:
    """``gbuffer_transmission``: the transmissive materials the G-buffer renders see through ("behind"), prepared
    (``materials.install_behind``); () for "surface", and for a scene without transmissive materials (logged: it
    renders as "surface", with no extra render)."""
    if cfg.gbuffer_transmission != "behind":
        return ()
    behind = mats.transmissive_materials(scene, infos)
    if not behind:
        log.info("blendsr: %s: no transmissive material: gbuffer_transmission behind renders as surface (no extra "
                 "render)", cfg.scene or "scene")
        return ()
    mats.install_behind(view_layer, behind)
    log.info("blendsr: %s: the G-buffers see through %d transmissive material(s): %s", cfg.scene or "scene",
             len(behind), ", ".join(behind))
    return behind


def _render_view_layer(scene):
    """The context's view layer when it belongs to ``scene``, else the scene's first."""
    ctx_vl = getattr(bpy.context, "view_layer", None)
    view_layer = scene.view_layers.get(ctx_vl.name) if ctx_vl is not None else None
    return view_layer or scene.view_layers[0]


# ----------------------------------------------------------------------------------------------
# The product
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ResolvedRender:
    """What a render derives from its configuration and the scene, settled once, before anything is written
    (``resolve_render``): ``frames``, every frame of the clip (a frame's jitter is indexed by its position) and
    ``my_frames``, those this process renders (shard, only_frames); ``hr_size`` and ``levels`` (the manifest's
    {name: {"width", "height", ...}}); ``light``, the manifest's light record; the camera and its report; the view
    layer; the materials, their flags (``flag_lut``: material pass index -> flag bits, uint32) and the pass plan;
    ``moving``, the names of the objects that move (pass index 1); ``material_mode``, the manifest's record of
    ``materials = "untextured"`` (None for "keep"); ``behind``, the transmissive materials the G-buffer renders see
    through (``gbuffer_transmission = "behind"``; empty otherwise, and for a scene without any)."""

    frames: tuple[int, ...]
    my_frames: tuple[int, ...]
    hr_size: tuple[int, int]
    levels: dict
    light: dict
    cam: Any
    camera_report: dict
    view_layer: Any
    materials: dict
    plan: PassPlan
    flag_lut: np.ndarray
    moving: tuple[str, ...]
    material_mode: dict | None = None
    behind: tuple[str, ...] = ()


STAGES = (scene_stage, unit_stage, camera_stage, light_stage, pass_stage)


def resolve_render(cfg: RenderConfig, scene, scene_info: dict | None = None) -> ResolvedRender:
    """Check the scene against ``cfg`` and settle everything the manifest and every frame need: the one place the
    configuration meets the scene, stage by stage (``STAGES``, module doc). Sets up the scene for it (untextured
    materials, camera, light, AOVs, pass indices of moving objects). ``scene_info``: what loading the scene
    recorded (``render.load_scene``; the built-in scene and generated environments keep their light)."""
    s = scene_stage(cfg, scene, scene_info or {})
    u = unit_stage(s)
    c = camera_stage(u)
    lt = light_stage(c)
    p = pass_stage(lt)
    return ResolvedRender(frames=p.frames, my_frames=p.my_frames, hr_size=p.hr_size,
                          levels=levels_header(p.hr_size, cfg.scales), light=p.light, cam=p.cam,
                          camera_report=p.camera_report, view_layer=p.view_layer, materials=p.materials, plan=p.plan,
                          flag_lut=p.flag_lut, moving=p.moving, material_mode=p.material_mode, behind=p.behind)
