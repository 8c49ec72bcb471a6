"""Light a user's level (bpy layer): ``light = "auto"`` and the level's sky meshes.

``auto`` decides by measurement, per clip, from the clip's own cameras (``PROBE_FRAMES`` frames spread over it):

1. *The file's light.* A probe render (``PROBE_WIDTH`` px wide, ``PROBE_SPP`` samples, Cycles) of those frames. Its
   pixels that show the level (a view ray hits it within its extent: not the sky, not a sky mesh) give the
   log-average luminance and the *dark fraction*: pixels under ``DARK`` once the log-average is keyed to ``KEY``
   (what a game's auto exposure does). The file's lamps, world and emission light what the cameras see when the
   dark fraction is at most ``LIT_MAX_DARK`` and the log-average at least ``LIT_MIN_LOG_AVERAGE``: then nothing is
   added. A file with no light source at all is not rendered: it is unlit.
2. Otherwise light is added, and the file's own is kept beside it:
   - *sun and sky* (``add_sky``: it replaces the world) when a camera eye sees the sky: at least
     ``OPEN_SKY_MIN`` of the rays over its upper hemisphere leave the level, or at least ``SEES_SKY_MIN`` of its
     view rays do;
   - *ceiling lights* when an eye of the camera path (up to 64 spread over the clip) stands under a roof: at least
     ``ROOF_MIN`` of the rays within ``ROOF_CONE_DEG`` of its zenith hit the level (a room with doorways to the
     void is under a roof; a street is not). They are area lamps facing
     down just under the ceilings of the space around the roofed eyes (points of a ``INTERIOR_SPACING_M`` grid
     within ``INTERIOR_REACH_M`` of them, each at its nearest eye's height, with a floor below and a ceiling above:
     ``ceiling_points``; at most ``INTERIOR_MAX_LIGHTS``, nearest first), each of
     ``INTERIOR_IRRADIANCE`` W/m^2 times its grid cell's area in scene units (the floor below receives about that
     irradiance from it, as the added sun gives ``SKY_SUN_STRENGTH`` W/m^2 outdoors).
   The probe is rendered again with the added light and both measurements go into the manifest.

A *sky mesh* (a skybox or skydome) is a mesh object that (a) holds the bounding box of every other renderable
object, (b) is hit by at least ``SKY_MESH_UPPER_HITS`` of the rays cast from the centre of the others' box over
the upper hemisphere, and (c) is drawn unlit (every material an emission or background shader and no lit BSDF:
a game's sky shader, glTF's KHR_materials_unlit) or lies around the level with a gap of at least
``SKY_MESH_MARGIN`` of the others' size on every side but the bottom and shows its front faces to the inside on at
least half of those rays, and (d) is not the floor the others stand on: along vertical rays from a 5x5 grid over
the others' box, its median surface below them lies at least ``SKY_MESH_MARGIN`` of their size under their box
(a dome has none). A room's shell is (a) and (b) but its floor carries the furniture: it stays level. Under
``auto`` and ``sky`` each sky mesh is seen by camera rays only (no shadow, diffuse, glossy, transmission or volume
rays: it neither shadows nor lights the level, as a game's skybox) and a lit one is drawn unlit (emission of its
base colour, strength 1). Camera planning and the sky measurements take the level without its sky meshes, so a
ray that reaches a sky mesh sees the sky.
"""
from __future__ import annotations

import contextlib
import logging
import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np

from ..colour_spaces import BT709_LUMA
from ..config import ConfigError
from .level_geometry import LevelGeometry, enclosure, trimesh_of

log = logging.getLogger(__name__)

#: Probe render: width in pixels (height from the clip's aspect), samples per pixel, frames of the clip.
PROBE_WIDTH = 96
PROBE_SPP = 8
PROBE_FRAMES = 3
#: A game's auto exposure keys the log-average luminance to middle grey.
KEY = 0.18
#: A pixel darker than this once keyed is black on screen.
DARK = 1e-3
#: The file's light lights what the cameras see: at most this fraction of the level's pixels are dark (keyed) ...
LIT_MAX_DARK = 0.2
#: ... and their log-average luminance is at least this: an exposure of at most 2^4 (+4 stops, a game camera's usual
#: auto-exposure range) keys it. Blender's default grey world through a window or a dim emissive strip is less.
LIT_MIN_LOG_AVERAGE = KEY / 16
#: Luminance floor inside the log-average (a black pixel counts as this).
LOG_EPS = 1e-8
#: An eye sees the sky: this fraction of its upper hemisphere's rays leave the level (as
#: ``render_setup.SKY_LIT_MIN_SKY``).
OPEN_SKY_MIN = 0.05
#: ... or this fraction of its view rays do.
SEES_SKY_MIN = 0.02
#: An eye stands under a roof: this fraction of the rays within ``ROOF_CONE_DEG`` of its zenith hit the level.
ROOF_MIN = 0.5
ROOF_CONE_DEG = 45.0
#: Ceiling lights: grid spacing and reach around the eyes (metres), most lamps, floor irradiance of each (W/m^2 over
#: its cell), lamp size (metres), highest ceiling above a floor (metres).
INTERIOR_SPACING_M = 3.0
INTERIOR_REACH_M = 12.0
INTERIOR_MAX_LIGHTS = 64
INTERIOR_IRRADIANCE = 3.0
INTERIOR_LAMP_SIZE_M = 0.5
CEILING_MAX_M = 12.0
#: Sky meshes (module doc): upper-hemisphere rays that hit it, gap around the level, rays cast.
SKY_MESH_UPPER_HITS = 0.9
SKY_MESH_MARGIN = 0.25
SKY_MESH_RAYS = 256
LIT_BSDFS_OK = frozenset({"BSDF_TRANSPARENT"})  # glTF's unlit shader mixes emission with transparency
SKY_SUN_STRENGTH = 4.0      # W/m^2 of the added sun lamp
SKY_STRENGTH = 0.35         # multiplier of Blender's physical sky (its radiance is in daylight units)


