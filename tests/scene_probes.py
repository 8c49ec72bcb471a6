"""bpy probes for tests/test_scene_*.py, run in a subprocess: ``python tests/scene_probes.py PROBE JSON_ARGS``.

Each probe builds something with the bpy layer and prints one JSON line (prefixed ``PROBE-RESULT ``) describing what
Blender holds afterwards, so that the tests assert on plain data in their own process (bpy state is global and a
crash inside Blender kills the process)."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import bpy  # noqa: E402
import numpy as np  # noqa: E402

PRINCIPLED_INPUTS = ("Base Color", "Metallic", "Roughness", "IOR", "Transmission Weight", "Emission Color",
                     "Emission Strength", "Anisotropic", "Subsurface Weight", "Alpha", "Coat Weight", "Normal")


def _value(v):
    try:
        return [float(x) for x in v]
    except TypeError:
        return float(v)


def fcurves(idblock) -> list:
    """[(data_path, index, [frames], sorted interpolations)] of the ID's assigned action (slotted actions)."""
    ad = idblock.animation_data
    if ad is None or ad.action is None:
        return []
    out = []
    for layer in ad.action.layers:
        for strip in layer.strips:
            for cb in strip.channelbags:
                if ad.action_slot is not None and cb.slot != ad.action_slot:
                    continue
                for fc in cb.fcurves:
                    out.append((fc.data_path, fc.array_index, [kp.co[0] for kp in fc.keyframe_points],
                                sorted({kp.interpolation for kp in fc.keyframe_points})))
    return sorted(out)


def material_info(mat) -> dict:
    nt = mat.node_tree
    outs = [n for n in nt.nodes if n.type == "OUTPUT_MATERIAL"]
    surface = outs[0].inputs["Surface"].links if outs else []
    p = next((n for n in nt.nodes if n.type == "BSDF_PRINCIPLED"), None)
    info = {"surface": surface[0].from_node.type if surface else None,
            "node_types": sorted(n.type for n in nt.nodes), "inputs": {}}
    if p is not None:
        for name in PRINCIPLED_INPUTS:
            s = p.inputs[name]
            info["inputs"][name] = {"value": _value(s.default_value), "linked": s.is_linked}
    return info


def world_info(world) -> dict:
    if world is None or world.node_tree is None:
        return {}
    nt = world.node_tree
    bg = next((n for n in nt.nodes if n.type == "BACKGROUND"), None)
    link = bg.inputs["Color"].links if bg else []
    src = link[0].from_node if link else None
    image = getattr(src, "image", None)
    return {"background_color_from": src.type if src else None,
            "image": os.path.normpath(bpy.path.abspath(image.filepath)) if image is not None else None,
            "strength": float(bg.inputs["Strength"].default_value) if bg else None,
            "studiolights": bpy.utils.system_resource("DATAFILES", path="studiolights/world")}


def scene_summary(scene) -> dict:
    start, end = scene.frame_start, scene.frame_end
    objects = {}
    for ob in sorted(scene.objects, key=lambda o: o.name):
        d = {"type": ob.type, "matrix": [list(r) for r in ob.matrix_world],
             "materials": [m.name for m in getattr(ob.data, "materials", [])] if ob.data else [],
             "verts": len(ob.data.vertices) if ob.type == "MESH" else 0,
             "fcurves": fcurves(ob), "props": {k: _value(ob[k]) if not isinstance(ob[k], str) else ob[k]
                                                 for k in ob.keys() if not k.startswith("_")}}
        if ob.type == "MESH" and len(ob.data.vertices):
            co = np.empty(3 * len(ob.data.vertices))
            ob.data.vertices.foreach_get("co", co)
            m = np.array(ob.matrix_world)
            co = co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]
            d["bounds"] = [co.min(axis=0).tolist(), co.max(axis=0).tolist()]  # world space, m
        if ob.type == "CAMERA":
            d["camera"] = {"type": ob.data.type, "lens": ob.data.lens, "clip": [ob.data.clip_start, ob.data.clip_end]}
        objects[ob.name] = d
    # World matrices of the animated objects on every keyed frame.
    animated = [n for n, d in objects.items() if d["fcurves"]]
    per_frame = {n: [] for n in animated}
    for f in range(start - 1, end + 1):
        scene.frame_set(f)
        for n in animated:
            per_frame[n].append([list(r) for r in scene.objects[n].matrix_world])
    scene.frame_set(start)
    return {"frames": [start, end], "resolution": [scene.render.resolution_x, scene.render.resolution_y,
                                                   scene.render.resolution_percentage],
            "engine": scene.render.engine, "camera": scene.camera.name if scene.camera else None,
            "objects": objects, "materials": {m.name: material_info(m) for m in bpy.data.materials if m.users},
            "world": world_info(scene.world), "animated_matrices": per_frame,
            "images": sorted((i.name, i.source, bpy.path.abspath(i.filepath)) for i in bpy.data.images)}


