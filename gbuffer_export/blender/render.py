"""Render a clip with Cycles (bpy layer): the only module that drives Blender's renderer.

Per frame and in this order:
  1. HR G-buffer pass: ``gbuffer_spp`` samples, Gaussian pixel filter of width 0.01 px (point-sampled at the pixel
     centre, nothing mixes at edges), no bounces; writes only the passes the requested buffers need.
  2. HR ground truth: ``hr_spp`` samples, Blackman-Harris 1.5 px filter (anti-aliased), the scene's light paths,
     optional adaptive sampling and denoising; Combined pass only.
  3. LR render, once per LR level (``cfg.scales``: 'lr' at the first scale, 'lr_x<s>' at the others): ``lr_spp``
     samples, point-sampled (0.01 px filter, like a rasteriser), optionally jittered by a camera shift and
     denoised, with the level's G-buffer passes in the same render (point sampling makes them valid). Each level is
     rendered at its own size, never downsampled from HR (a downsampled image would be anti-aliased).
Then the passes are converted to the clip's conventions (``gbuffer_export.conventions``) and written atomically.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import bpy
import numpy as np

from .. import __version__
from ..clip import FRAMES_DIR, ClipError, ClipWriter, frame_name, levels_header
from ..config import ConfigError, RenderConfig
from ..conventions import (Flag, background_motion, halton_jitter, intrinsics_from_projection, level_name,
                           material_flags_for_source, pass_seed, scale_intrinsics, world_to_camera_normals)
from ..exr import read_exr_channels
from ..interrupt import check_interrupt, stop_on_sigint
from ..pixel_filter import HR_REFERENCE_FILTER, POINT_FILTER
from ..resources import TEMP_EXR_CHANNELS, check_render_resources
from . import materials as mats

BACKGROUND_DEPTH = 1e9  # Cycles writes 1e10 for background in the Depth pass


@dataclass(frozen=True)
class PassPlan:
    """Which Cycles passes a render needs, derived from the requested buffers."""

    depth: bool = False
    normal: bool = False
    vector: bool = False
    colors: bool = False
    emit: bool = False
    index: bool = False
    aovs: tuple[str, ...] = ()

    @property
    def any(self) -> bool:
        return any((self.depth, self.normal, self.vector, self.colors, self.emit, self.index, self.aovs))


def plan_passes(buffers, fbeta: str, aov_names) -> PassPlan:
    """The passes that the G-buffers in ``buffers`` need, and no others."""
    b = set(buffers)
    need_gbuf = bool(b - {"radiance"})
    table_fbeta = "fbeta" in b and fbeta != "cycles"
    return PassPlan(
        depth=need_gbuf,  # background mask for every G-buffer
        normal="normal" in b or table_fbeta,
        vector="motion" in b or "motion_next" in b,  # one Vector pass holds both
        colors="fbeta" in b and fbeta == "cycles",
        emit="emission" in b,
        index="flags" in b or "fbeta" in b,
        aovs=tuple(aov_names),
    )


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
    from .scene_setup import load_scene_file
    if cfg.scene.suffix.lower() == ".blend":
        check_blend_file(cfg.scene)
    try:
        scene = load_scene_file(cfg.scene)
    except RuntimeError as exc:
        raise ConfigError(f"{cfg.scene}: Blender could not open it ({str(exc).splitlines()[0]})") from None
    return scene, {"file": cfg.scene.name, "sha256": file_sha256(cfg.scene), "builtin": None}


def renderable_meshes(scene) -> list:
    return [ob for ob in scene.objects if ob.type in ("MESH", "CURVE", "SURFACE", "META", "FONT", "CURVES",
                                                       "POINTCLOUD", "VOLUME")
            and not ob.hide_render]


def resolve_frames(cfg: RenderConfig, scene) -> list[int]:
    start, end = scene.frame_start, scene.frame_end
    if cfg.frames is None:
        return list(range(start, end + 1))
    a, b = cfg.frames
    if cfg.scene is not None and cfg.camera_path.startswith("scene") and (a < start or b > end):
        raise ConfigError(f"--frames {a}:{b} is outside the scene's range {start}:{end}")
    return list(range(a, b + 1))


def resolve_size(cfg: RenderConfig, scene) -> tuple[int, int]:
    if cfg.hr_size is not None:
        return cfg.hr_size
    pct = scene.render.resolution_percentage / 100.0
    w, h = int(scene.render.resolution_x * pct), int(scene.render.resolution_y * pct)
    try:
        cfg.check_size((w, h), "scene resolution")
    except ConfigError as exc:
        raise ConfigError(f"{exc}; pass --hr-size") from None
    return w, h


def uses_level_camera(cfg: RenderConfig) -> bool:
    """fly always, and walk in a user's scene file, move inside the level (``level_cameras``); orbit and the
    built-in scene's walk frame the scene's bounds (``camera_paths``)."""
    return cfg.camera_path == "fly" or (cfg.camera_path == "walk" and cfg.scene is not None)


def setup_camera(cfg: RenderConfig, scene, frames: list[int]):
    """The clip's camera and its report for the manifest (the planned path's rules and measurements)."""
    if uses_level_camera(cfg):
        from .level_cameras import PathError
        from .scene_setup import make_level_camera
        try:
            return make_level_camera(scene, cfg.camera_path, (frames[0], frames[-1]), cfg.seed,
                                     region=cfg.extra.get("region"))
        except PathError as exc:
            raise ConfigError(f"{cfg.scene or 'scene'}: {exc}; a single object (no floor, nothing around it) is "
                              "framed by --camera-path orbit") from None
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
    vl = view_layer
    vl.use_pass_combined = True
    vl.use_pass_z = plan.depth
    vl.use_pass_normal = plan.normal
    vl.use_pass_vector = plan.vector
    vl.use_pass_diffuse_color = vl.use_pass_glossy_color = vl.use_pass_transmission_color = plan.colors
    vl.use_pass_emit = plan.emit
    vl.use_pass_environment = plan.emit  # the emission buffer's background pixels (conventions: emission)
    vl.use_pass_material_index = plan.index
    vl.use_pass_object_index = plan.index
    for name in ("use_pass_mist", "use_pass_position", "use_pass_uv", "use_pass_ambient_occlusion",
                 "use_pass_shadow"):
        if hasattr(vl, name):
            setattr(vl, name, False)
    for name in ("use_pass_diffuse_direct", "use_pass_diffuse_indirect", "use_pass_glossy_direct",
                 "use_pass_glossy_indirect", "use_pass_transmission_direct", "use_pass_transmission_indirect"):
        setattr(vl, name, False)
    cyc = vl.cycles
    for name in ("denoising_store_passes", "use_pass_volume_direct", "use_pass_volume_indirect",
                 "use_pass_shadow_catcher"):
        if hasattr(cyc, name):
            setattr(cyc, name, False)


def set_sampling(scene, *, spp: int, filter_width: float, filter_type: str, bounces: bool, denoise: bool,
                 adaptive: bool, cfg: RenderConfig, seed: int, light_paths: dict) -> dict:
    """Apply one pass's sampling settings; returns them for the manifest."""
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
# Reading passes
# ----------------------------------------------------------------------------------------------

