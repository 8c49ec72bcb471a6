"""Third-party assets in a generated environment (bpy layer): import, normalise, ground, HDRI, clutter, and a
camera path that keeps its distance from the geometry.

- :func:`import_asset` brings a glTF/GLB (Blender's importer, with the extensions ``gltf_import`` adds) or the objects of a .blend (appended) into the scene.
- :func:`normalise` scales the asset so that its largest side is ``target_size_m`` and stands it on z = 0 at the
  origin (assets range from 7 cm toys to a 100 m fox).
- :func:`scene_mesh` collects the evaluated triangles of every renderable object into one ``trimesh.Trimesh``
  (world space): placement and camera checks use the real geometry, not bounding boxes, so concave assets (a
  chair, a vase of flowers) keep their real clearance.
- :func:`place_clutter` stands other assets around the main one, their footprints (the circle holding their
  vertices projected on the ground) not overlapping.
- :func:`camera_with_clearance` keys a seeded orbit or walk (``camera_paths``) and accepts it when every eye
  position stays ``clearance`` (a fraction of the framing radius) from every triangle and the main asset's centre
  is visible (not hidden by clutter) on at least 75% of the frames; else it tries the next seed, and keeps the best.
- :func:`build_asset_scene` does all of it for one dataset clip.
"""
from __future__ import annotations

import math
import random
from pathlib import Path

import bpy
import numpy as np

from ..errors import BlendSRError
from .camera_paths import GROUND_PROPERTY, GEOMETRY_TYPES, make_camera_path, object_boxes
from .default_scene import hdri_path, make_world
from .gltf_import import import_gltf

GROUND_SIZE_FACTOR = 8.0      # ground side = max(10 m, 8 x target size)
CAMERA_TRIES = 8
MIN_VISIBLE_FRACTION = 0.75


class AssetError(BlendSRError):
    """An asset that cannot be imported or placed; the message is one line naming the file."""


def import_asset(scene, path: Path) -> list:
    """Import a .gltf/.glb or append the objects of a .blend into ``scene``; returns the new top-level objects
    (cameras and lights of a .blend are left out: the environment lights the asset)."""
    path = Path(path)
    if not path.is_file():
        raise AssetError(f"{path}: asset file not found")
    from ..scene_refs import SceneRefError, check_scene_refs
    try:  # the one resolver, as for a scene file: an asset reads only inside its own folder
        check_scene_refs(path)
    except SceneRefError as exc:
        raise AssetError(str(exc)) from None
    before = set(bpy.data.objects)
    suffix = path.suffix.lower()
    if suffix in (".gltf", ".glb"):
        try:
            result = import_gltf(path)
        except RuntimeError as exc:
            raise AssetError(f"{path}: the glTF importer failed ({str(exc).splitlines()[0]})") from None
        if "FINISHED" not in result:
            raise AssetError(f"{path}: the glTF importer failed ({result})")
        new = [ob for ob in bpy.data.objects if ob not in before]
        for ob in new:
            if ob.name not in scene.objects:
                scene.collection.objects.link(ob)
    elif suffix == ".blend":
        try:
            with bpy.data.libraries.load(str(path), link=False) as (src, dst):
                dst.objects = [n for n in src.objects]
        except (OSError, RuntimeError) as exc:
            raise AssetError(f"{path}: Blender could not read it ({str(exc).splitlines()[0]})") from None
        new = []
        for ob in dst.objects:
            if ob is None:
                continue
            if ob.type in ("CAMERA", "LIGHT", "LIGHT_PROBE", "SPEAKER"):
                bpy.data.objects.remove(ob, do_unlink=True)
                continue
            scene.collection.objects.link(ob)
            new.append(ob)
    else:
        raise AssetError(f"{path}: not a .gltf, .glb or .blend file")
    new = [ob for ob in new if ob.name in bpy.data.objects]
    if not any(ob.type in GEOMETRY_TYPES for ob in new):
        raise AssetError(f"{path}: no renderable geometry imported")
    new_set = set(new)
    return [ob for ob in new if ob.parent not in new_set]


def _bounds(scene, objects) -> tuple[np.ndarray, np.ndarray]:
    """World AABB of the renderable geometry of ``objects`` and their children (evaluated, current frame)."""
    names = set()
    for ob in objects:
        names.add(ob.name)
        names.update(c.name for c in ob.children_recursive)
    boxes = [b for b in object_boxes(scene) if b.name in names]
    if not boxes:
        raise AssetError(f"objects {sorted(names)[:3]}: no renderable geometry")
    return np.min([b.lo for b in boxes], axis=0), np.max([b.hi for b in boxes], axis=0)


