"""Render a clip with Cycles (bpy layer): the only module that drives Blender's renderer.

Per frame and in this order:
  1. HR G-buffer pass: ``gbuffer_spp`` samples, Gaussian pixel filter of width 0.01 px (point-sampled at the pixel
     centre, nothing mixes at edges), no bounces but transparent ones (rays pass alpha cut-outs, as in the LR
     render); writes only the passes the requested buffers need.
  2. HR ground truth: ``hr_spp`` samples, Blackman-Harris 1.5 px filter (anti-aliased), the scene's light paths,
     optional adaptive sampling and denoising; Combined pass only.
  3. LR render, once per LR level (``cfg.scales``: 'lr' at the first scale, 'lr_x<s>' at the others): ``lr_spp``
     samples, point-sampled (0.01 px filter, like a rasteriser), optionally jittered by a camera shift and
     denoised, with the level's G-buffer passes in the same render (point sampling makes them valid). Each level is
     rendered at its own size, never downsampled from HR (a downsampled image would be anti-aliased).
Then the passes are converted to the clip's buffers (``convert.CONVERTERS``, one converter per buffer) and written
atomically. What the configuration and the scene settle is resolved once (``resolve_render`` -> frozen
``ResolvedRender``); what every frame shares is one frozen ``RenderContext``.
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import logging
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import bpy
import numpy as np

from .. import __version__
from ..clip import FRAMES_DIR, ClipWriter, frame_name, levels_header
from ..config import ConfigError, RenderConfig, recorded_keys
from ..conventions import (Flag, computed_buffers, exposure_header, halton_jitter, intrinsics_from_projection,
                           level_name, material_flags_for_source, pass_seed)
from ..interrupt import check_interrupt, stop_on_sigint
from ..pixel_filter import HR_REFERENCE_FILTER, POINT_FILTER, footprint_fbeta
from ..regions import dilate
from ..resources import TEMP_EXR_CHANNELS, check_render_resources
from . import materials as mats
from .convert import (BACKGROUND_DEPTH, PASSES, LevelCameras, PassPlan, colour_sum, convert, plan_passes,
                      reactive_mask, read_passes)

log = logging.getLogger(__name__)


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def check_blend_file(path: Path) -> None:
    """ConfigError unless ``path`` starts like a .blend (plain, gzip or zstd compressed)."""
    with open(path, "rb") as f:
        head = f.read(7)
    if not (head.startswith(b"BLENDER") or head[:2] == b"\x1f\x8b" or head[:4] == b"\x28\xb5\x2f\xfd"):
        raise ConfigError(f"{path}: not a .blend file (bad header)")


# ----------------------------------------------------------------------------------------------
# Scene loading and checks
# ----------------------------------------------------------------------------------------------

def load_scene(cfg: RenderConfig):
    """Open the scene file (or build the default scene) and return (scene, scene_info for the manifest)."""
    if cfg.scene is None:
        from ..config import check_builtin_frames
        from .default_scene import build_default_scene
        check_builtin_frames(cfg.frames)
        frames = cfg.frames or (1, 48)
        res = cfg.hr_size or (640, 360)
        scene = build_default_scene(seed=cfg.seed, frames=(min(frames[0], 1), max(frames[1], 48)), resolution=res)
        return scene, {"file": None, "sha256": None, "builtin": "default", "seed": cfg.seed}
    from .scene_setup import check_scene_geometry, load_scene_file
    if cfg.scene.suffix.lower() == ".blend":
        check_blend_file(cfg.scene)
    try:
        scene, loaded = load_scene_file(cfg.scene, cfg.allow_read)
    except RuntimeError as exc:
        raise ConfigError(f"{cfg.scene}: Blender could not open it ({str(exc).splitlines()[0]})") from None
    check_scene_geometry(scene, cfg.scene)  # empty, degenerate, non-finite or absurd: refused before rendering
    allowed = {"allow_read": [str(Path(d).absolute()) for d in cfg.allow_read]} if cfg.allow_read else {}
    return scene, {"file": cfg.scene.name, "sha256": file_sha256(cfg.scene), "builtin": None, **allowed, **loaded}


def renderable_meshes(scene) -> list:
    return [ob for ob in scene.objects if ob.type in ("MESH", "CURVE", "SURFACE", "META", "FONT", "CURVES",
                                                       "POINTCLOUD", "VOLUME")
            and not ob.hide_render]


def has_fog(scene) -> bool:
    """True when a renderable object of ``scene`` is a volume-only domain (``materials.volume_domain``): its G-buffer
    passes need a render of their own with the volumes muted."""
    return any(mats.volume_domain(ob) for ob in renderable_meshes(scene))


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


#: ``light = "sky"``: the least fraction of the upper hemisphere a level camera's eye must see as sky (the sun and
#: sky are the only light; an eye under a roof renders black). 5 %: a street between buildings sees far more.
SKY_LIT_MIN_SKY = 0.05


def level_rules(cfg: RenderConfig):
    """The rules of ``cfg``'s level camera path (``level_cameras.PathRules``): a sky-lit level's eyes must see the
    sky."""
    from .level_cameras import PathRules
    return PathRules(min_sky_fraction=SKY_LIT_MIN_SKY) if cfg.light == "sky" else PathRules()


def setup_camera(cfg: RenderConfig, scene, frames: list[int], level=None):
    """The clip's camera and its report for the manifest (the planned path's rules and measurements). ``level``:
    the level's geometry for a level camera (``lighting.LevelLight.level``; None: taken from the scene)."""
    if uses_level_camera(cfg):
        from .level_cameras import ROOF, PathError
        from .level_geometry import LevelGeometryError
        from .scene_setup import LevelUnit, make_level_camera
        try:
            return make_level_camera(scene, cfg.camera_path, (frames[0], frames[-1]), cfg.seed,
                                     region=cfg.extra.get("region"), rules=level_rules(cfg), geom=level,
                                     unit=LevelUnit(cfg.unit_scale, cfg.scene))
        except (PathError, LevelGeometryError) as exc:
            if isinstance(exc, PathError) and ROOF in exc.reasons:  # a sky-lit walk stood under a roof on some try
                raise ConfigError(f"{cfg.scene or 'scene'}: {exc}; set light auto (it lights a level under a roof "
                                  "with lamps under its ceilings, and adds the sun and sky where the cameras see "
                                  "the sky)", key="light") from None
            raise ConfigError(f"{cfg.scene or 'scene'}: {exc}; blendsr dataset --dry-run names a fix that works for "
                              "a level (another camera kind, fewer regions, unit_scale); a single object (no floor, "
                              "nothing around it) is framed by camera_path orbit", key="camera_path") from None
    if cfg.camera_path in ("orbit", "walk"):
        from .camera_paths import make_camera_path
        return make_camera_path(scene, cfg.camera_path, (frames[0], frames[-1]), cfg.seed), {"kind": cfg.camera_path}
    from .scene_setup import pick_scene_camera
    cam = pick_scene_camera(scene, cfg.camera_path, cfg.scene or "scene", int(cfg.extra.get("camera_index", 0)))
    return cam, {"kind": "scene", "choice": cfg.camera_path, "name": cam.name}