# ----------------------------------------------------------------------------------------------
# The file's light sources, the added sun and sky, light variations
# ----------------------------------------------------------------------------------------------

def _socket_value(sock):
    v = getattr(sock, "default_value", None)
    return tuple(v) if v is not None and hasattr(v, "__len__") else v


def world_emits(scene) -> bool:
    """Whether the world lights the scene: a Background or Emission node with a non-zero strength whose colour
    is linked (a texture) or not black."""
    w = scene.world
    if w is None:
        return False
    nt = w.node_tree
    if nt is None:
        return any(c > 0 for c in w.color)
    for n in nt.nodes:
        if n.type not in ("BACKGROUND", "EMISSION") or n.mute:
            continue
        s = n.inputs.get("Strength")
        c = n.inputs.get("Color")
        strong = s is None or s.is_linked or (_socket_value(s) or 0) > 0
        bright = c is None or c.is_linked or any(x > 0 for x in (_socket_value(c) or (0,))[:3])
        if strong and bright and n.outputs[0].is_linked:
            return True
    return False


def material_emits(mat) -> bool:
    if mat is None or mat.node_tree is None:
        return False
    for n in mat.node_tree.nodes:
        if n.mute:
            continue
        if n.type == "EMISSION":
            s, c = n.inputs.get("Strength"), n.inputs.get("Color")
        elif n.type == "BSDF_PRINCIPLED":
            s, c = n.inputs.get("Emission Strength"), n.inputs.get("Emission Color")
        else:
            continue
        if s is None or c is None:
            continue
        if (s.is_linked or (_socket_value(s) or 0) > 0) and (c.is_linked or any(x > 0 for x in _socket_value(c)[:3])):
            return True
    return False


def light_sources(scene, exclude: set = frozenset()) -> dict:
    """What lights ``scene``: counts of lamps with energy, emissive materials on renderable objects (those of the
    objects named in ``exclude`` left out: sky meshes, which light nothing), and whether the world emits."""
    lamps = [ob for ob in scene.objects if ob.type == "LIGHT" and not ob.hide_render and ob.data.energy > 0]
    emissive = {s.material.name for ob in scene.objects if ob.type == "MESH" and not ob.hide_render
                and ob.name not in exclude for s in ob.material_slots if material_emits(s.material)}
    return {"lamps": len(lamps), "sun_lamps": sum(ob.data.type == "SUN" for ob in lamps),
            "emissive_materials": len(emissive), "world": world_emits(scene)}


def check_lit(scene, where, light: str) -> dict:
    """ConfigError when nothing lights the scene and ``light`` is "scene"; the light sources otherwise."""
    src = light_sources(scene)
    if light == "scene" and not (src["lamps"] or src["emissive_materials"] or src["world"]):
        raise ConfigError(f"{where}: the scene has no lights, no emissive material and a black world, so every "
                          "frame would be black; set light auto (it adds a sun and sky where the cameras see the sky "
                          "and lights under the ceilings where they do not, recorded in the manifest)", key="light")
    return src