# ----------------------------------------------------------------------------------------------
# Probes
# ----------------------------------------------------------------------------------------------

def probe_default(args) -> dict:
    """Factory engine, then one summary per (seed, frames, resolution) build."""
    from gbuffer_export.blender import default_scene as ds
    bpy.ops.wm.read_factory_settings(use_empty=True)
    factory = {"engine": bpy.context.scene.render.engine}
    builds = []
    for b in args["builds"]:
        scene = ds.build_default_scene(seed=b["seed"], frames=tuple(b["frames"]), resolution=tuple(b["resolution"]),
                                       props=tuple(b.get("props", ())))
        builds.append(scene_summary(scene))
    from gbuffer_export.blender.default_scene.families import CLASSES, RANGES
    return {"factory": factory, "builds": builds, "features": ds.DEFAULT_SCENE_FEATURES,
            "optional_props": ds.OPTIONAL_PROPS, "family_ranges": RANGES, "family_classes": CLASSES}


def probe_deformed(args) -> dict:
    """The default scene of ``seed``/``frames``/``props`` (as ``blendsr dataset`` builds a builtin clip) and, for each
    mesh an armature deforms: its rest vertices (object space, every ``every``-th), its skinning (per-vertex weight
    sums, vertices in no group, the groups of given rest regions), and per frame from start-1 to end the world-space
    evaluated vertices, the same rest vertices moved rigidly by the object's transform, and the largest ratio of an
    evaluated edge's length to its rest length; for each rig per frame its world matrix and per leg the thigh's
    keyed angle about X, the hip joint and the ankle (world)."""
    from gbuffer_export.blender.default_scene import build_default_scene
    scene = build_default_scene(seed=args["seed"], frames=tuple(args["frames"]), resolution=(64, 36),
                                props=tuple(args["props"]))
    every = args.get("every", 5)
    meshes = {o.name: _skinning(o, every) for o in scene.objects
              if o.type == "MESH" and any(m.type == "ARMATURE" for m in o.modifiers)}
    rigs = {o.name: {"matrix": [], "legs": {"L": [], "R": []}} for o in scene.objects if o.type == "ARMATURE"}
    for f in range(scene.frame_start - 1, scene.frame_end + 1):
        scene.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        for name, rec in meshes.items():
            _deformed_frame(scene.objects[name].evaluated_get(dg), rec, every)
        for name, rec in rigs.items():
            rig = scene.objects[name]
            m = np.array(rig.matrix_world)
            rec["matrix"].append(m.tolist())
            for side in "LR":
                thigh, shin = rig.pose.bones[f"thigh.{side}"], rig.pose.bones[f"shin.{side}"]
                hip, ankle = (m[:3, :3] @ np.array(p) + m[:3, 3] for p in (thigh.head, shin.tail))
                rec["legs"][side].append([thigh.rotation_euler[0], hip.tolist(), ankle.tolist()])
    return {"frames": [scene.frame_start, scene.frame_end], "meshes": meshes, "rigs": rigs,
            "params": {o.name: o["family_params"] for o in scene.objects if "family_params" in o},
            "starts": {o.name: o["walk_start"] for o in scene.objects if "walk_start" in o}}


def _skinning(ob, every: int) -> dict:
    """The rest and skinning part of ``probe_deformed``'s record of ``ob``."""
    rest = np.empty(3 * len(ob.data.vertices))
    ob.data.vertices.foreach_get("co", rest)
    rest = rest.reshape(-1, 3)
    h = float(rest[:, 2].max())
    names = {g.index: g.name for g in ob.vertex_groups}
    sums = np.array([sum(g.weight for g in v.groups) for v in ob.data.vertices])
    groups = [{names[g.group] for g in v.groups if g.weight > 0} for v in ob.data.vertices]
    feet = set().union(*[g for g, p in zip(groups, rest) if p[2] < 0.06 * h])
    hands = set().union(*[g for g, p in zip(groups, rest) if p[2] < 0.465 * h and abs(p[0]) > 0.125 * h])
    return {"height": h, "rest": rest[::every].tolist(), "weight_sum": [float(sums.min()), float(sums.max())],
            "ungrouped": int(sum(not g for g in groups)), "feet_groups": sorted(feet), "hand_groups": sorted(hands),
            "deformed": [], "rigid": [], "edge_stretch": []}