def check_camera(cam, cfg: RenderConfig) -> None:
    if cam.type != "CAMERA":
        raise ConfigError(f"{cfg.scene or 'scene'}: scene camera {cam.name!r} is not a camera object")
    if cam.data.type != "PERSP":
        raise ConfigError(f"{cfg.scene or 'scene'}: camera {cam.name!r} is {cam.data.type.lower()}; only perspective "
                          "cameras are supported (Blender's motion vectors are wrong for orthographic ones)")


# ----------------------------------------------------------------------------------------------
# Render settings
# ----------------------------------------------------------------------------------------------

def base_settings(scene, view_layer, cfg: RenderConfig) -> dict:
    """Settings common to every pass: Cycles on ``cfg.device``, raw linear float EXR output, no post-processing.
    Returns the device Cycles renders on (for the manifest)."""
    from .scene_setup import select_device
    r = scene.render
    r.engine = "CYCLES"
    device = select_device(scene, cfg.device)
    r.resolution_percentage = 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.use_border = False
    r.use_motion_blur = False  # the Vector pass is all zeros with motion blur
    r.film_transparent = False
    r.use_compositing = False
    r.use_sequencer = False
    r.use_persistent_data = True
    r.use_file_extension = False
    if cfg.threads:
        r.threads_mode = "FIXED"
        r.threads = cfg.threads
    else:
        r.threads_mode = "AUTO"
    s = r.image_settings
    s.media_type = "MULTI_LAYER_IMAGE"
    s.color_depth = "32"
    s.exr_codec = "ZIP"
    s.use_exr_interleave = False  # old files may set True; one part per pass either way reads the same
    scene.cycles.use_animated_seed = False
    scene.cycles.film_exposure = 1.0
    for vl in scene.view_layers:
        vl.use = vl == view_layer
    if cfg.max_bounces is not None:
        scene.cycles.max_bounces = cfg.max_bounces
    return device


def set_passes(view_layer, plan: PassPlan) -> None:
    """Enable the passes of ``plan`` (each row of ``convert.PASSES``: its view-layer switches) and no others."""
    vl = view_layer
    vl.use_pass_combined = True
    for field, row in PASSES.items():
        for switch in row.switches:
            setattr(vl, switch, getattr(plan, field))
    owned = {switch for row in PASSES.values() for switch in row.switches}  # a pass a row enables is not also off
    for name in ("use_pass_mist", "use_pass_position", "use_pass_uv", "use_pass_ambient_occlusion",
                 "use_pass_shadow", "use_pass_diffuse_direct", "use_pass_diffuse_indirect", "use_pass_glossy_direct",
                 "use_pass_glossy_indirect", "use_pass_transmission_direct", "use_pass_transmission_indirect"):
        if hasattr(vl, name) and name not in owned:
            setattr(vl, name, False)
    cyc = vl.cycles
    for name in ("denoising_store_passes", "use_pass_volume_direct", "use_pass_volume_indirect",
                 "use_pass_shadow_catcher"):
        if hasattr(cyc, name):
            setattr(cyc, name, False)


