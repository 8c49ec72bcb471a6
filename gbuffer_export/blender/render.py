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
atomically. What the configuration and the scene settle is resolved once, stage by stage (``render_setup``:
``resolve_render`` -> frozen ``ResolvedRender``); what every frame shares is one frozen ``RenderContext``.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
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
from ..clip import FRAMES_DIR, ClipWriter
from ..config import ConfigError, RenderConfig, recorded_keys
from ..conventions import exposure_header, halton_jitter, intrinsics_from_projection, level_name, pass_seed
from ..interrupt import check_interrupt, stop_on_sigint
from ..pixel_filter import HR_REFERENCE_FILTER, POINT_FILTER, footprint_fbeta
from ..provenance import other_code, short_revision, source_revision
from ..regions import dilate
from ..resources import TEMP_EXR_CHANNELS, check_render_resources, render_threads
from . import materials as mats
from .convert import BACKGROUND_DEPTH, PASSES, LevelCameras, PassPlan, colour_sum, convert, reactive_mask, read_passes
from .render_setup import ResolvedRender, renderable_meshes, resolve_render

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


def has_fog(scene) -> bool:
    """True when a renderable object of ``scene`` is a volume-only domain (``materials.volume_domain``): its G-buffer
    passes need a render of their own with the volumes muted."""
    return any(mats.volume_domain(ob) for ob in renderable_meshes(scene))


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
    threads = render_threads(cfg.threads)
    if threads:
        r.threads_mode = "FIXED"
        r.threads = threads
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
    commit: str | None = None  # the code that renders (gbuffer_export.provenance), taken before the first frame


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
    commit = source_revision()
    if skipped:
        log.info("blendsr: resuming %s: %d of %d frames already done", cfg.output, skipped, len(r.my_frames))
        _warn_other_code(writer, [f for f in r.my_frames if f not in todo], commit)
    remove_stale_scratch(cfg.output)
    tmpdir = Path(tempfile.mkdtemp(prefix=f".render-{os.getpid()}-", dir=cfg.output))
    try:
        ctx = RenderContext(cfg=cfg, scene=scene, resolved=r, light_paths=light_paths, tmpdir=tmpdir, writer=writer,
                            commit=commit)
        _render_frames(ctx, todo)
        writer.merge()
    finally:
        for p in tmpdir.glob("*"):
            p.unlink()
        tmpdir.rmdir()
        writer.close()
    return cfg.output


def _warn_other_code(writer: ClipWriter, done: list[int], commit: str | None) -> None:
    """A warning when finished frames of the clip being resumed name other code than this render's
    (``provenance.other_code``): the clip will hold frames of two code versions."""
    records = {}
    for f in done:
        try:
            records[f] = json.loads(writer.record_path(f).read_text())
        except (OSError, ValueError):
            continue  # is_frame_done read it a moment ago; a record gone since is rendered again
    made = other_code(records, commit)
    if made:
        log.warning("blendsr: %s: resuming a clip begun by other code (%s); this render is %s", writer.path, made,
                    short_revision(commit) if commit else "of unrecorded code")


def _render_frames(ctx: RenderContext, todo: list[int]) -> None:
    """Render and commit each frame of ``todo`` (a partial frame is discarded on Ctrl-C)."""
    bar = _progress(todo, ctx.cfg)
    for f in bar:
        check_interrupt()  # Ctrl-C (render_clip, dataset_job: gbuffer_export.interrupt)
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            rec = render_frame(ctx, f)
        except KeyboardInterrupt:
            ctx.writer.discard_frame(f)  # the partial frame is never committed
            raise
        # wall seconds (what the frame took on this machine and load) and this process's CPU seconds, all threads
        # (Cycles renders in this process): the load-independent cost, summed over the threads it used
        rec["seconds_total"] = time.perf_counter() - t0
        rec["cpu_seconds_total"] = time.process_time() - c0
        rec["commit"] = ctx.commit  # the code that rendered this frame (gbuffer_export.provenance)
        ctx.writer.commit_frame(f, rec)
        if hasattr(bar, "set_postfix"):
            bar.set_postfix(gt=f"{rec['hr']['seconds'].get('radiance', 0):.1f}s")


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