def normalise(scene, objects, target_size_m: float, name: str, location=(0.0, 0.0), rot_z: float = 0.0):
    """Parent ``objects`` to a new empty that scales them to ``target_size_m`` (largest side) and stands their
    bottom centre at ``location`` (x, y) on z = 0, turned by ``rot_z`` radians. Returns the empty."""
    scene.frame_set(scene.frame_start)
    lo, hi = _bounds(scene, objects)
    size = float((hi - lo).max())
    if not math.isfinite(size) or size <= 0:
        raise AssetError(f"{name}: degenerate bounds {lo} .. {hi}")
    s = target_size_m / size
    root = bpy.data.objects.new(f"{name} Root", None)
    scene.collection.objects.link(root)
    for ob in objects:
        ob.parent = root
    c = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    cz, sz = math.cos(rot_z), math.sin(rot_z)
    off = -s * np.array([cz * c[0] - sz * c[1], sz * c[0] + cz * c[1], c[2]])
    root.scale = (s, s, s)
    root.rotation_euler = (0.0, 0.0, rot_z)
    root.location = (float(location[0] + off[0]), float(location[1] + off[1]), float(off[2]))
    root["blendsr_asset"] = name
    root["blendsr_scale"] = s
    scene.frame_set(scene.frame_start)
    return root


def ground(scene, size: float, rng: random.Random):
    """A square ground at z = 0 (top face), ``size`` metres wide: 25 cm tiles with 3 mm joints in a seeded
    colour and roughness (``tiled_ground``)."""
    roughness = rng.uniform(0.35, 0.8)
    base = np.array([rng.uniform(0.25, 0.6), rng.uniform(0.25, 0.55), rng.uniform(0.2, 0.5)])
    offset = rng.choice((0.0, 0.5))
    tile = rng.choice((0.2, 0.25, 0.4))
    return tiled_ground(scene, size, colors=(tuple(base), tuple((base * rng.uniform(0.8, 1.15)).clip(0, 1))),
                        roughness=roughness, offset=offset, tile_m=tile)


def tiled_ground(scene, size: float, *, colors, roughness: float, offset: float = 0.0, tile_m: float = 0.25):
    """A square ground slab with its top face at z = 0, ``size`` metres wide, tagged ``GROUND_PROPERTY``: tiles of
    ``tile_m`` metres (rows shifted by ``offset`` of a tile) in two linear RGB ``colors``, 3 mm joints, one
    ``roughness``. Returns the object."""
    import bmesh
    from mathutils import Matrix, Vector

    mat = bpy.data.materials.new("Ground Tiles")
    nt = mat.node_tree
    bsdf = nt.nodes["Principled BSDF"]
    bsdf.inputs["Roughness"].default_value = roughness
    brick = nt.nodes.new("ShaderNodeTexBrick")
    brick.offset = offset
    for k, v in {"Color1": (*colors[0], 1), "Color2": (*colors[1], 1), "Mortar": (0.2, 0.2, 0.2, 1), "Scale": 1.0,
                 "Mortar Size": 0.003, "Brick Width": tile_m, "Row Height": tile_m}.items():
        brick.inputs[k].default_value = v
    tc = nt.nodes.new("ShaderNodeTexCoord")
    nt.links.new(tc.outputs["Object"], brick.inputs["Vector"])
    nt.links.new(brick.outputs["Color"], bsdf.inputs["Base Color"])
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=1.0, matrix=Matrix.LocRotScale(Vector((0, 0, -0.025)), None,
                                                                    Vector((size, size, 0.05))))
    mesh = bpy.data.meshes.new("Ground")
    bm.to_mesh(mesh)
    bm.free()
    mesh.materials.append(mat)
    obj = bpy.data.objects.new("Ground", mesh)
    obj[GROUND_PROPERTY] = True
    scene.collection.objects.link(obj)
    return obj