def set_sampling(scene, *, spp: int, pixel_filter: tuple[str, float], denoise: bool, adaptive: bool,
                 cfg: RenderConfig, seed: int, light_paths: dict | None) -> dict:
    """Apply one pass's sampling settings (``pixel_filter``: Cycles' filter type and width in pixels, as
    ``POINT_FILTER``; ``light_paths``: the scene's bounce limits, or None for a pass without bounces, every limit
    0); returns them for the manifest."""
    filter_type, filter_width = pixel_filter
    bounces = light_paths is not None
    light_paths = light_paths if bounces else dict.fromkeys(LIGHT_PATH_KEYS, 0)
    c = scene.cycles
    c.samples = spp
    c.pixel_filter_type = filter_type
    c.filter_width = filter_width
    c.seed = seed
    c.use_adaptive_sampling = adaptive
    if adaptive:
        c.adaptive_threshold = cfg.adaptive_threshold
        c.adaptive_min_samples = cfg.adaptive_min_samples
    c.use_denoising = denoise
    if denoise:
        c.denoiser = "OPENIMAGEDENOISE"
        c.denoising_input_passes = "RGB_ALBEDO_NORMAL"
        c.denoising_prefilter = "ACCURATE"
    for k, v in light_paths.items():
        setattr(c, k, v if bounces else 0)
    if not bounces:
        c.use_fast_gi = False
    out = {"spp": spp, "pixel_filter": filter_type, "filter_width_px": filter_width, "seed": seed,
           "denoise": denoise, "adaptive": adaptive}
    if adaptive:
        out.update(adaptive_threshold=cfg.adaptive_threshold, adaptive_min_samples=cfg.adaptive_min_samples)
    if denoise:
        out.update(denoiser="OPENIMAGEDENOISE", denoising_input_passes="RGB_ALBEDO_NORMAL")
    out["light_paths"] = {k: (v if bounces else 0) for k, v in light_paths.items()}
    return out


LIGHT_PATH_KEYS = ("max_bounces", "diffuse_bounces", "glossy_bounces", "transmission_bounces", "volume_bounces",
                   "transparent_max_bounces")


# ----------------------------------------------------------------------------------------------
# Rendering a pass
# ----------------------------------------------------------------------------------------------

@contextlib.contextmanager
def quiet_stdout():
    """Silence Blender's per-render log lines on file descriptor 1 (set BLENDSR_VERBOSE=1 to keep them)."""
    from .fds import captured
    with captured((1,)):
        yield


def _check_disk_after_write(path: Path, scene) -> None:
    """Raise ENOSPC naming ``path``'s folder when it has less free space than Cycles' temporary EXR needs: a full
    disk while Cycles writes leaves no file or a truncated one, which is not the user's EXR to blame."""
    import errno
    import shutil
    r = scene.render
    need = int(r.resolution_x * r.resolution_y * r.resolution_percentage / 100 * TEMP_EXR_CHANNELS * 4)
    try:
        free = shutil.disk_usage(path.parent).free
    except OSError:
        return
    if free < need:
        raise OSError(errno.ENOSPC, f"No space left on device (Cycles' temporary EXR needs about {need} bytes, "
                                    f"{free} free)", str(path.parent))


def render_to(scene, path: Path) -> dict[str, np.ndarray]:
    scene.render.filepath = str(path)
    with quiet_stdout():
        bpy.ops.render.render(write_still=True, scene=scene.name)
    check_interrupt()  # Ctrl-C during the pass: stop here (its 'CANCELLED' result means a refused render instead)
    if not path.is_file():
        _check_disk_after_write(path, scene)
        raise RuntimeError(f"Cycles wrote no output to {path}")
    try:
        return read_passes(path)
    except (ValueError, OSError):
        _check_disk_after_write(path, scene)
        raise


def camera_pose(cam) -> np.ndarray:
    """world_from_camera without scale (4x4 float64)."""
    m = np.array(cam.matrix_world, dtype=np.float64)
    for i in range(3):
        n = np.linalg.norm(m[:3, i])
        if n > 0:
            m[:3, i] /= n
    return m