def read_passes(path: Path) -> dict[str, np.ndarray]:
    """Passes of a Blender multilayer EXR as {'Combined': HxWx4, 'Depth': HxWx1, ...} (view-layer prefix dropped,
    channels in the order RGBA / XYZW)."""
    raw = read_exr_channels(path)
    groups: dict[str, dict[str, np.ndarray]] = {}
    for full, arr in raw.items():
        parts = full.split(".")
        if len(parts) < 2:
            continue
        groups.setdefault(parts[-2], {})[parts[-1]] = arr
    order = "RGBAXYZW"
    out = {}
    for name, chans in groups.items():
        keys = sorted(chans, key=lambda c: order.index(c) if c in order else 99)
        out[name] = np.stack([chans[k] for k in keys], axis=-1).astype(np.float32)
    return out


@contextlib.contextmanager
def quiet_stdout():
    """Silence Blender's per-render log lines on file descriptor 1 (set BLENDSR_VERBOSE=1 to keep them)."""
    if os.environ.get("BLENDSR_VERBOSE"):
        yield
        return
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 1)
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


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
# Conversion to the clip's buffers
# ----------------------------------------------------------------------------------------------

def convert(passes: dict, plan: PassPlan, buffers, *, m, k, m_prev, k_prev, jitter, flag_lut: np.ndarray,
            fbeta_source: str, m_next=None, k_next=None) -> dict[str, np.ndarray]:
    """Turn Cycles passes of one level into clip buffers (see conventions). ``m_next``, ``k_next``: the camera of
    frame t+1, needed for ``motion_next``."""
    out = {}
    depth = passes["Depth"][..., 0].astype(np.float64) if plan.depth else None
    bg = depth >= BACKGROUND_DEPTH if depth is not None else None
    if "depth" in buffers:
        out["depth"] = np.where(bg, np.inf, depth)[..., None]
    if "normal" in buffers or (fbeta_source != "cycles" and "fbeta" in buffers):
        n = world_to_camera_normals(passes["Normal"][..., :3], m)
        out["normal"] = np.where(bg[..., None], 0.0, n)
    if "motion" in buffers:
        vec = passes["Vector"]
        mv = np.stack([vec[..., 0], -vec[..., 1]], axis=-1).astype(np.float64)
        h, w = mv.shape[:2]
        bgm = background_motion(h, w, k, m, k_prev, m_prev, jitter)
        out["motion"] = np.where(bg[..., None], bgm, mv)
    if "motion_next" in buffers:
        # Vector Z, W = p(t) - p(t+1) with y up: p_next - p = (-Z, +W) in image coordinates (y down)
        vec = passes["Vector"]
        mv = np.stack([-vec[..., 2], vec[..., 3]], axis=-1).astype(np.float64)
        h, w = mv.shape[:2]
        bgm = background_motion(h, w, k, m, k_next, m_next, jitter)
        out["motion_next"] = np.where(bg[..., None], bgm, mv)
    flags = None
    if plan.index:
        mat_index = np.rint(passes["Material Index"][..., 0]).astype(np.int64)
        obj_index = np.rint(passes["Object Index"][..., 0]).astype(np.int64)
        mat_index = np.clip(mat_index, 0, len(flag_lut) - 1)
        flags = flag_lut[mat_index].astype(np.uint32)
        flags |= np.where(obj_index > 0, int(Flag.MOVING), 0).astype(np.uint32)
        flags = np.where(bg, int(Flag.BACKGROUND), flags).astype(np.uint32)
        if "flags" in buffers:
            out["flags"] = flags[..., None]
    for b, aov in (*mats.AOV_COLOR.items(), *mats.AOV_VALUE.items()):
        if b in buffers:
            arr = passes[aov][..., :3] if b in mats.AOV_COLOR else passes[aov][..., :1]
            out[b] = np.where(bg[..., None], 0.0, arr)
    if "emission" in buffers:
        # surfaces: their emission; background: the environment seen directly (conventions: emission)
        out["emission"] = np.maximum(np.where(bg[..., None], passes["Environment"][..., :3],
                                              passes["Emission"][..., :3]), 0.0)
    if "fbeta" in buffers:
        if fbeta_source == "cycles":
            fb = (passes["Diffuse Color"][..., :3] + passes["Glossy Color"][..., :3]
                  + passes["Transmission Color"][..., :3])
        else:
            from ..brdf import compute_fbeta
            gbuf = {key: out[key] for key in ("albedo", "normal", "roughness", "metallic", "specular") if key in out}
            gbuf["flags"] = flags[..., None]
            fb = compute_fbeta(fbeta_source, gbuf, k, jitter)
        out["fbeta"] = np.where(bg[..., None], 1.0, fb)
    return out


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
    k, n = cfg.shard
    mine = range(a, b + 1)[k - 1::n]
    done = 0
    fdir = cfg.output / FRAMES_DIR
    if fdir.is_dir():
        for e in os.scandir(fdir):
            stem, dot, ext = e.name.partition(".")
            if ext == "json" and stem.isdigit() and int(stem) in mine:
                done += 1
    return len(mine) - done