def _deformed_frame(ev, rec: dict, every: int) -> None:
    """Append one frame of ``ev`` (an evaluated, armature-deformed mesh object) to its ``probe_deformed`` record."""
    mesh = ev.to_mesh()
    co = np.empty(3 * len(mesh.vertices))
    mesh.vertices.foreach_get("co", co)
    ev.to_mesh_clear()
    co = co.reshape(-1, 3)
    rest = np.empty(3 * len(ev.original.data.vertices))
    ev.original.data.vertices.foreach_get("co", rest)
    rest = rest.reshape(-1, 3)
    edges = np.empty(2 * len(ev.original.data.edges), dtype=np.int64)
    ev.original.data.edges.foreach_get("vertices", edges)
    e = edges.reshape(-1, 2)
    stretch = np.linalg.norm(co[e[:, 0]] - co[e[:, 1]], axis=1) / np.linalg.norm(rest[e[:, 0]] - rest[e[:, 1]], axis=1)
    m = np.array(ev.matrix_world)
    rec["edge_stretch"].append(float(stretch.max()))
    for key, pts in (("deformed", co), ("rigid", rest)):
        rec[key].append((pts[::every] @ m[:3, :3].T + m[:3, 3]).tolist())


def _world_vertices(ev, matrix) -> np.ndarray:
    """(N, 3) world positions of the evaluated object ``ev``'s mesh vertices under ``matrix``."""
    mesh = ev.to_mesh()
    co = np.empty(3 * len(mesh.vertices))
    mesh.vertices.foreach_get("co", co)
    ev.to_mesh_clear()
    m = np.array(matrix)
    return co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]


def probe_walk_turn(args) -> dict:
    """One walker (1.7 m, 5 cm a frame) in an empty scene of frames 1-8: ``placement.measure``'s boxes of it (keyed at
    the origin heading +X), the world boxes of its evaluated vertices keyed so, and keyed again at each of
    ``starts`` ([x, y, direction]), per frame."""
    from gbuffer_export.blender.default_scene import placement
    from gbuffer_export.blender.default_scene.character import build_figure, key_walk
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 8
    rig, body = build_figure(scene, "Walker 1", 1.7, [bpy.data.materials.new(n) for n in ("a", "b", "c")])
    angles = {"swing": 0.45, "knee": 0.7, "arm": 0.35}

    def key(start):
        placement.unkey(rig)
        key_walk(rig, np.arange(0, 9), start[:2], start[2] * np.pi / 2, 0.05, 1.7, angles, 1.0)

    def vertex_boxes():
        out = []
        for f in range(1, 9):
            scene.frame_set(f)
            ev = body.evaluated_get(bpy.context.evaluated_depsgraph_get())
            co = _world_vertices(ev, ev.matrix_world)
            out.append([co.min(axis=0).tolist(), co.max(axis=0).tolist()])
        return out
    measured = [own.tolist() for own, _, _ in placement.measure(scene, body, key)]
    result = {"measured": measured, "origin": vertex_boxes(), "moved": []}
    for start in args["starts"]:
        key(start)
        result["moved"].append(vertex_boxes())
    return result


def probe_crowd(args) -> dict:
    """The default scene of ``seed``/``frames``/``props`` (``shown``: the frames a clip renders, default ``frames``)
    with its walkers: per walker per frame shown, how many of its
    evaluated vertices lie within ``gap`` metres of the box of any other object's (or instance's, or the other
    walker's) evaluated vertices (objects topped within ``sweep.STEP_M`` of the ground, the floor and fog left out),
    each walker's recorded start, and what of a walker is left in ``bpy.data`` (objects, meshes, armatures, actions,
    materials whose name starts with "Walker")."""
    from gbuffer_export.blender.default_scene import build_default_scene
    from gbuffer_export.sweep import STEP_M
    scene = build_default_scene(seed=args["seed"], frames=tuple(args["frames"]), resolution=(64, 36),
                                props=tuple(args["props"]), shown=tuple(args.get("shown", args["frames"])))
    walkers = sorted(o.name for o in scene.objects if o.type == "MESH" and o.name.startswith("Walker"))
    near = {w: [] for w in walkers}
    shown = args.get("shown", args["frames"])
    for f in range(shown[0], shown[1] + 1):
        scene.frame_set(f)
        verts, boxes = {}, []
        for inst in bpy.context.evaluated_depsgraph_get().object_instances:
            ob = inst.object
            if ob.type != "MESH" or ob.original.hide_render or ob.original.name in ("Floor", "Fog Volume"):
                continue
            co = _world_vertices(ob, inst.matrix_world)
            if not inst.is_instance and ob.original.name in walkers:
                verts[ob.original.name] = co
            elif len(co) and co[:, 2].max() > STEP_M:
                boxes.append((co.min(axis=0) - args["gap"], co.max(axis=0) + args["gap"]))
        for w, co in verts.items():
            inside = np.zeros(len(co), bool)
            others = [(c.min(axis=0) - args["gap"], c.max(axis=0) + args["gap"]) for v, c in verts.items() if v != w]
            for lo, hi in boxes + others:
                inside |= np.all((co > lo) & (co < hi), axis=1)
            near[w].append(int(inside.sum()))
    left = sorted(x.name for coll in (bpy.data.objects, bpy.data.meshes, bpy.data.armatures, bpy.data.actions,
                                      bpy.data.materials) for x in coll if x.name.startswith("Walker"))
    return {"walkers": walkers, "near": near, "left": left, "left_out": list(scene.get("blendsr_left_out", [])),
            "params": {w: json.loads(scene.objects[w]["family_params"]) for w in walkers},
            "starts": {w: json.loads(scene.objects[w]["walk_start"]) for w in walkers}}