def camera_intrinsics(cam, scene, width: int, height: int) -> tuple[float, float, float, float]:
    """Un-jittered (fx, fy, cx, cy) of the scene camera for a width x height image."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    proj = cam.calc_matrix_camera(depsgraph, x=width, y=height, scale_x=1.0, scale_y=1.0)
    return intrinsics_from_projection(np.array(proj), width, height)


# ----------------------------------------------------------------------------------------------
# The clip
# ----------------------------------------------------------------------------------------------

def render_clip(cfg: RenderConfig, info: dict | None = None) -> Path:
    """Render (or resume) the clip described by ``cfg`` and return its directory (``info``: more manifest
    ``scene`` entries, e.g. a dataset clip's id). Ctrl-C stops it between Cycles passes
    (``gbuffer_export.interrupt``)."""
    if cfg.frames is not None and cfg.hr_size is not None:  # refuse a runaway before building the scene
        check_render_resources(cfg.hr_size, cfg.scales, cfg.buffers, frames_left(cfg), cfg.output,
                               scene=str(cfg.scene or "scene"))
    with stop_on_sigint():
        scene, scene_info = load_scene(cfg)
        check_interrupt()
        return render_loaded_scene(cfg, scene, {**scene_info, **(info or {})})


def remove_stale_scratch(clip_dir: Path, max_age_s: float = 86400.0) -> list[Path]:
    """Remove the ``.render-PID-*`` scratch folders of renders that died (their process is gone) and old ones of
    the earlier ``.render-*`` form (untouched for ``max_age_s``); a live shard's folder is kept. Returns them."""
    import shutil
    gone = []
    for d in clip_dir.glob(".render-*"):
        if not d.is_dir() or d.is_symlink():
            continue
        parts = d.name.split("-")
        if len(parts) >= 3 and parts[1].isdigit():
            pid = int(parts[1])
            alive = pid != os.getpid()  # this process renders one clip at a time: its own folder is stale
            if alive:
                try:
                    os.kill(pid, 0)
                except ProcessLookupError:
                    alive = False
                except PermissionError:
                    pass
        else:
            try:
                alive = time.time() - d.stat().st_mtime < max_age_s
            except OSError:
                continue
        if not alive:
            shutil.rmtree(d, ignore_errors=True)
            gone.append(d)
    return gone


def frames_left(cfg: RenderConfig) -> int:
    """How many frames of ``cfg.frames`` this shard still renders (its finished frame records subtracted),
    counted without listing the range: a runaway ``--frames 1:1000000`` is refused at once."""
    a, b = cfg.frames
    mine = cfg.my_frames(range(a, b + 1))
    done = 0
    fdir = cfg.output / FRAMES_DIR
    if fdir.is_dir():
        for e in os.scandir(fdir):
            stem, dot, ext = e.name.partition(".")
            if ext == "json" and stem.isdigit() and int(stem) in mine:
                done += 1
    return len(mine) - done


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


def built_by_blendsr(scene_info: dict) -> bool:
    """The built-in scene or an asset in a generated environment: BlendSR built it and its light (sun, HDRI)."""
    return bool(scene_info.get("builtin")) or "asset" in scene_info


def _level_light(cfg: RenderConfig, scene, scene_info: dict, first_frame: int):
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


def resolve_render(cfg: RenderConfig, scene, scene_info: dict | None = None) -> ResolvedRender:
    """Check the scene against ``cfg`` and settle everything the manifest and every frame need: the one place the
    configuration meets the scene (frames inside the scene's range, sizes, light, camera, resources, materials,
    passes). Sets up the scene for it (light, camera, AOVs, pass indices of moving objects). ``scene_info``: what
    loading the scene recorded (``load_scene``; the built-in scene and generated environments keep their light)."""
    if not renderable_meshes(scene):
        raise ConfigError(f"{cfg.scene or 'scene'}: the scene is empty (no renderable objects)")
    frames = resolve_frames(cfg, scene)
    # before the light is probed and the materials inspected: both see the materials that render
    material_mode = mats.make_untextured(scene) if cfg.materials == "untextured" else None
    if cfg.light == "scene":
        from .scene_setup import check_lit
        check_lit(scene, cfg.scene or "scene", "scene")  # an unlit scene is refused before its camera is planned
    ll = _level_light(cfg, scene, scene_info or {}, frames[0])
    cam, camera_report = setup_camera(cfg, scene, frames, ll.level if ll is not None else None)
    check_camera(cam, cfg)
    scene.camera = cam
    hr_size = resolve_size(cfg, scene)
    light = prepare_light(cfg, scene, cam, frames, hr_size, ll)
    my_frames = tuple(cfg.my_frames(frames))
    undone = [f for f in my_frames if not (cfg.output / FRAMES_DIR / f"{frame_name(f)}.json").is_file()]
    from .scene_setup import scene_memory_bytes
    check_render_resources(hr_size, cfg.scales, cfg.buffers, len(undone), cfg.output,
                           scene_bytes=scene_memory_bytes(scene), scene=str(cfg.scene or "scene"))
    view_layer = _render_view_layer(scene)
    infos = mats.inspect_materials(scene)
    mats.raise_alpha_threshold(view_layer)  # a cut-out hole is never a G-buffer surface (the AOVs rely on it)
    aov_names = mats.install_aovs(scene, view_layer, infos, computed_buffers(cfg.buffers, cfg.fbeta))
    plan = plan_passes(cfg.buffers, cfg.fbeta, aov_names)
    behind = _resolve_behind(cfg, scene, view_layer, infos) if plan.any else ()
    if behind:
        plan = dataclasses.replace(plan, aovs=(*plan.aovs, mats.AOV_REACTIVE))
    flag_lut = np.zeros(len(infos) + 1, dtype=np.uint32)
    flag_lut[0] = int(Flag.NO_MATERIAL)
    for info in infos.values():
        flag_lut[info.index] = material_flags_for_source(info.flags, cfg.fbeta)
    moving = [ob for ob in renderable_meshes(scene) if mats.object_is_moving(ob, scene, frames[0])]
    for ob in renderable_meshes(scene):
        ob.pass_index = 1 if ob in moving else 0
    return ResolvedRender(frames=tuple(frames), my_frames=my_frames, hr_size=hr_size,
                          levels=levels_header(hr_size, cfg.scales), light=light, cam=cam, camera_report=camera_report,
                          view_layer=view_layer, materials=infos, plan=plan,
                          flag_lut=flag_lut, moving=tuple(sorted(ob.name for ob in moving)),
                          material_mode=material_mode, behind=behind)


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


@dataclass(frozen=True)
class RenderContext:
    """What every frame of one clip's render shares, fixed before its first frame: the configuration, the scene,
    what was resolved from both (``ResolvedRender``), the scene's own bounce limits (``light_paths``:
    ``LIGHT_PATH_KEYS``) and where files go."""

    cfg: RenderConfig
    scene: Any
    resolved: ResolvedRender
    light_paths: dict
    tmpdir: Path
    writer: ClipWriter


def _manifest_header(cfg: RenderConfig, scene, scene_info: dict, r: ResolvedRender, device: dict,
                     light_paths: dict) -> dict:
    """The clip manifest's header (``device``: ``base_settings``')."""
    plan = r.plan
    return {
        "blendsr_version": __version__,
        "blender_version": bpy.app.version_string,
        "scene": {**scene_info, "name": scene.name, "camera": r.cam.name},
        "scale": cfg.scale,
        "levels": r.levels,
        "frames": list(r.frames),
        "buffers": list(cfg.buffers),
        "fbeta_source": cfg.fbeta,
        "camera_path": cfg.camera_path,
        "camera": r.camera_report,
        "light": r.light,
        "scene_linear": _scene_linear_name(),
        **exposure_header(cfg.exposure),  # auto: metered as frames finish (ClipWriter); 1: no key
        "render": {
            "engine": "CYCLES", "device": device["device"], "device_names": device["names"],
            "device_requested": device["requested"], "seed": cfg.seed, "jitter": cfg.jitter,
            "hr": {"spp": cfg.hr_spp, "denoise": cfg.hr_denoise, "adaptive": cfg.adaptive,
                   "adaptive_threshold": cfg.adaptive_threshold if cfg.adaptive else None,
                   "adaptive_min_samples": cfg.adaptive_min_samples if cfg.adaptive else None,
                   "pixel_filter": HR_REFERENCE_FILTER[0], "filter_width_px": HR_REFERENCE_FILTER[1]},
            "lr": {"spp": cfg.lr_spp, "denoise": cfg.lr_denoise, "pixel_filter": POINT_FILTER[0],
                   "filter_width_px": POINT_FILTER[1]},
            "gbuffer": {"spp": cfg.gbuffer_spp, "pixel_filter": POINT_FILTER[0], "filter_width_px": POINT_FILTER[1],
                        "max_bounces": 0, "hr_pass": plan.any, "lr_source": "the LR render's own passes",
                        "emission_background": "environment" if plan.emit else None,
                        # only when "behind": a clip of the default "surface" keeps the identity it had before the key
                        **_transmission_header(cfg, r),
                        # only when footprint: a point-sampled clip keeps the identity it had before the key
                        **({"hr_fbeta": "footprint"} if _footprint(cfg, plan) else {})},
            "light_paths": light_paths,
            "passes": {k_: v for k_, v in plan.__dict__.items()},
        },
        "materials": {n: i.to_json() for n, i in r.materials.items()},
        "material_summary": mats.material_summary(r.materials),
        # only when untextured: a clip of the scene's own materials keeps the identity it had before the key
        **({"material_mode": r.material_mode} if r.material_mode else {}),
        "moving_objects": list(r.moving),
        # every key added after MANIFEST_BY_HAND, from its rule; none at its legacy value (identity kept)
        **recorded_keys(cfg),
        "shard": list(cfg.shard),
        "command": " ".join(sys.argv),
    }


def _transmission_header(cfg: RenderConfig, r: ResolvedRender) -> dict:
    """The manifest's ``render.gbuffer`` entries of ``gbuffer_transmission = "behind"`` (none for "surface")."""
    if cfg.gbuffer_transmission != "behind":
        return {}
    if not r.behind:
        return {"transmission": "behind", "transmissive_materials": [],
                "transmission_note": "no transmissive material: rendered as surface, no extra render"}
    return {"transmission": "behind", "transmissive_materials": list(r.behind),
            "lr_source": "the LR render's own passes, and where glass is in view a G-buffer render over its "
                         "bounding box (the LR render's camera, jitter, seed and samples)"}


def _footprint(cfg: RenderConfig, plan: PassPlan) -> bool:
    """Whether the HR F_beta is the footprint one (``hr_fbeta``; needs the colour passes and the fbeta buffer)."""
    return plan.colors and "fbeta" in cfg.buffers and cfg.hr_fbeta == "footprint"


def render_loaded_scene(cfg: RenderConfig, scene, scene_info: dict) -> Path:
    """Render the clip from an already loaded scene (the add-on calls this inside Blender)."""
    r = resolve_render(cfg, scene, scene_info)
    device = base_settings(scene, r.view_layer, cfg)
    # One pass set for every render of the clip, set here once: with persistent data, Cycles 5.0.1 renders a frame
    # whose Vector pass was switched off since the previous render with stale texture lookups (measured:
    # GlassBrokenWindow's crack and alpha textures vanished from the ground truth, its glass became a uniform tint;
    # docs/rendering.md, "One pass set per clip"). A render reads only the passes it needs.
    set_passes(r.view_layer, r.plan)
    light_paths = {k_: getattr(scene.cycles, k_) for k_ in LIGHT_PATH_KEYS}
    writer = ClipWriter(cfg.output, _manifest_header(cfg, scene, scene_info, r, device, light_paths))
    todo = [f for f in r.my_frames if not writer.is_frame_done(f)]  # one writer per clip: held until close() below
    skipped = len(r.my_frames) - len(todo)
    if skipped:
        log.info("blendsr: resuming %s: %d of %d frames already done", cfg.output, skipped, len(r.my_frames))
    remove_stale_scratch(cfg.output)
    tmpdir = Path(tempfile.mkdtemp(prefix=f".render-{os.getpid()}-", dir=cfg.output))
    try:
        ctx = RenderContext(cfg=cfg, scene=scene, resolved=r, light_paths=light_paths, tmpdir=tmpdir, writer=writer)
        _render_frames(ctx, todo)
        writer.merge()
    finally:
        for p in tmpdir.glob("*"):
            p.unlink()
        tmpdir.rmdir()
        writer.close()
    return cfg.output


def _render_frames(ctx: RenderContext, todo: list[int]) -> None:
    """Render and commit each frame of ``todo`` (a partial frame is discarded on Ctrl-C)."""
    bar = _progress(todo, ctx.cfg)
    for f in bar:
        check_interrupt()  # Ctrl-C (render_clip, dataset_job: gbuffer_export.interrupt)
        t0 = time.perf_counter()
        try:
            rec = render_frame(ctx, f)
        except KeyboardInterrupt:
            ctx.writer.discard_frame(f)  # the partial frame is never committed
            raise
        rec["seconds_total"] = time.perf_counter() - t0
        ctx.writer.commit_frame(f, rec)
        if hasattr(bar, "set_postfix"):
            bar.set_postfix(gt=f"{rec['hr']['seconds'].get('radiance', 0):.1f}s")


def prepare_light(cfg: RenderConfig, scene, cam, frames: list[int], hr_size: tuple[int, int], ll=None) -> dict:
    """``cfg.light`` "auto": keep the file's light where it lights what ``cam`` sees, add a sun and sky and/or
    ceiling lights where it does not (``lighting``); "sky": add a default sun and sky; "scene": keep the file's
    light, refused when nothing lights it. ``ll``: the user's level and its sky meshes (``lighting.LevelLight``;
    None for a scene BlendSR built, whose light is its own); under auto and sky its sky meshes are seen by the
    camera only. Returns the manifest's ``light`` record."""
    from .scene_setup import add_sky, apply_variation, check_lit
    sky_meshes = {}
    if ll is not None:
        from .lighting import treat_sky_meshes
        treated = treat_sky_meshes(scene, ll) if cfg.light in ("auto", "sky") else []
        sky_meshes = {"sky_meshes": {"found": list(ll.sky_meshes), "treated": treated, "candidates": ll.sky_report}}
    if cfg.light == "sky":
        out = {**add_sky(scene, cfg.seed), "scene_sources": check_lit(scene, cfg.scene or "scene", "sky")}
    elif cfg.light == "auto" and ll is not None:
        from .lighting import auto_light
        out = auto_light(scene, cfg, cam, frames, hr_size, ll)
    elif cfg.light == "auto":
        from .lighting import unmeasured_auto_light
        out = unmeasured_auto_light(scene, cfg.seed)
    else:
        out = {"light": "scene", "scene_sources": check_lit(scene, cfg.scene or "scene", "scene")}
    out.update(sky_meshes)
    variation = apply_variation(scene, cfg.extra.get("variation"))
    if variation:
        out["variation"] = variation
    return out


def _scene_linear_name() -> str:
    """Name of the scene-linear (working) colour space: the primaries of the radiance buffers."""
    cs = getattr(bpy.data, "colorspace", None)
    name = getattr(cs, "working_space", None) if cs is not None else None
    return str(name) if name else "Linear Rec.709"


def _progress(frames, cfg):
    from .devices import probe_devices
    probe_devices()  # Cycles' GPU-library warnings now (dropped), not inside the first frame's bar
    if not cfg.progress:
        return frames
    from tqdm import tqdm
    return tqdm(frames, desc="render", unit="frame", file=sys.stderr, dynamic_ncols=True)


def frame_cameras(ctx: RenderContext, frame: int) -> LevelCameras:
    """The HR camera of ``frame``: poses and intrinsics of frames t, t-1 and (with ``motion_next``) t+1. Leaves the
    scene at ``frame``."""
    cam, scene = ctx.resolved.cam, ctx.scene
    w, h = ctx.resolved.hr_size
    scene.frame_set(frame - 1)
    m_prev, k_prev = camera_pose(cam), camera_intrinsics(cam, scene, w, h)
    m_next = k_next = None
    if "motion_next" in ctx.cfg.buffers:  # the camera of frame t+1 (Cycles' Vector pass evaluates it too)
        scene.frame_set(frame + 1)
        m_next, k_next = camera_pose(cam), camera_intrinsics(cam, scene, w, h)
    scene.frame_set(frame)
    return LevelCameras(camera_pose(cam), camera_intrinsics(cam, scene, w, h), m_prev, k_prev, m_next, k_next)


def render_frame(ctx: RenderContext, frame: int) -> dict:
    """Render one frame at every level of ``ctx.resolved.levels``, write its buffers, return its record."""
    cams = frame_cameras(ctx, frame)
    record = {"hr": render_hr(ctx, frame, cams)}
    cfg = ctx.cfg
    jit = halton_jitter(ctx.resolved.frames.index(frame)) if cfg.jitter == "halton" else (0.0, 0.0)
    for i, scale in enumerate(cfg.scales):
        record[level_name(scale, cfg.scales[0])] = render_lr_level(ctx, frame, cams, i, scale, jit)
    return record


def render_gbuffer(ctx: RenderContext, path: Path, seed: int, spp: int,
                   pixel_filter: tuple[str, float] = POINT_FILTER) -> dict[str, np.ndarray]:
    """A G-buffer render at the scene's current size and camera: ``spp`` samples (point-sampled unless
    ``pixel_filter`` says otherwise), no bounces but the scene's transparent ones (the rays pass alpha cut-outs, as
    in the LR render); with ``gbuffer_transmission = "behind"`` its transmissive materials are transparent too
    (``materials.see_through``); fog and other volume-only domains are muted (``materials.volumes_muted``).
    Returns its passes."""
    set_sampling(ctx.scene, spp=spp, pixel_filter=pixel_filter, denoise=False, adaptive=False,
                 cfg=ctx.cfg, seed=seed, light_paths=None)
    # camera rays pass alpha cut-outs as in the LR render, whose passes are the LR G-buffers (docs/rendering.md)
    ctx.scene.cycles.transparent_max_bounces = ctx.light_paths["transparent_max_bounces"]
    with mats.see_through(ctx.resolved.behind), mats.volumes_muted(ctx.scene):
        return render_to(ctx.scene, path)


def bounding_box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1), end-exclusive, of the True pixels of a non-empty H x W ``mask`` (rows from the top)."""
    ys, xs = np.nonzero(mask)
    return int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1


@contextlib.contextmanager
def render_border(scene, mask: np.ndarray):
    """While inside, Cycles renders only the bounding box of ``mask`` (H x W bool, rows from the top) with a pixel
    to spare, into a full-size image (the rest is not rendered: read only what ``mask`` covers)."""
    r = scene.render
    h, w = mask.shape
    y0, y1, x0, x1 = bounding_box(mask)
    saved = (r.use_border, r.use_crop_to_border, r.border_min_x, r.border_max_x, r.border_min_y, r.border_max_y)
    r.use_border, r.use_crop_to_border = True, False
    r.border_min_x, r.border_max_x = max(x0 - 1, 0) / w, min(x1 + 1, w) / w
    r.border_min_y, r.border_max_y = 1.0 - min(y1 + 1, h) / h, 1.0 - max(y0 - 1, 0) / h  # y up
    try:
        yield
    finally:
        (r.use_border, r.use_crop_to_border, r.border_min_x, r.border_max_x, r.border_min_y,
         r.border_max_y) = saved


def render_hr(ctx: RenderContext, frame: int, cams: LevelCameras) -> dict:
    """The HR level of a frame: the G-buffer pass (when any G-buffer is asked for), then the ground truth; writes
    its buffers and returns its record."""
    cfg, scene, plan = ctx.cfg, ctx.scene, ctx.resolved.plan
    scene.render.resolution_x, scene.render.resolution_y = ctx.resolved.hr_size
    seconds, hr_out, near_glass = {}, {}, None
    if plan.any:
        t = time.perf_counter()
        passes = render_gbuffer(ctx, ctx.tmpdir / "hr_gbuffer.exr", pass_seed(cfg.seed, frame, 0), cfg.gbuffer_spp)
        seconds["gbuffer"] = time.perf_counter() - t
        bg = passes["Depth"][..., 0] >= BACKGROUND_DEPTH
        # footprints reaching glass: the ground truth's colour passes see the glass there ("behind")
        near_glass = dilate(reactive_mask(passes), 1) if ctx.resolved.behind else None
        t = time.perf_counter()
        hr_out = convert(passes, plan, cfg.buffers, cams, jitter=(0.0, 0.0), flag_lut=ctx.resolved.flag_lut,
                         fbeta_source=cfg.fbeta)
        seconds["convert"] = time.perf_counter() - t
    footprint = _footprint(cfg, plan)
    if not (footprint and near_glass is not None and near_glass.any()):
        near_glass = None
    if footprint and has_fog(scene):   # the radiance render's colour passes hold the fog: take every pixel's behind
        near_glass = np.ones(bg.shape, dtype=bool)
    if near_glass is not None:  # the surface behind, filtered alike (the ground truth's filter, seed and samples)
        t = time.perf_counter()
        with render_border(scene, near_glass):
            behind = render_gbuffer(ctx, ctx.tmpdir / "hr_footprint.exr", pass_seed(cfg.seed, frame, 1),
                                    cfg.hr_spp, HR_REFERENCE_FILTER)
        seconds["footprint"] = time.perf_counter() - t
        behind_colors = colour_sum(behind)
    settings_hr = set_sampling(scene, spp=cfg.hr_spp, pixel_filter=HR_REFERENCE_FILTER, denoise=cfg.hr_denoise,
                               adaptive=cfg.adaptive, cfg=cfg, seed=pass_seed(cfg.seed, frame, 1),
                               light_paths=ctx.light_paths)
    t = time.perf_counter()
    passes = render_to(scene, ctx.tmpdir / "hr_radiance.exr")
    seconds["radiance"] = time.perf_counter() - t
    hr_out["radiance"] = passes["Combined"][..., :3]
    if footprint:
        filtered = colour_sum(passes)
        if near_glass is not None:
            filtered = np.where(near_glass[..., None], behind_colors, filtered)
        hr_out["fbeta"] = footprint_fbeta(hr_out["fbeta"], filtered, bg)
    t = time.perf_counter()
    for b in cfg.buffers:
        ctx.writer.write_buffer(frame, "hr", b, hr_out[b])
    seconds["write"] = time.perf_counter() - t
    return cams.record(jitter=[0.0, 0.0], spp=cfg.hr_spp, seed=settings_hr["seed"],
                       gbuffer_seed=pass_seed(cfg.seed, frame, 0) if plan.any else None, seconds=seconds)


def lr_gbuffer_behind(ctx: RenderContext, path: Path, passes: dict, seed: int) -> dict:
    """``gbuffer_transmission = "behind"`` at an LR level: ``passes`` (the LR render's) with those of a G-buffer
    render over the bounding box of the pixels whose first surface is transmissive (the LR render's
    ``AOV_REACTIVE``, grown by a pixel): the same camera, jitter, seed and samples, so every other pixel of the box
    gets the values it has in ``passes``. ``passes`` itself when no glass is in view (no render)."""
    near = dilate(reactive_mask(passes), 1)
    if not near.any():
        return passes
    with render_border(ctx.scene, near):
        behind = render_gbuffer(ctx, path, seed, ctx.cfg.lr_spp)
    y0, y1, x0, x1 = bounding_box(near)
    box = np.zeros((*near.shape, 1), bool)
    box[y0:y1, x0:x1] = True
    return {k: np.where(box, behind[k], v) if k in behind and k != "Combined" else v for k, v in passes.items()}


def render_lr_level(ctx: RenderContext, frame: int, cams_hr: LevelCameras, i: int, scale: float, jit) -> dict:
    """Render LR level ``i`` of ``cfg.scales`` (size HR / ``scale``) of a frame, jittered by ``jit`` pixels of the
    level, with its G-buffer passes in the same render; write its buffers and return its record. Cycles seed:
    pass 2 + i."""
    cfg, scene, cam = ctx.cfg, ctx.scene, ctx.resolved.cam
    lvl = level_name(scale, cfg.scales[0])
    lw, lh = ctx.resolved.levels[lvl]["width"], ctx.resolved.levels[lvl]["height"]
    cams = cams_hr.at_scale(scale)
    scene.render.resolution_x, scene.render.resolution_y = lw, lh
    # shift is in units of the larger image side; +shift_x moves content left (sample at p + dx),
    # +shift_y moves content down in y-down image coordinates (sample at p - dy): see conventions.
    base_shift = (cam.data.shift_x, cam.data.shift_y)
    cam.data.shift_x = base_shift[0] + jit[0] / max(lw, lh)
    cam.data.shift_y = base_shift[1] - jit[1] / max(lw, lh)
    settings_lr = set_sampling(scene, spp=cfg.lr_spp, pixel_filter=POINT_FILTER, denoise=cfg.lr_denoise,
                               adaptive=False, cfg=cfg, seed=pass_seed(cfg.seed, frame, 2 + i),
                               light_paths=ctx.light_paths)
    seconds, extra = {}, {}
    plan = ctx.resolved.plan
    try:
        t = time.perf_counter()
        passes = gpasses = render_to(scene, ctx.tmpdir / f"{lvl}.exr")
        seconds["radiance"] = time.perf_counter() - t
        fog = plan.any and has_fog(scene)
        if plan.any and (ctx.resolved.behind or fog):
            t = time.perf_counter()
            gpasses = (render_gbuffer(ctx, ctx.tmpdir / f"{lvl}_gbuffer.exr", settings_lr["seed"], cfg.lr_spp) if fog
                       else lr_gbuffer_behind(ctx, ctx.tmpdir / f"{lvl}_gbuffer.exr", passes, settings_lr["seed"]))
            if gpasses is not passes:
                seconds["gbuffer"] = time.perf_counter() - t
                extra["gbuffer_seed"] = settings_lr["seed"]
    finally:
        cam.data.shift_x, cam.data.shift_y = base_shift
    t = time.perf_counter()
    lr_out = convert(gpasses, plan, cfg.buffers, cams, jitter=jit, flag_lut=ctx.resolved.flag_lut,
                     fbeta_source=cfg.fbeta) if plan.any else {}
    lr_out["radiance"] = passes["Combined"][..., :3]
    seconds["convert"] = time.perf_counter() - t
    t = time.perf_counter()
    for b in cfg.buffers:
        ctx.writer.write_buffer(frame, lvl, b, lr_out[b])
    seconds["write"] = time.perf_counter() - t
    return cams.record(jitter=list(jit), spp=cfg.lr_spp, seed=settings_lr["seed"], **extra, seconds=seconds)