def render_loaded_scene(cfg: RenderConfig, scene, scene_info: dict) -> Path:
    """Render the clip from an already loaded scene (the add-on calls this inside Blender)."""
    if not renderable_meshes(scene):
        raise ConfigError(f"{cfg.scene or 'scene'}: the scene is empty (no renderable objects)")
    all_frames = resolve_frames(cfg, scene)
    light = prepare_light(cfg, scene)
    cam, camera_report = setup_camera(cfg, scene, all_frames)
    check_camera(cam, cfg)
    scene.camera = cam
    w, h = resolve_size(cfg, scene)
    levels = levels_header((w, h), cfg.scales)
    undone = [f for i, f in enumerate(all_frames) if i % cfg.shard[1] == cfg.shard[0] - 1
              and not (cfg.output / FRAMES_DIR / f"{frame_name(f)}.json").is_file()]
    from .scene_setup import scene_memory_bytes
    check_render_resources((w, h), cfg.scales, cfg.buffers, len(undone), cfg.output,
                           scene_bytes=scene_memory_bytes(scene), scene=str(cfg.scene or "scene"))
    ctx_vl = getattr(bpy.context, "view_layer", None)
    view_layer = scene.view_layers.get(ctx_vl.name) if ctx_vl is not None else None
    view_layer = view_layer or scene.view_layers[0]
    infos = mats.inspect_materials(scene)
    need_fbeta_gbuf = "fbeta" in cfg.buffers and cfg.fbeta != "cycles"
    aov_buffers = set(cfg.buffers) | ({"albedo", "roughness", "metallic", "specular"} if need_fbeta_gbuf else set())
    aov_names = mats.install_aovs(scene, view_layer, infos, aov_buffers)
    plan = plan_passes(aov_buffers, cfg.fbeta, aov_names)
    flag_lut = np.zeros(len(infos) + 1, dtype=np.uint32)
    flag_lut[0] = int(Flag.NO_MATERIAL)
    for info in infos.values():
        flag_lut[info.index] = material_flags_for_source(info.flags, cfg.fbeta)
    moving = [ob for ob in renderable_meshes(scene) if mats.object_is_moving(ob, scene, all_frames[0])]
    for ob in renderable_meshes(scene):
        ob.pass_index = 1 if ob in moving else 0

    device = base_settings(scene, view_layer, cfg)
    light_paths = {k_: getattr(scene.cycles, k_) for k_ in LIGHT_PATH_KEYS}
    shard_k, shard_n = cfg.shard
    my_frames = [f for i, f in enumerate(all_frames) if i % shard_n == shard_k - 1]
    header = {
        "blendsr_version": __version__,
        "blender_version": bpy.app.version_string,
        "scene": {**scene_info, "name": scene.name, "camera": cam.name},
        "scale": cfg.scale,
        "levels": levels,
        "frames": all_frames,
        "buffers": list(cfg.buffers),
        "fbeta_source": cfg.fbeta,
        "camera_path": cfg.camera_path,
        "camera": camera_report,
        "light": light,
        "scene_linear": _scene_linear_name(),
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
                        "emission_background": "environment" if plan.emit else None},
            "light_paths": light_paths,
            "passes": {k_: v for k_, v in plan.__dict__.items()},
        },
        "materials": {n: i.to_json() for n, i in infos.items()},
        "material_summary": mats.material_summary(infos),
        "moving_objects": sorted(ob.name for ob in moving),
        "shard": [shard_k, shard_n],
        "command": " ".join(sys.argv),
    }
    writer = ClipWriter(cfg.output, header)  # one writer per clip: held until writer.close() below
    todo = [f for f in my_frames if not writer.is_frame_done(f)]
    skipped = len(my_frames) - len(todo)
    if skipped:
        print(f"blendsr: resuming {cfg.output}: {skipped} of {len(my_frames)} frames already done", file=sys.stderr)
    remove_stale_scratch(cfg.output)
    tmpdir = Path(tempfile.mkdtemp(prefix=f".render-{os.getpid()}-", dir=cfg.output))
    try:
        bar = _progress(todo, cfg)
        for f in bar:
            check_interrupt()  # Ctrl-C (render_clip, dataset_job: gbuffer_export.interrupt)
            t0 = time.perf_counter()
            try:
                rec = render_frame(scene, cam, view_layer, cfg, f, all_frames.index(f), plan, flag_lut,
                                   light_paths, levels, tmpdir, writer)
            except KeyboardInterrupt:
                writer.discard_frame(f)  # the partial frame is never committed
                raise
            rec["seconds_total"] = time.perf_counter() - t0
            writer.commit_frame(f, rec)
            if hasattr(bar, "set_postfix"):
                bar.set_postfix(gt=f"{rec['hr']['seconds'].get('radiance', 0):.1f}s")
        writer.merge()
    finally:
        for p in tmpdir.glob("*"):
            p.unlink()
        tmpdir.rmdir()
        writer.close()
    return cfg.output