def probe_walker_share(args) -> dict:
    """The default scene of ``seed``/``props`` (frames 1-8) with its walkers: each walker's share of the frame at
    ``frame`` by ``placement.frame_share`` (one ray per pixel of ``size``; ``ortho``: through the scene camera made
    orthographic, that many metres wide, after placement) and by Cycles (one sample a pixel, a
    0.01-pixel filter so that it lands on the pixel's centre, the Object Index pass; what the rays pass through,
    glass and alpha-cut objects, hidden from Cycles' camera rays), and what its walk start records."""
    from gbuffer_export.blender.default_scene import build_default_scene
    from gbuffer_export.blender.default_scene.placement import _see_through, frame_share
    from gbuffer_export.exr import read_exr_channels
    size = tuple(args["size"])
    scene = build_default_scene(seed=args["seed"], frames=(1, 8), resolution=size, props=tuple(args["props"]))
    walkers = sorted((o for o in scene.objects if o.type == "MESH" and o.name.startswith("Walker")),
                     key=lambda o: o.name)
    if args.get("ortho"):                         # judged as placed; then measured through an orthographic camera
        scene.camera.data.type, scene.camera.data.ortho_scale = "ORTHO", args["ortho"]
    rays = {w.name: frame_share(scene, w, [args["frame"]], grid=size) for w in walkers}
    cache = {}
    for ob in scene.objects:      # the rays go on through glass and alpha cuts: so do Cycles' camera rays here
        if ob.type == "MESH" and _see_through(ob, cache):
            ob.visible_camera = False
    for i, w in enumerate(walkers):
        w.pass_index = i + 1
    scene.render.engine = "CYCLES"
    scene.cycles.device, scene.cycles.samples, scene.cycles.use_denoising = "CPU", 1, False
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.filter_width = 0.01
    scene.render.threads_mode, scene.render.threads = "FIXED", 2
    scene.view_layers[0].use_pass_object_index = True
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = args["out"]
    scene.frame_set(args["frame"])
    bpy.ops.render.render(write_still=True)
    index = next(v for k, v in read_exr_channels(args["out"]).items() if k.endswith("Object Index.X"))
    rendered = {w.name: float(np.mean(np.rint(index) == i + 1)) for i, w in enumerate(walkers)}
    from gbuffer_export.blender.default_scene.families import FENCE_LANE_Y, SEEN_FLOOR
    return {"rays": rays, "rendered": rendered, "starts": {w.name: json.loads(w["walk_start"]) for w in walkers},
            "left_out": list(scene.get("blendsr_left_out", [])), "floor": SEEN_FLOOR, "fence_y": FENCE_LANE_Y}


def probe_default_render(args) -> dict:
    """Tiny Cycles render of the default scene with a Depth pass, written as a multilayer EXR."""
    from gbuffer_export.blender.default_scene import build_default_scene
    scene = build_default_scene(seed=args.get("seed", 0), frames=(1, 4), resolution=tuple(args.get("size", (64, 36))),
                                props=tuple(args.get("props", ())))
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 1
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.render.threads_mode = "FIXED"
    scene.render.threads = 2
    scene.view_layers[0].use_pass_z = True
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = args["out"]
    scene.frame_set(args.get("frame", 1))
    bpy.ops.render.render(write_still=True)
    return {"out": args["out"], "view_layer": scene.view_layers[0].name}


def _project(scene, cam, points) -> list:
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector
    return [list(world_to_camera_view(scene, cam, Vector(p))) for p in points]


