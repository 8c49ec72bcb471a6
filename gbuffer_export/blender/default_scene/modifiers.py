"""Modifier-built geometry of the default scene (bpy layer): booleans, displacement, geometry-node instancing, each
evaluated and applied (the object keeps a plain mesh: nothing is re-evaluated at render time), and a small armature
that skins a mesh. Units are metres."""
from __future__ import annotations

import bpy
import numpy as np

#: The point attribute the instancing node group stores (the instance's index) to count the realised instances.
INSTANCE_ATTRIBUTE = "blendsr_instance"


def apply_modifiers(obj) -> None:
    """Replace ``obj``'s mesh by its evaluated mesh (every modifier applied) and remove the modifiers."""
    dg = bpy.context.evaluated_depsgraph_get()
    dg.update()
    mesh = bpy.data.meshes.new_from_object(obj.evaluated_get(dg), preserve_all_data_layers=True, depsgraph=dg)
    old = obj.data
    obj.modifiers.clear()
    obj.data = mesh
    mesh.name = obj.name
    if old.users == 0:
        bpy.data.meshes.remove(old)


def boolean_cut(obj, cutter) -> None:
    """Cut ``cutter`` (a mesh object of closed shells in ``obj``'s local coordinates, removed afterwards) out of
    ``obj`` with an exact Boolean difference, applied."""
    cutter.hide_render = True
    cutter.location, cutter.rotation_euler, cutter.scale = obj.location, obj.rotation_euler, obj.scale
    mod = obj.modifiers.new("Cut", "BOOLEAN")
    mod.operation, mod.solver, mod.object = "DIFFERENCE", "EXACT", cutter
    apply_modifiers(obj)
    mesh = cutter.data
    bpy.data.objects.remove(cutter, do_unlink=True)
    bpy.data.meshes.remove(mesh)


def displace(obj, texture: str, scale_m: float, strength_m: float, levels: int, seed: int) -> None:
    """Subdivide ``obj`` (``levels`` Catmull-Clark levels) and displace it along its normals by ``strength_m`` times a
    legacy procedural ``texture`` (``CLOUDS``, ``VORONOI``, ``STUCCI``, ``MARBLE``...) of ``scale_m`` metre features,
    centred on 0 (mid level 0.5), placed by ``seed``; applied."""
    tex = bpy.data.textures.new(f"{obj.name} Displacement", texture)
    tex.noise_scale = scale_m
    if hasattr(tex, "noise_depth"):
        tex.noise_depth = 2
    sub = obj.modifiers.new("Subdivide", "SUBSURF")
    sub.levels = sub.render_levels = levels
    mod = obj.modifiers.new("Displace", "DISPLACE")
    mod.texture, mod.strength, mod.mid_level = tex, strength_m, 0.5
    offset = bpy.data.objects.new(f"{obj.name} Texture Offset", None)   # texture space: shifted by the seed
    offset.location = tuple(np.random.default_rng(seed).uniform(-50.0, 50.0, size=3))
    mod.texture_coords, mod.texture_coords_object = "OBJECT", offset
    apply_modifiers(obj)
    bpy.data.objects.remove(offset)
    bpy.data.textures.remove(tex)
    for f in obj.data.polygons:
        f.use_smooth = True


def _socket(node, identifier: str):
    return next(s for s in node.inputs if s.identifier == identifier)


def _random(ng, kind: str, lo, hi, seed: int):
    """A Random Value node of ``kind`` (FLOAT_VECTOR, FLOAT, INT) in [lo, hi] with ``seed``; returns its output."""
    n = ng.nodes.new("FunctionNodeRandomValue")
    n.data_type = kind
    suffix = {"FLOAT_VECTOR": "", "FLOAT": "_001", "INT": "_002"}[kind]
    _socket(n, "Min" + suffix).default_value = lo
    _socket(n, "Max" + suffix).default_value = hi
    n.inputs["Seed"].default_value = seed
    return n.outputs[{"FLOAT_VECTOR": 0, "FLOAT": 1, "INT": 2}[kind]]