def prepare_light(cfg: RenderConfig, scene) -> dict:
    """``cfg.light`` "sky": add a default sun and sky; "scene": keep the file's light, refused when nothing lights
    it. Returns the manifest's ``light`` record."""
    from .scene_setup import add_sky, apply_variation, check_lit
    if cfg.light == "sky":
        out = {**add_sky(scene, cfg.seed), "scene_sources": check_lit(scene, cfg.scene or "scene", "sky")}
    else:
        out = {"light": "scene", "scene_sources": check_lit(scene, cfg.scene or "scene", "scene")}
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


def render_frame(scene, cam, view_layer, cfg: RenderConfig, frame: int, index: int, plan: PassPlan,
                 flag_lut, light_paths, levels: dict, tmpdir: Path, writer: ClipWriter) -> dict:
    """Render one frame at every level of ``levels`` (the manifest's), write its buffers, return its record."""
    w, h = levels["hr"]["width"], levels["hr"]["height"]
    scene.frame_set(frame - 1)
    m_prev = camera_pose(cam)
    k_prev_hr = camera_intrinsics(cam, scene, w, h)
    m_next = k_next_hr = None
    if "motion_next" in cfg.buffers:  # the camera of frame t+1 (Cycles' Vector pass evaluates it too)
        scene.frame_set(frame + 1)
        m_next = camera_pose(cam)
        k_next_hr = camera_intrinsics(cam, scene, w, h)
    scene.frame_set(frame)
    m = camera_pose(cam)
    k_hr = camera_intrinsics(cam, scene, w, h)
    gbuf_buffers = [b for b in cfg.buffers if b != "radiance"]
    if "fbeta" in cfg.buffers and cfg.fbeta != "cycles":  # table sources read these even when not written
        gbuf_buffers += [b for b in ("albedo", "normal", "roughness", "metallic", "specular", "flags")
                         if b not in gbuf_buffers]
    base_shift = (cam.data.shift_x, cam.data.shift_y)
    record = {}

    # --- HR: G-buffer pass, then ground truth -----------------------------------------------------------
    scene.render.resolution_x, scene.render.resolution_y = w, h
    seconds = {}
    hr_out = {}
    if plan.any:
        set_passes(view_layer, plan)
        settings_g = set_sampling(scene, spp=cfg.gbuffer_spp, filter_width=POINT_FILTER[1], filter_type=POINT_FILTER[0],
                                  bounces=False, denoise=False, adaptive=False, cfg=cfg,
                                  seed=pass_seed(cfg.seed, frame, 0), light_paths=light_paths)
        t = time.perf_counter()
        passes = render_to(scene, tmpdir / "hr_gbuffer.exr")
        seconds["gbuffer"] = time.perf_counter() - t
        t = time.perf_counter()
        hr_out = convert(passes, plan, gbuf_buffers, m=m, k=k_hr, m_prev=m_prev, k_prev=k_prev_hr,
                         jitter=(0.0, 0.0), flag_lut=flag_lut, fbeta_source=cfg.fbeta, m_next=m_next,
                         k_next=k_next_hr)
        seconds["convert"] = time.perf_counter() - t
    set_passes(view_layer, PassPlan())
    settings_hr = set_sampling(scene, spp=cfg.hr_spp, filter_width=HR_REFERENCE_FILTER[1], filter_type=HR_REFERENCE_FILTER[0], bounces=True,
                               denoise=cfg.hr_denoise, adaptive=cfg.adaptive, cfg=cfg,
                               seed=pass_seed(cfg.seed, frame, 1), light_paths=light_paths)
    t = time.perf_counter()
    passes = render_to(scene, tmpdir / "hr_radiance.exr")
    seconds["radiance"] = time.perf_counter() - t
    hr_out["radiance"] = passes["Combined"][..., :3]
    t = time.perf_counter()
    for b in cfg.buffers:
        writer.write_buffer(frame, "hr", b, hr_out[b])
    seconds["write"] = time.perf_counter() - t
    record["hr"] = {"world_from_camera": m, "prev_world_from_camera": m_prev, "intrinsics": k_hr,
                    "prev_intrinsics": k_prev_hr, "jitter": [0.0, 0.0], "spp": cfg.hr_spp,
                    "seed": settings_hr["seed"], "gbuffer_seed": pass_seed(cfg.seed, frame, 0) if plan.any else None,
                    "seconds": seconds}
    if m_next is not None:
        record["hr"].update(next_world_from_camera=m_next, next_intrinsics=k_next_hr)

    # --- LR: per level one point-sampled render with its own G-buffer passes ----------------------------------
    jit = halton_jitter(index) if cfg.jitter == "halton" else (0.0, 0.0)
    for i, scale in enumerate(cfg.scales):
        lvl = level_name(scale, cfg.scales[0])
        record[lvl] = render_lr_level(scene, cam, view_layer, cfg, frame, lvl, i, scale,
                                      (levels[lvl]["width"], levels[lvl]["height"]), jit, plan, flag_lut,
                                      light_paths, gbuf_buffers, (m, k_hr, m_prev, k_prev_hr, m_next, k_next_hr),
                                      base_shift, tmpdir, writer)
    return record