def scene_mesh(scene, frames=None, exclude=()):
    """One ``trimesh.Trimesh`` of every renderable, non-ground geometry object at each of ``frames`` (default: the
    current frame), world space. ``mesh.metadata['owner']`` holds, per face, the index into
    ``mesh.metadata['names']`` of the object it came from."""
    import trimesh

    frames = [scene.frame_current] if frames is None else list(frames)
    verts, faces, owner, names = [], [], [], []
    offset = 0
    for f in frames:
        scene.frame_set(int(f))
        dg = bpy.context.evaluated_depsgraph_get()
        for inst in dg.object_instances:
            ob = inst.object
            if ob.type not in GEOMETRY_TYPES or ob.original.hide_render or ob.original.get(GROUND_PROPERTY):
                continue
            if ob.original.name in exclude:
                continue
            try:
                me = ob.to_mesh()
            except RuntimeError:
                continue
            try:
                me.calc_loop_triangles()
                n = len(me.vertices)
                if n == 0 or len(me.loop_triangles) == 0:
                    continue
                v = np.empty(n * 3, dtype=np.float64)
                me.vertices.foreach_get("co", v)
                t = np.empty(len(me.loop_triangles) * 3, dtype=np.int64)
                me.loop_triangles.foreach_get("vertices", t)
            finally:
                ob.to_mesh_clear()
            m = np.array(inst.matrix_world, dtype=np.float64)
            v = v.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]
            name = ob.original.name
            if name not in names:
                names.append(name)
            verts.append(v)
            faces.append(t.reshape(-1, 3) + offset)
            owner.append(np.full(len(t) // 3, names.index(name)))
            offset += n
    if not verts:
        raise AssetError(f"scene {scene.name!r}: no renderable geometry")
    mesh = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)
    mesh.metadata["owner"] = np.concatenate(owner)
    mesh.metadata["names"] = names
    return mesh


def footprint_radius(mesh) -> tuple[np.ndarray, float]:
    """Centre (x, y) of the ground projection's bounding box and the radius (metres) of the circle about it that
    holds every vertex of ``mesh`` projected on the ground."""
    pts = mesh.vertices[:, :2]
    c = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    return c, float(np.linalg.norm(pts - c, axis=1).max())


def place_clutter(scene, main_names, clutter_paths, target_size_m: float, rng: random.Random) -> list[str]:
    """Stand each clutter asset (scaled to 40-80% of ``target_size_m``) on a ring around the main asset so that
    no two footprints overlap (20 tries each; an asset that does not fit is left out). Returns the names placed."""
    main = scene_mesh(scene, exclude=())
    keep = {i for i, n in enumerate(main.metadata["names"]) if n in main_names}
    c0, r0 = footprint_radius(main.submesh([np.isin(main.metadata["owner"], list(keep))], append=True)) \
        if keep else (np.zeros(2), target_size_m / 2)
    placed: list[tuple[np.ndarray, float]] = [(c0, r0)]
    names = []
    for k, path in enumerate(clutter_paths):
        objs = import_asset(scene, Path(path))
        size = target_size_m * rng.uniform(0.4, 0.8)
        root = normalise(scene, objs, size, f"{Path(path).stem} clutter {k}", (0.0, 0.0), rng.uniform(0, 2 * math.pi))
        sub_names = {root.name} | {c.name for c in root.children_recursive}
        m = scene_mesh(scene)
        own = [i for i, n in enumerate(m.metadata["names"]) if n in sub_names]
        cc, rc = footprint_radius(m.submesh([np.isin(m.metadata["owner"], own)], append=True))
        ok = False
        for _ in range(20):
            ang = rng.uniform(0.0, 2.0 * math.pi)
            dist = r0 + rc + rng.uniform(0.05, 0.6) * target_size_m
            pos = c0 + dist * np.array([math.cos(ang), math.sin(ang)])
            if all(np.linalg.norm(pos - pc) > pr + rc + 0.02 * target_size_m for pc, pr in placed):
                ok = True
                break
        if not ok:
            for ob in [root, *root.children_recursive]:
                bpy.data.objects.remove(ob, do_unlink=True)
            continue
        root.location = (root.location[0] + pos[0] - cc[0], root.location[1] + pos[1] - cc[1], root.location[2])
        placed.append((pos, rc))
        names.append(root.name)
    scene.frame_set(scene.frame_start)
    return names


def path_quality(mesh, eyes: np.ndarray, target: np.ndarray, main_owner: set[int], clearance: float) -> dict:
    """How a camera path sits in the geometry: least eye-to-triangle distance (metres) and the fraction of frames
    whose ray from the eye to ``target`` first hits the main asset (or nothing)."""
    import trimesh
    _, dist, _ = trimesh.proximity.closest_point(mesh, eyes)
    dirs = target[None] - eyes
    lengths = np.linalg.norm(dirs, axis=1)
    dirs = dirs / np.maximum(lengths[:, None], 1e-12)
    tri, ray, loc = mesh.ray.intersects_id(eyes, dirs, multiple_hits=False, return_locations=True)
    visible = np.ones(len(eyes), dtype=bool)
    for t, r, p in zip(tri, ray, loc):
        owner = int(mesh.metadata["owner"][t])
        if owner not in main_owner and np.linalg.norm(p - eyes[r]) < lengths[r] - 1e-6:
            visible[r] = False
    return {"min_distance": float(dist.min()), "visible_fraction": float(visible.mean()),
            "ok": bool(dist.min() >= clearance and visible.mean() >= MIN_VISIBLE_FRACTION)}


def camera_with_clearance(scene, kind: str, frames: tuple[int, int], seed: int, main_names,
                          clearance_fraction: float = 0.08):
    """Key a seeded ``kind`` path (``camera_paths.make_camera_path``) whose eyes keep ``clearance_fraction`` of
    the scene's size (largest side of the non-ground bounds) from every triangle (checked with trimesh on the
    evaluated geometry at the first, middle and last frame) and see the main asset; tries seeds
    seed, seed+1, ... up to ``CAMERA_TRIES``, keeps the first that passes or else the best. Returns (camera,
    report)."""
    start, end = frames
    mesh = scene_mesh(scene, frames=sorted({start, (start + end) // 2, end}))
    scene.frame_set(start)
    lo, hi = mesh.bounds
    size = float((hi - lo).max())
    clearance = clearance_fraction * size
    main_owner = {i for i, n in enumerate(mesh.metadata["names"]) if n in main_names}
    main_mesh = mesh.submesh([np.isin(mesh.metadata["owner"], list(main_owner))], append=True) if main_owner else mesh
    target = main_mesh.bounds.mean(axis=0)
    best = None
    for t in range(CAMERA_TRIES):
        cam = make_camera_path(scene, kind, frames, seed + t)
        eyes = []
        for f in range(start, end + 1):
            scene.frame_set(f)
            eyes.append(np.array(cam.matrix_world.translation, dtype=np.float64))
        q = path_quality(mesh, np.array(eyes), target, main_owner, clearance)
        q["seed"] = seed + t
        score = (q["ok"], q["visible_fraction"], q["min_distance"])
        if best is None or score > best[0]:
            best = (score, q)
        if q["ok"]:
            break
    q = best[1]
    if q["seed"] != seed + t:
        cam = make_camera_path(scene, kind, frames, q["seed"])
    scene.frame_set(start)
    q["clearance"] = clearance
    return cam, q


def build_asset_scene(job, *, frames: tuple[int, int], resolution: tuple[int, int],
                      ground_plane: bool = True) -> tuple[object, dict]:
    """A factory-empty scene with the dataset job's asset (``gbuffer_export.dataset.spec.ClipJob``: ``asset``,
    ``seed``, ``camera``, ``hdri``, ``hdri_rotation_deg``, ``hdri_strength``, ``target_size_m``, ``clutter``)
    normalised at the origin, a seeded ground, the HDRI world, clutter and a camera path with clearance. Returns
    (scene, info for the clip's manifest)."""
    asset, seed, camera, hdri = Path(job.asset), job.seed, job.camera, job.hdri
    hdri_rotation_deg, hdri_strength = job.hdri_rotation_deg, job.hdri_strength
    target_size_m, clutter = job.target_size_m, job.clutter
    rng = random.Random(seed)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    start, end = int(frames[0]), int(frames[1])
    scene.frame_start, scene.frame_end = start, end
    scene.render.resolution_x, scene.render.resolution_y = int(resolution[0]), int(resolution[1])
    scene.render.resolution_percentage = 100
    scene.frame_set(start)
    objs = import_asset(scene, asset)
    root = normalise(scene, objs, target_size_m, asset.stem, (0.0, 0.0), rng.uniform(0.0, 2.0 * math.pi))
    main_names = {root.name} | {c.name for c in root.children_recursive}
    placed = place_clutter(scene, main_names, [Path(c) for c in clutter], target_size_m, rng) if clutter else []
    if ground_plane:
        ground(scene, max(10.0, GROUND_SIZE_FACTOR * target_size_m), rng)
    make_world(scene, hdri_path(hdri), math.radians(hdri_rotation_deg), hdri_strength)
    cam, quality = camera_with_clearance(scene, camera, (start, end), seed, main_names)
    info = {"asset": asset.name, "asset_scale": float(root["blendsr_scale"]), "clutter": placed,
            "hdri": hdri, "hdri_rotation_deg": hdri_rotation_deg, "hdri_strength": hdri_strength,
            "camera_path": camera, "camera_seed": quality["seed"],
            "camera_min_distance_m": quality["min_distance"], "camera_clearance_m": quality["clearance"],
            "main_visible_fraction": quality["visible_fraction"]}
    return scene, info