def scatter_node_group(name: str, sources, density: float, scale: tuple[float, float], seed: int):
    """A geometry node group: Distribute Points on Faces (``density`` per m2, ``seed``) + Instance on Points (one of
    the objects ``sources`` at random, turned at random about +Z and a little about X and Y, scaled by
    ``scale`` (low, high)) + Realize Instances, joined to the input mesh; each realised point stores its instance's
    index in ``INSTANCE_ATTRIBUTE``."""
    ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin, gout = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    coll = bpy.data.collections.new(f"{name} Sources")
    for ob in sources:
        coll.objects.link(ob)
    info = ng.nodes.new("GeometryNodeCollectionInfo")
    info.inputs["Collection"].default_value = coll
    info.inputs["Separate Children"].default_value = True
    info.inputs["Reset Children"].default_value = True
    dist = ng.nodes.new("GeometryNodeDistributePointsOnFaces")
    dist.inputs["Density"].default_value, dist.inputs["Seed"].default_value = density, seed
    inst = ng.nodes.new("GeometryNodeInstanceOnPoints")
    rot = ng.nodes.new("FunctionNodeEulerToRotation")
    links = ng.links
    links.new(gin.outputs[0], dist.inputs["Mesh"])
    links.new(dist.outputs["Points"], inst.inputs["Points"])
    links.new(info.outputs["Instances"], inst.inputs["Instance"])
    inst.inputs["Pick Instance"].default_value = True
    links.new(_random(ng, "INT", 0, len(sources) - 1, seed + 1), inst.inputs["Instance Index"])
    links.new(_random(ng, "FLOAT_VECTOR", (-0.3, -0.3, 0.0), (0.3, 0.3, 6.2832), seed + 2), rot.inputs["Euler"])
    links.new(rot.outputs["Rotation"], inst.inputs["Rotation"])
    links.new(_random(ng, "FLOAT", scale[0], scale[1], seed + 3), inst.inputs["Scale"])
    store = ng.nodes.new("GeometryNodeStoreNamedAttribute")
    store.data_type, store.domain = "INT", "INSTANCE"
    store.inputs["Name"].default_value = INSTANCE_ATTRIBUTE
    links.new(inst.outputs["Instances"], store.inputs["Geometry"])
    links.new(ng.nodes.new("GeometryNodeInputIndex").outputs["Index"], store.inputs["Value"])
    real = ng.nodes.new("GeometryNodeRealizeInstances")
    links.new(store.outputs["Geometry"], real.inputs["Geometry"])
    join = ng.nodes.new("GeometryNodeJoinGeometry")
    links.new(real.outputs["Geometry"], join.inputs["Geometry"])
    links.new(gin.outputs[0], join.inputs["Geometry"])
    links.new(join.outputs["Geometry"], gout.inputs[0])
    return ng


def instance_on_faces(obj, sources, density: float, scale: tuple[float, float], seed: int) -> int:
    """Scatter ``sources`` (mesh objects, not linked to the scene; removed afterwards) over ``obj``'s faces with
    :func:`scatter_node_group` as a Geometry Nodes modifier, applied; returns the number of realised instances."""
    ng = scatter_node_group(f"{obj.name} Scatter", sources, density, scale, seed)
    obj.modifiers.new("Scatter", "NODES").node_group = ng
    apply_modifiers(obj)
    attr = obj.data.attributes[INSTANCE_ATTRIBUTE]        # the input mesh's points hold 0, as instance 0 does
    ids = np.zeros(len(attr.data), dtype=np.int32)
    attr.data.foreach_get("value", ids)
    obj.data.attributes.remove(attr)
    coll = bpy.data.collections[f"{obj.name} Scatter Sources"]
    for ob in sources:
        mesh = ob.data
        bpy.data.objects.remove(ob, do_unlink=True)
        bpy.data.meshes.remove(mesh)
    bpy.data.collections.remove(coll)
    bpy.data.node_groups.remove(ng)
    return int(len(np.unique(ids)))