def render_lr_level(scene, cam, view_layer, cfg: RenderConfig, frame: int, lvl: str, i: int, scale: float,
                    size: tuple[int, int], jit, plan: PassPlan, flag_lut, light_paths, gbuf_buffers, cams,
                    base_shift, tmpdir: Path, writer: ClipWriter) -> dict:
    """Render LR level ``lvl`` (the ``i``-th of ``cfg.scales``, ``size`` = HR / ``scale``) of a frame, jittered by
    ``jit`` pixels of the level; write its buffers and return its record. Cycles seed: pass 2 + i."""
    lw, lh = size
    m, k_hr, m_prev, k_prev_hr, m_next, k_next_hr = cams
    k_lr, k_prev_lr = scale_intrinsics(k_hr, 1 / scale), scale_intrinsics(k_prev_hr, 1 / scale)
    k_next_lr = scale_intrinsics(k_next_hr, 1 / scale) if k_next_hr is not None else None
    scene.render.resolution_x, scene.render.resolution_y = lw, lh
    # shift is in units of the larger image side; +shift_x moves content left (sample at p + dx),
    # +shift_y moves content down in y-down image coordinates (sample at p - dy): see conventions.
    cam.data.shift_x = base_shift[0] + jit[0] / max(lw, lh)
    cam.data.shift_y = base_shift[1] - jit[1] / max(lw, lh)
    set_passes(view_layer, plan)
    settings_lr = set_sampling(scene, spp=cfg.lr_spp, filter_width=POINT_FILTER[1], filter_type=POINT_FILTER[0],
                               bounces=True, denoise=cfg.lr_denoise, adaptive=False, cfg=cfg,
                               seed=pass_seed(cfg.seed, frame, 2 + i), light_paths=light_paths)
    seconds = {}
    try:
        t = time.perf_counter()
        passes = render_to(scene, tmpdir / f"{lvl}.exr")
        seconds["radiance"] = time.perf_counter() - t
    finally:
        cam.data.shift_x, cam.data.shift_y = base_shift
    t = time.perf_counter()
    lr_out = convert(passes, plan, gbuf_buffers, m=m, k=k_lr, m_prev=m_prev, k_prev=k_prev_lr, jitter=jit,
                     flag_lut=flag_lut, fbeta_source=cfg.fbeta, m_next=m_next, k_next=k_next_lr) if plan.any else {}
    lr_out["radiance"] = passes["Combined"][..., :3]
    seconds["convert"] = time.perf_counter() - t
    t = time.perf_counter()
    for b in cfg.buffers:
        writer.write_buffer(frame, lvl, b, lr_out[b])
    seconds["write"] = time.perf_counter() - t
    rec = {"world_from_camera": m, "prev_world_from_camera": m_prev, "intrinsics": k_lr,
           "prev_intrinsics": k_prev_lr, "jitter": list(jit), "spp": cfg.lr_spp, "seed": settings_lr["seed"],
           "seconds": seconds}
    if m_next is not None:
        rec.update(next_world_from_camera=m_next, next_intrinsics=k_next_lr)
    return rec