def add_sky(scene, seed: int = 0) -> dict:
    """Light ``scene`` with a sun lamp and Blender's physical sky (multiple scattering) whose sun points the same
    way: elevation 25-60 degrees and azimuth drawn from ``seed``. Returns what was added (for the manifest)."""
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 5])
    elev, azim = float(rng.uniform(25.0, 60.0)), float(rng.uniform(0.0, 360.0))
    world = bpy.data.worlds.new("BlendSR Sky")
    world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    sky = nt.nodes.new("ShaderNodeTexSky")
    sky.sky_type = "MULTIPLE_SCATTERING"
    sky.sun_disc = False  # the sun lamp is the sun: sharp shadows, sampled directly
    sky.sun_elevation, sky.sun_rotation = math.radians(elev), math.radians(azim)
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = SKY_STRENGTH
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(sky.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    scene.world = world
    lamp = bpy.data.lights.new("BlendSR Sun", "SUN")
    lamp.energy = SKY_SUN_STRENGTH
    lamp.angle = math.radians(0.53)
    ob = bpy.data.objects.new("BlendSR Sun", lamp)
    # A sun lamp shines along its -Z: point it from the sky position (elevation, azimuth about +Z from +Y).
    ob.rotation_euler = (math.radians(90.0 - elev), 0.0, math.radians(azim))
    scene.collection.objects.link(ob)
    return {"light": "sky", "sun_elevation_deg": elev, "sun_azimuth_deg": azim, "sun_strength_w_m2": SKY_SUN_STRENGTH,
            "sky": "MULTIPLE_SCATTERING", "sky_strength": SKY_STRENGTH}


def apply_variation(scene, variation: dict | None) -> dict:
    """Apply a drawn light variation (``dataset.spec.Variation``) to ``scene``; returns what changed."""
    if not variation:
        return {}
    done = {}
    world = scene.world
    nodes = world.node_tree.nodes if world is not None and world.node_tree is not None else []
    if "world_strength" in variation:
        bgs = [n for n in nodes if n.type == "BACKGROUND"]
        for n in bgs:
            n.inputs["Strength"].default_value *= variation["world_strength"]
        done["world_strength"] = {"multiplier": variation["world_strength"], "nodes": len(bgs)}
    lamps = [ob for ob in scene.objects if ob.type == "LIGHT"]
    if "light_strength" in variation:
        for ob in lamps:
            ob.data.energy *= variation["light_strength"]
        done["light_strength"] = {"multiplier": variation["light_strength"], "lamps": len(lamps)}
    if "sun_elevation_deg" in variation:
        elev, azim = variation["sun_elevation_deg"], variation["sun_azimuth_deg"]
        suns = [ob for ob in lamps if ob.data.type == "SUN"]
        for ob in suns:
            ob.rotation_mode = "XYZ"
            ob.rotation_euler = (math.radians(90.0 - elev), 0.0, math.radians(azim))
        for n in nodes:
            if n.type == "TEX_SKY":
                n.sun_elevation, n.sun_rotation = math.radians(elev), math.radians(azim)
        done["sun"] = {"elevation_deg": elev, "azimuth_deg": azim, "sun_lamps": len(suns)}
    if "hdri" in variation:
        envs = [n for n in nodes if n.type == "TEX_ENVIRONMENT"]
        if envs:
            from .default_scene import hdri_path
            img = bpy.data.images.load(str(hdri_path(variation["hdri"])), check_existing=True)
            for n in envs:
                n.image = img
                mapping = n.inputs["Vector"].links[0].from_node if n.inputs["Vector"].is_linked else None
                if mapping is not None and mapping.type == "MAPPING":
                    mapping.inputs["Rotation"].default_value[2] = math.radians(variation["hdri_rotation_deg"])
                else:
                    tc = world.node_tree.nodes.new("ShaderNodeTexCoord")
                    mp = world.node_tree.nodes.new("ShaderNodeMapping")
                    mp.inputs["Rotation"].default_value[2] = math.radians(variation["hdri_rotation_deg"])
                    world.node_tree.links.new(tc.outputs["Generated"], mp.inputs["Vector"])
                    world.node_tree.links.new(mp.outputs["Vector"], n.inputs["Vector"])
        done["hdri"] = {"file": variation["hdri"], "rotation_deg": variation["hdri_rotation_deg"],
                        "applied": bool(envs)}
    return done


# ----------------------------------------------------------------------------------------------
# The level's geometry and its sky meshes
# ----------------------------------------------------------------------------------------------

@dataclass
class LevelLight:
    """A user's level for lighting: its geometry without sky meshes (``level``; camera planning uses it) and the
    sky-mesh detection (``sky_meshes``: object names; ``sky_report``: the measured numbers per candidate)."""

    level: LevelGeometry
    sky_meshes: list = field(default_factory=list)
    sky_report: list = field(default_factory=list)


def subset(geom: LevelGeometry, keep_owner: np.ndarray) -> LevelGeometry:
    """The geometry of the objects whose owner index is in ``keep_owner``."""
    mask = np.isin(geom.owner, keep_owner)
    return LevelGeometry(np.asarray(geom.mesh.vertices), np.asarray(geom.mesh.faces)[mask], geom.metres_per_unit,
                         geom.names, geom.owner[mask])


def material_unlit(mat) -> bool:
    """An emission or background shader and no lit BSDF (transparency aside): the material is drawn unlit."""
    if mat is None or mat.node_tree is None:
        return False
    types = {n.type for n in mat.node_tree.nodes if not n.mute}
    lit = {t for t in types if t.startswith("BSDF_") or t in ("SUBSURFACE_SCATTERING", "PRINCIPLED_VOLUME")}
    return bool(types & {"EMISSION", "BACKGROUND"}) and not (lit - LIT_BSDFS_OK)


def object_unlit(ob) -> bool:
    mats = [s.material for s in ob.material_slots]
    return bool(mats) and all(material_unlit(m) for m in mats)


def object_boxes(geom: LevelGeometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The owner indices of ``geom`` and each one's bounding box (lo, hi: (N, 3)), in one pass over the triangles."""
    order = np.argsort(geom.owner, kind="stable")
    owner = geom.owner[order]
    tri = geom.mesh.triangles[order]
    ids, starts = np.unique(owner, return_index=True)
    return ids, np.minimum.reduceat(tri.min(axis=1), starts), np.maximum.reduceat(tri.max(axis=1), starts)


def find_sky_meshes(geom: LevelGeometry, unlit: set) -> tuple[list[int], list[dict]]:
    """Owner indices of the sky meshes of ``geom`` (module doc; ``unlit``: names of objects drawn unlit) and the
    measured numbers of every object that holds the others' box."""
    ids, lo_all, hi_all = object_boxes(geom)
    if len(ids) < 2:
        return [], []
    glo, ghi = lo_all.min(axis=0), hi_all.max(axis=0)
    found, report = [], []
    for k, i in enumerate(ids):
        lo, hi = lo_all[k], hi_all[k]
        tol = 1e-3 * float(np.max(hi - lo))
        if not (np.all(lo <= glo + tol) and np.all(hi >= ghi - tol)):
            continue  # (a): only an object whose box is the level's whole box holds every other one
        rest = np.arange(len(ids)) != k
        rlo, rhi = lo_all[rest].min(axis=0), hi_all[rest].max(axis=0)  # the rest of the level
        enc = enclosure(trimesh_of(geom.mesh.triangles[geom.owner == i]), rlo, rhi, SKY_MESH_RAYS)
        upper, inward, below = enc["upper_hits"], enc["front_inside"], enc["gap_below"]
        size = float(np.max(rhi - rlo)) or 1.0
        gaps = np.concatenate([rlo[:2] - lo[:2], hi - rhi])  # x-, y-, x+, y+, z+ (the bottom may be the ground)
        margin = float(gaps.min() / size)
        name = geom.names[i] if i < len(geom.names) else str(i)
        is_unlit = name in unlit
        sky = upper >= SKY_MESH_UPPER_HITS and below >= SKY_MESH_MARGIN and (
            is_unlit or (margin >= SKY_MESH_MARGIN and inward >= 0.5))
        report.append({"object": name, "sky": bool(sky), "upper_hits": round(upper, 4),
                       "front_faces_inside": round(inward, 4), "margin": round(margin, 4),
                       "gap_below": round(below, 4) if math.isfinite(below) else None, "unlit": is_unlit})
        if sky:
            found.append(int(i))
    return found, report


def level_light(scene, frame: int) -> LevelLight:
    """The level's geometry at ``frame`` and its sky meshes (found, not yet treated)."""
    from .level_geometry import from_scene
    geom = from_scene(scene, frame)
    unlit = {ob.name for ob in scene.objects if ob.type in ("MESH", "CURVE", "SURFACE", "META", "FONT")
             and object_unlit(ob)}
    sky_ids, report = find_sky_meshes(geom, unlit)
    if not sky_ids:
        return LevelLight(geom, [], report)
    keep = np.setdiff1d(np.unique(geom.owner), sky_ids)
    names = [geom.names[i] for i in sky_ids]
    log.info("blendsr: sky mesh %s: it encloses the level (seen by the camera only, casts no shadow)",
             ", ".join(names))
    return LevelLight(subset(geom, keep), names, report)


def treat_sky_meshes(scene, ll: LevelLight) -> list:
    """Make each sky mesh visible to camera rays only and draw a lit one unlit. Returns what was done."""
    done = []
    for name in ll.sky_meshes:
        ob = scene.objects.get(name)
        if ob is None:
            continue
        for attr in ("visible_shadow", "visible_diffuse", "visible_glossy", "visible_transmission",
                     "visible_volume_scatter"):
            setattr(ob, attr, False)
        ob.visible_camera = True
        made_unlit = []
        if not object_unlit(ob):
            for slot in ob.material_slots:
                if slot.material is not None and not material_unlit(slot.material):
                    slot.material = _unlit_copy(slot.material)
                    made_unlit.append(slot.material.name)
        done.append({"object": name, "visible": ["camera"], "made_unlit": made_unlit})
    return done


def _unlit_copy(mat):
    """A copy of ``mat`` whose surface is an Emission of its base colour (strength 1): a game's sky shader."""
    m = mat.copy()
    m.name = f"{mat.name} (unlit sky)"
    nt = m.node_tree
    out = next((n for n in nt.nodes if n.type == "OUTPUT_MATERIAL" and n.is_active_output), None) \
        or nt.nodes.new("ShaderNodeOutputMaterial")
    em = nt.nodes.new("ShaderNodeEmission")
    em.inputs["Strength"].default_value = 1.0
    base = next((n for n in nt.nodes if n.type == "BSDF_PRINCIPLED"), None)
    col = base.inputs.get("Base Color") if base is not None else None
    if col is not None and col.is_linked:
        nt.links.new(col.links[0].from_socket, em.inputs["Color"])
    elif col is not None:
        em.inputs["Color"].default_value = col.default_value
    for link in list(out.inputs["Surface"].links):
        nt.links.remove(link)
    nt.links.new(em.outputs["Emission"], out.inputs["Surface"])
    return m


# ----------------------------------------------------------------------------------------------
# What the cameras see
# ----------------------------------------------------------------------------------------------

def probe_frames(frames) -> list[int]:
    frames = list(frames)
    idx = np.unique(np.linspace(0, len(frames) - 1, min(PROBE_FRAMES, len(frames))).round().astype(int))
    return [frames[i] for i in idx]


def camera_rays(cam, scene, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The eye (3,) and the unit view rays (H*W, 3, rows from the top) of ``cam`` at the current frame."""
    from ..conventions import intrinsics_from_projection
    m = np.array(cam.matrix_world, dtype=np.float64)
    rot = m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0, keepdims=True)
    dg = bpy.context.evaluated_depsgraph_get()
    proj = np.array(cam.calc_matrix_camera(dg, x=width, y=height, scale_x=1.0, scale_y=1.0))
    fx, fy, cx, cy = intrinsics_from_projection(proj, width, height)
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    d = np.stack([(jj - cx) / fx, -(ii - cy) / fy, -np.ones_like(jj)], axis=-1).reshape(-1, 3) @ rot.T
    return m[:3, 3].copy(), d / np.linalg.norm(d, axis=1, keepdims=True)


def roofed(level: LevelGeometry, eyes: np.ndarray, n: int = 256) -> np.ndarray:
    """Per eye: the fraction of rays within ``ROOF_CONE_DEG`` of the zenith (of ``n`` over the sphere) that hit the
    level within its extent."""
    from .level_geometry import sphere_directions
    d = sphere_directions(n)
    d = d[d[:, 2] >= math.cos(math.radians(ROOF_CONE_DEG))]
    eyes = np.asarray(eyes, np.float64).reshape(-1, 3)
    dist, _ = level.first_hits(np.repeat(eyes, len(d), axis=0), np.tile(d, (len(eyes), 1)))
    return (dist <= level.extent).reshape(len(eyes), len(d)).mean(axis=1)


def eye_sky(level: LevelGeometry, eye: np.ndarray, rays: np.ndarray) -> tuple[float, float, np.ndarray]:
    """(open sky over the eye's upper hemisphere, fraction of view rays leaving the level, view rays' level mask)."""
    from .level_cameras import sky_fraction
    dist, _ = level.first_hits(np.repeat(eye[None], len(rays), axis=0), rays)
    on_level = dist <= level.extent
    return float(sky_fraction(level, eye[None])[0]), float(1.0 - on_level.mean()), on_level


@contextlib.contextmanager
def _overridden(pairs, restore_in_order: bool = False):
    """Set each (object, attribute, value) and restore the old values after (in reverse order, or in the same
    order where one value constrains the next: an image format's media type, then its format and depth)."""
    saved = [(o, a, getattr(o, a)) for o, a, _ in pairs]
    try:
        for o, a, v in pairs:
            setattr(o, a, v)
        yield
    finally:
        for o, a, v in (saved if restore_in_order else reversed(saved)):
            setattr(o, a, v)


def probe_render(scene, cam, frames: list[int], size: tuple[int, int], device: str, threads: int) -> list:
    """Luminance images (H, W) of ``cam`` at ``frames``: a small, noisy Cycles render with the scene's own light
    paths; every render setting is restored after."""
    from ..interrupt import check_interrupt
    from .convert import read_passes
    from .fds import captured
    from .scene_setup import select_device
    from ..resources import render_threads
    r, c = scene.render, scene.cycles
    select_device(scene, device)
    threads = render_threads(threads)
    pairs = [(r, "engine", "CYCLES"), (r, "resolution_x", size[0]), (r, "resolution_y", size[1]),
             (r, "resolution_percentage", 100), (r, "use_border", False), (r, "film_transparent", False),
             (r, "use_compositing", False), (r, "use_sequencer", False), (r, "use_persistent_data", False),
             (r, "use_motion_blur", False), (r, "threads_mode", "FIXED" if threads else "AUTO"),
             (c, "samples", PROBE_SPP), (c, "use_adaptive_sampling", False), (c, "use_denoising", False),
             (c, "film_exposure", 1.0), (c, "seed", 0), (scene, "camera", cam), (r, "filepath", r.filepath)]
    if threads:
        pairs.append((r, "threads", threads))
    s = r.image_settings
    fmt = [(s, "media_type", "MULTI_LAYER_IMAGE"), (s, "file_format", "OPEN_EXR_MULTILAYER"),
           (s, "color_depth", "32"), (s, "exr_codec", "ZIP")]
    out, frame0 = [], scene.frame_current
    luma = np.array(BT709_LUMA, np.float32)
    with tempfile.TemporaryDirectory(prefix="blendsr-probe-") as tmp, _overridden(pairs), _overridden(fmt, True):
        for f in frames:
            scene.frame_set(f)
            path = Path(tmp) / f"probe_{f}.exr"
            r.filepath = str(path)
            with captured():  # Blender's per-render log lines (BLENDSR_VERBOSE=1 keeps them)
                bpy.ops.render.render(write_still=True, scene=scene.name)
            check_interrupt()  # Ctrl-C during the probe: stop here
            rgb = read_passes(path)["Combined"][..., :3]
            out.append(np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0) @ luma)
    scene.frame_set(frame0)
    return out


def luminance_stats(lum: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """Mean and log-average luminance, and the fractions of pixels under ``DARK`` as rendered and once the
    log-average is keyed to ``KEY``; over ``mask`` (the level's pixels) when it holds at least a tenth of them."""
    y = np.maximum(np.asarray(lum, np.float64).ravel(), 0.0)
    if mask is not None and mask.mean() >= 0.1:
        y = y[mask.ravel()]
    if y.size == 0:
        return {"pixels": 0, "mean": 0.0, "log_average": 0.0, "dark_fraction": 1.0, "dark_fraction_keyed": 1.0}
    la = float(np.exp(np.mean(np.log(LOG_EPS + y))))
    return {"pixels": int(y.size), "mean": float(y.mean()), "log_average": la,
            "dark_fraction": float((y < DARK).mean()),
            "dark_fraction_keyed": float((y * (KEY / max(la, LOG_EPS)) < DARK).mean())}


def is_lit(stats: dict) -> bool:
    return stats["dark_fraction_keyed"] <= LIT_MAX_DARK and stats["log_average"] >= LIT_MIN_LOG_AVERAGE


# ----------------------------------------------------------------------------------------------
# Added light
# ----------------------------------------------------------------------------------------------

def ceiling_points(level: LevelGeometry, eyes: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Points just under the ceilings of the walkable space around ``eyes`` (module doc), nearest first, their
    heights above their floors (scene units) and the grid spacing (scene units). A grid point stands at the height
    of its nearest eye, 0.25 m from every triangle, seen from one of its 4 nearest eyes (the cameras' space: not
    behind a wall, not inside a solid), with a floor below and a ceiling above (neither steep) less than
    ``CEILING_MAX_M`` apart: that eye's storey."""
    from .level_cameras import UP, WALKABLE_COS
    s, reach = level.units(INTERIOR_SPACING_M), level.units(INTERIOR_REACH_M)
    clo, chi = level.content_bounds(0.0)
    lo = np.maximum(eyes[:, :2].min(axis=0) - reach, clo[:2])
    hi = np.minimum(eyes[:, :2].max(axis=0) + reach, chi[:2])
    axes = [np.arange(a + 0.5 * s, b, s) if b - a > s else np.array([0.5 * (a + b)]) for a, b in zip(lo, hi)]
    xy = np.stack(np.meshgrid(*axes), axis=-1).reshape(-1, 2)
    gap = np.linalg.norm(xy[:, None, :] - eyes[None, :, :2], axis=2)
    near = gap.argmin(axis=1)
    keep = gap.min(axis=1) <= reach
    pts = np.column_stack([xy, eyes[near, 2]])[keep]
    if len(pts) == 0:
        return np.zeros((0, 3)), np.zeros(0), s
    up_d, up_t = level.first_hits(pts, np.repeat(UP[None], len(pts), axis=0))
    dn_d, dn_t = level.first_hits(pts, np.repeat(-UP[None], len(pts), axis=0))
    flat = np.abs(level.normals[np.maximum(up_t, 0)][:, 2]) >= WALKABLE_COS
    flat &= np.abs(level.normals[np.maximum(dn_t, 0)][:, 2]) >= WALKABLE_COS
    ok = (up_t >= 0) & (dn_t >= 0) & flat & (up_d + dn_d <= level.units(CEILING_MAX_M))
    ok &= level.nearest_distance(pts) >= level.units(0.25)
    idx = [k for k in np.flatnonzero(ok) if _seen_from(level, pts[k], eyes)]
    lamps = pts[idx] + UP[None] * (up_d[idx] - level.units(0.05))[:, None]
    heights = up_d[idx] + dn_d[idx] - level.units(0.05)  # of the lamp above its floor
    order = np.argsort(gap.min(axis=1)[keep][idx], kind="stable")[:INTERIOR_MAX_LIGHTS]
    return lamps[order], heights[order], s


def _seen_from(level: LevelGeometry, p: np.ndarray, eyes: np.ndarray, k: int = 4) -> bool:
    """Whether one of the ``k`` eyes nearest to ``p`` sees it (nothing between): ``p`` is in the cameras' space, not
    behind a wall or inside a solid."""
    near = eyes[np.argsort(np.linalg.norm(eyes - p, axis=1))[:k]]
    d = p[None] - near
    n = np.linalg.norm(d, axis=1)
    if (n < 1e-9).any():
        return True
    dist, _ = level.first_hits(near, d / n[:, None])
    return bool((dist >= n - level.units(0.01)).any())


def add_ceiling_lights(scene, points: np.ndarray, heights: np.ndarray, spacing: float, metres_per_unit: float) -> dict:
    """Square area lamps facing down at ``points``; each of ``INTERIOR_IRRADIANCE`` x its cell area watts."""
    power = INTERIOR_IRRADIANCE * spacing * spacing
    size = INTERIOR_LAMP_SIZE_M / metres_per_unit
    coll = bpy.data.collections.new("BlendSR Ceiling Lights")
    scene.collection.children.link(coll)
    for k, p in enumerate(points):
        lamp = bpy.data.lights.new(f"BlendSR Ceiling {k:03d}", "AREA")
        lamp.shape, lamp.size, lamp.energy = "SQUARE", size, power
        ob = bpy.data.objects.new(lamp.name, lamp)
        ob.location = tuple(float(v) for v in p)  # an area lamp shines along its -Z: down
        coll.objects.link(ob)
    return {"lamps": int(len(points)), "power_w": power, "size_m": INTERIOR_LAMP_SIZE_M,
            "spacing_m": INTERIOR_SPACING_M, "irradiance_w_m2": INTERIOR_IRRADIANCE,
            "height_above_floor_m": [round(float(heights.min()) * metres_per_unit, 3),
                                     round(float(heights.max()) * metres_per_unit, 3)] if len(heights) else None}


# ----------------------------------------------------------------------------------------------
# light = "auto"
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ProbeView:
    """What the clip's camera sees at one probe frame: its eye, open sky over it, sky in view, its level pixels."""

    frame: int
    eye: np.ndarray
    open_sky: float
    sees_sky: float
    level_mask: np.ndarray


def probe_views(scene, cam, frames: list[int], level: LevelGeometry, size: tuple[int, int]) -> list[ProbeView]:
    out = []
    for f in frames:
        scene.frame_set(f)
        eye, rays = camera_rays(cam, scene, *size)
        open_sky, sees, mask = eye_sky(level, eye, rays)
        out.append(ProbeView(f, eye, open_sky, sees, mask.reshape(size[1], size[0])))
    return out


def path_eyes(scene, cam, frames: list[int], most: int = 64) -> np.ndarray:
    """The camera's eye at up to ``most`` frames spread over ``frames`` (scene units)."""
    idx = np.unique(np.linspace(0, len(frames) - 1, min(most, len(frames))).round().astype(int))
    eyes = []
    for i in idx:
        scene.frame_set(frames[i])
        eyes.append(np.array(cam.matrix_world, dtype=np.float64)[:3, 3])
    return np.array(eyes)


def measure(scene, cam, views: list[ProbeView], size, cfg) -> dict:
    """Luminance statistics of a probe render over the level's pixels of every probe frame."""
    lums = probe_render(scene, cam, [v.frame for v in views], size, cfg.device, cfg.threads)
    return luminance_stats(np.concatenate([y.ravel() for y in lums]),
                           np.concatenate([v.level_mask.ravel() for v in views]))


def unmeasured_auto_light(scene, seed: int) -> dict:
    """``light = "auto"`` where nothing is measured: a scene BlendSR built and lit, or one without triangles (no ray
    to cast), which keeps its own light or, having none, gets a sun and sky."""
    src = light_sources(scene)
    if src["lamps"] or src["emissive_materials"] or src["world"]:
        return {"light": "auto", "kept": "scene", "added": [], "scene_sources": src,
                "why": "not measured (a scene BlendSR built, or no triangles): the scene's own light"}
    return {"light": "auto", "kept": None, "added": ["sky"], "scene_sources": src, "sky": add_sky(scene, seed),
            "why": "the file has no light source (not measured: no triangles)"}


def auto_light(scene, cfg, cam, frames, hr_size: tuple[int, int], ll: LevelLight) -> dict:
    """``light = "auto"`` on a user's level (module doc): keep the file's light when it lights what the clip's
    cameras see, else add a sun and sky and/or ceiling lights. Returns the manifest's ``light`` record."""
    frame0 = scene.frame_current
    size = (PROBE_WIDTH, max(4, round(PROBE_WIDTH * hr_size[1] / hr_size[0])))
    views = probe_views(scene, cam, probe_frames(frames), ll.level, size)
    src = light_sources(scene, exclude=set(ll.sky_meshes))
    rec = {"light": "auto", "scene_sources": src,
           "rule": {"lit_max_dark_fraction_keyed": LIT_MAX_DARK, "lit_min_log_average": LIT_MIN_LOG_AVERAGE,
                    "key": KEY, "dark": DARK, "open_sky_min": OPEN_SKY_MIN, "sees_sky_min": SEES_SKY_MIN,
                    "roof_min": ROOF_MIN, "roof_cone_deg": ROOF_CONE_DEG},
           "views": [{"frame": v.frame, "open_sky": round(v.open_sky, 4), "sees_sky": round(v.sees_sky, 4)}
                     for v in views],
           "probe": {"size": list(size), "spp": PROBE_SPP, "frames": [v.frame for v in views]}}
    has_source = bool(src["lamps"] or src["emissive_materials"] or src["world"])
    before = measure(scene, cam, views, size, cfg) if has_source else None
    rec["probe"]["scene_light"] = before
    if before is not None and is_lit(before):
        rec.update(kept="scene", added=[], why="the file's light lights what the cameras see")
    else:
        rec.update(why=_why_dark(before), kept="scene" if has_source else None)
        rec.update(add_light(scene, cfg.seed, cam, frames, views, ll, src))
        after = rec["probe"]["with_added_light"] = measure(scene, cam, views, size, cfg)
        added = " and ".join(rec["added"])
        if not is_lit(after):
            log.warning("blendsr: %s: light auto added %s but %.0f%% of what the cameras see stays dark "
                        "(log-average %.3g)", cfg.scene or "scene", added, 100 * after["dark_fraction_keyed"],
                        after["log_average"])
        log.info("blendsr: %s: light auto: added %s (%s)", cfg.scene or "scene", added, rec["why"])
    scene.frame_set(frame0)
    return rec


def _why_dark(before: dict | None) -> str:
    if before is None:
        return "the file has no light source"
    if before["dark_fraction_keyed"] > LIT_MAX_DARK:
        return f"the file's light leaves {before['dark_fraction_keyed']:.0%} of what the cameras see dark"
    return f"the file's light is too dim: log-average luminance {before['log_average']:.3g} < {LIT_MIN_LOG_AVERAGE:.3g}"


def add_light(scene, seed: int, cam, frames, views: list[ProbeView], ll: LevelLight, src: dict) -> dict:
    """Add a sun and sky where the probe views see the sky and ceiling lights over the path's eyes that stand
    under a roof (a sun and sky when neither applies). Returns the manifest's entries (``added``, ``sky``,
    ``ceiling_lights``, ``path``)."""
    out, added = {}, []
    world = scene.world.name if scene.world is not None and src["world"] else None
    if max(v.open_sky for v in views) >= OPEN_SKY_MIN or max(v.sees_sky for v in views) >= SEES_SKY_MIN:
        out["sky"] = {**add_sky(scene, seed), "replaced_world": world}
        added.append("sky")
    eyes = path_eyes(scene, cam, list(frames))
    under = roofed(ll.level, eyes) >= ROOF_MIN
    out["path"] = {"eyes": len(eyes), "roofed_fraction": round(float(under.mean()), 4)}
    if under.any():
        pts, heights, spacing = ceiling_points(ll.level, eyes[under])
        if len(pts):
            out["ceiling_lights"] = add_ceiling_lights(scene, pts, heights, spacing, ll.level.metres_per_unit)
            added.append("ceiling_lights")
    if not added:  # no sky in view and no ceiling within reach: the sky is the light left
        out["sky"] = {**add_sky(scene, seed), "replaced_world": world}
        added.append("sky")
    out["added"] = added
    return out


# ----------------------------------------------------------------------------------------------
# A clip's light
# ----------------------------------------------------------------------------------------------

def light_clip(scene, cfg, cam, frames, hr_size: tuple[int, int], ll: LevelLight | None,
               sources: dict | None = None) -> dict:
    """``cfg.light`` "auto": keep the file's light where it lights what ``cam`` sees, add a sun and sky and/or
    ceiling lights where it does not (``auto_light``); "sky": add a default sun and sky; "scene": keep the file's
    light (``sources``: its light sources, already checked lit; None: checked here). ``ll``: the user's level and
    its sky meshes (None for a scene BlendSR built, whose light is its own); under auto and sky its sky meshes are
    seen by the camera only. Then ``cfg.extra["variation"]``. Returns the manifest's ``light`` record."""
    sky_meshes = {}
    if ll is not None:
        treated = treat_sky_meshes(scene, ll) if cfg.light in ("auto", "sky") else []
        sky_meshes = {"sky_meshes": {"found": list(ll.sky_meshes), "treated": treated, "candidates": ll.sky_report}}
    if cfg.light == "sky":
        out = {**add_sky(scene, cfg.seed), "scene_sources": check_lit(scene, cfg.scene or "scene", "sky")}
    elif cfg.light == "auto" and ll is not None:
        out = auto_light(scene, cfg, cam, frames, hr_size, ll)
    elif cfg.light == "auto":
        out = unmeasured_auto_light(scene, cfg.seed)
    else:
        sources = sources if sources is not None else check_lit(scene, cfg.scene or "scene", "scene")
        out = {"light": "scene", "scene_sources": sources}
    out.update(sky_meshes)
    variation = apply_variation(scene, cfg.extra.get("variation"))
    if variation:
        out["variation"] = variation
    return out