def _camera_record(scene, cam, frames, points) -> dict:
    rec = {"matrices": [], "projected": []}
    for f in range(frames[0] - 1, frames[1] + 1):
        scene.frame_set(f)
        rec["matrices"].append([list(r) for r in cam.matrix_world])
        rec["projected"].append(_project(scene, cam, points))
    rec["fcurves"] = fcurves(cam)
    rec["clip"] = [cam.data.clip_start, cam.data.clip_end]
    rec["lens"] = cam.data.lens
    rec["type"] = cam.data.type
    rec["is_scene_camera"] = scene.camera == cam
    rec["name"] = cam.name
    return rec


def _paths(scene, frames, runs) -> dict:
    from gbuffer_export.blender import camera_paths as cp
    boxes = cp.clip_boxes(scene, tuple(frames))
    centre, radius = cp.framing_sphere(boxes)
    out = {"boxes": [[b.name, list(b.lo), list(b.hi), b.ground] for b in boxes], "centre": list(centre),
           "radius": radius, "bounds": [list(x) for x in cp.scene_bounds(scene)], "runs": []}
    for kind, seed in runs:
        n_actions = len(bpy.data.actions)
        cam = cp.make_camera_path(scene, kind, tuple(frames), seed)
        rec = _camera_record(scene, cam, frames, [centre])
        rec.update(kind=kind, seed=seed, n_cameras=sum(o.type == "CAMERA" and o.name.startswith(cp.CAMERA_NAME)
                                                      for o in bpy.data.objects),
                   actions_added=len(bpy.data.actions) - n_actions)
        out["runs"].append(rec)
    return out


def probe_paths_default(args) -> dict:
    """Camera paths on the default scene."""
    from gbuffer_export.blender.default_scene import build_default_scene
    scene = build_default_scene(seed=0, frames=tuple(args["frames"]))
    return _paths(scene, args["frames"], args["runs"])


def probe_paths_scaled(args) -> dict:
    """Camera paths on a factory scene holding two boxes and a ground plane, all scaled by ``scale``."""
    import bmesh
    from mathutils import Matrix, Vector
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = 320, 180
    s = args["scale"]

    def box(name, center, size):
        bm = bmesh.new()
        bmesh.ops.create_cube(bm, size=1.0, matrix=Matrix.LocRotScale(Vector(center) * s, None, Vector(size) * s))
        me = bpy.data.meshes.new(name)
        bm.to_mesh(me)
        bm.free()
        ob = bpy.data.objects.new(name, me)
        scene.collection.objects.link(ob)
        return ob

    box("Ground", (0, 0, -0.01), (30, 30, 0.02))  # unflagged: the heuristic must find it
    box("Block", (0.3, 0.1, 0.5), (1.0, 0.6, 1.0))
    box("Post", (-0.6, -0.2, 0.9), (0.1, 0.1, 1.8))
    hidden = box("Hidden", (50, 50, 50), (1, 1, 1))
    hidden.hide_render = True
    out = _paths(scene, args["frames"], args["runs"])
    out["scale"] = s
    return out


def probe_gltf(args) -> dict:
    """build_gltf_scene on each model; reopen each saved .blend and summarise it."""
    sys.path.insert(0, str(REPO / "examples"))
    from render_gltf import build_gltf_scene
    from gbuffer_export.blender import camera_paths as cp
    out = []
    for model, blend in args["models"]:
        path = build_gltf_scene(model, frames=(1, 6), resolution=(320, 180), blend_path=blend)
        bpy.ops.wm.open_mainfile(filepath=str(path))
        scene = bpy.context.scene
        rec = {"model": model, "blend": str(path), "frames": [scene.frame_start, scene.frame_end],
               "resolution": [scene.render.resolution_x, scene.render.resolution_y],
               "world": world_info(scene.world),
               "packed": [i.name for i in bpy.data.images if i.packed_file is not None],
               "unpacked": [i.name for i in bpy.data.images if i.source == "FILE" and i.packed_file is None],
               "camera": scene.camera.name if scene.camera else None, "per_frame": []}
        for f in (1, 6):
            scene.frame_set(f)
            boxes = cp.object_boxes(scene)
            rec["per_frame"].append([[b.name, list(b.lo), list(b.hi), b.ground] for b in boxes])
        out.append(rec)
    return {"models": out}


PROBES = {name[len("probe_"):]: fn for name, fn in globals().items() if name.startswith("probe_")}

if __name__ == "__main__":
    result = PROBES[sys.argv[1]](json.loads(sys.argv[2]) if len(sys.argv) > 2 else {})
    print("PROBE-RESULT " + json.dumps(result, default=lambda o: np.asarray(o).tolist()), flush=True)
