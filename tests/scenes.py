"""Tiny .blend fixtures built in code, run as a script in a subprocess (bpy state is global and a crash in Blender
kills the process): ``python tests/scenes.py KIND OUT.blend``.

Kinds:
  basic     ground plane (no material), metal sphere, checkered cube that moves, sky visible, animated camera
  furnace   white furnace: uniform world of radiance 1, objects invisible to secondary rays, static camera
  finetex   white furnace with one plane filling the view whose base colour is a checker finer than a pixel
  nocamera  basic without camera
  empty     camera and world only
  ortho     basic with an orthographic camera
  occluder  a box sliding sideways in front of a wall (known disocclusions), camera panning slowly
  colours   basic plus an emissive cube of coloured base and emission colour (Linear Rec.709 working space)
  acescg    colours with the blend file's working colour space changed to ACEScg (its colours converted)
  dimlamp   basic lit by a point lamp of 0.01 W under a sky of strength 1e-4 (a level lit in other units)
  glasspane a checkered wall under the sky behind two thin panes: Principled glass (transmission 1) on the left
            half, a Glass BSDF on the right; sun and grey world, the camera moving slightly
  nopane    glasspane with both panes deleted (what "behind" G-buffers must describe)
  cutout    a wall behind a pane whose alpha is a cut-out mask (0 or 1) on its left half and 0.25 on its right
  nocutout  cutout without the pane (what the G-buffers must describe at its holes)
  imagetex  two planes filling the view side by side, each with a packed image texture (red/blue stripes; a green
            and white checker also driving a Bump node through a Non-Color copy), under a uniform grey world
"""
from __future__ import annotations

import sys


def _principled(name, **inputs):
    import bpy
    mat = bpy.data.materials.new(name)
    node = mat.node_tree.nodes["Principled BSDF"]
    for k, v in inputs.items():
        node.inputs[k].default_value = v
    return mat


def _world(strength_rgb):
    import bpy
    w = bpy.data.worlds.new("World")
    bpy.context.scene.world = w
    w.node_tree.nodes["Background"].inputs[0].default_value = (*strength_rgb, 1.0)
    w.node_tree.nodes["Background"].inputs[1].default_value = 1.0


def _camera(animated=True, ortho=False):
    import bpy
    sc = bpy.context.scene
    bpy.ops.object.camera_add(location=(0, -8, 2.2), rotation=(1.45, 0, 0))
    cam = bpy.context.object
    if ortho:
        cam.data.type = "ORTHO"
    sc.camera = cam
    if animated:
        cam.keyframe_insert("location", frame=0)
        cam.keyframe_insert("rotation_euler", frame=0)
        cam.location = (1.0, -7.0, 2.4)
        cam.rotation_euler = (1.43, 0.0, 0.12)
        cam.keyframe_insert("location", frame=10)
        cam.keyframe_insert("rotation_euler", frame=10)
    return cam


def basic(camera=True, ortho=False):
    import bpy
    bpy.ops.mesh.primitive_plane_add(size=30)
    bpy.ops.mesh.primitive_uv_sphere_add(location=(0, 0, 1))
    bpy.context.object.data.materials.append(_principled("metal", Metallic=1.0, Roughness=0.3))
    bpy.ops.mesh.primitive_cube_add(location=(2.5, 0, 0.5), size=1)
    cube = bpy.context.object
    mat = _principled("checker")
    nt = mat.node_tree
    chk = nt.nodes.new("ShaderNodeTexChecker")
    chk.inputs["Scale"].default_value = 20
    nt.links.new(chk.outputs["Color"], nt.nodes["Principled BSDF"].inputs["Base Color"])
    cube.data.materials.append(mat)
    cube.keyframe_insert("location", frame=0)
    cube.location = (2.5, 1.0, 0.5)
    cube.keyframe_insert("location", frame=10)
    _world((0.6, 0.7, 1.0))
    if camera:
        _camera(ortho=ortho)


def furnace():
    import bpy
    specs = [("white", dict(**{"Base Color": (1, 1, 1, 1)}, Roughness=0.5)),
             ("grey", dict(**{"Base Color": (0.5, 0.5, 0.5, 1)}, Roughness=0.2)),
             ("gold", dict(**{"Base Color": (1.0, 0.78, 0.34, 1)}, Metallic=1.0, Roughness=0.3)),
             ("red", dict(**{"Base Color": (0.8, 0.1, 0.1, 1)}, Roughness=0.7))]
    for i, (name, inputs) in enumerate(specs):
        bpy.ops.mesh.primitive_uv_sphere_add(location=((i - 1.5) * 2.2, 0, 0), segments=48, ring_count=24)
        ob = bpy.context.object
        bpy.ops.object.shade_smooth()
        ob.data.materials.append(_principled(name, **inputs))
        ob.visible_diffuse = ob.visible_glossy = ob.visible_transmission = False
        ob.visible_volume_scatter = ob.visible_shadow = False
    _world((1.0, 1.0, 1.0))
    _camera(animated=False)
    cam = bpy.context.scene.camera
    cam.location, cam.rotation_euler = (0, -9, 0), (1.5708, 0, 0)


def finetex():
    """A plane facing the camera under a uniform white world, invisible to secondary rays, its base colour a
    red/white checker of squares well under an HR pixel at 128x72 (a fabric weave finer than the pixel)."""
    import bpy
    bpy.ops.mesh.primitive_plane_add(size=20, location=(0, 0, 0), rotation=(1.5708, 0, 0))
    ob = bpy.context.object
    mat = _principled("weave", Roughness=0.6)
    chk = mat.node_tree.nodes.new("ShaderNodeTexChecker")
    chk.inputs["Scale"].default_value = 2000.0
    chk.inputs["Color1"].default_value = (0.9, 0.9, 0.9, 1)
    chk.inputs["Color2"].default_value = (0.6, 0.05, 0.05, 1)
    mat.node_tree.links.new(chk.outputs["Color"], mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
    ob.data.materials.append(mat)
    ob.visible_diffuse = ob.visible_glossy = ob.visible_transmission = False
    ob.visible_volume_scatter = ob.visible_shadow = False
    _world((1.0, 1.0, 1.0))
    cam = _camera(animated=False)
    cam.location, cam.rotation_euler = (0, -6, 0), (1.5708, 0, 0)


def occluder():
    """A 1.5 m box 6 m from the camera slides +0.5 m in x per frame in front of a wall 10 m away that fills the
    view; the camera turns by 0.2 degrees per frame. Frame t shows wall pixels the box covered in frame t-1."""
    import bpy
    bpy.ops.mesh.primitive_plane_add(size=40, location=(0, 2, 0), rotation=(1.5708, 0, 0))
    wall = _principled("wall")
    chk = wall.node_tree.nodes.new("ShaderNodeTexChecker")
    chk.inputs["Scale"].default_value = 30
    wall.node_tree.links.new(chk.outputs["Color"], wall.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
    bpy.context.object.data.materials.append(wall)
    bpy.ops.mesh.primitive_cube_add(location=(-2.0, -2, 0), size=1.5)
    box = bpy.context.object
    box.data.materials.append(_principled("box", **{"Base Color": (0.8, 0.2, 0.1, 1)}))
    box.keyframe_insert("location", frame=0)
    box.location = (3.0, -2, 0)
    box.keyframe_insert("location", frame=10)
    _world((0.5, 0.5, 0.5))
    cam = _camera(animated=False)
    cam.location, cam.rotation_euler = (0, -8, 0), (1.5708, 0, 0)
    cam.keyframe_insert("rotation_euler", frame=0)
    cam.rotation_euler = (1.5708, 0, 0.035)
    cam.keyframe_insert("rotation_euler", frame=10)
    for ob in (box, cam):
        for fc in ob.animation_data.action.fcurves if hasattr(ob.animation_data.action, "fcurves") else ():
            for kp in fc.keyframe_points:
                kp.interpolation = "LINEAR"


def _packed_image(name, size, colours, checker=False, non_color=False):
    """A ``size`` x ``size`` image alternating between two ``colours`` (RGB as stored) every 2 pixels: stripes
    along x, or a checker; packed into the .blend."""
    import bpy
    img = bpy.data.images.new(name, size, size)
    if non_color:  # before the pixels: a generated image's colour space change regenerates it
        img.colorspace_settings.name = "Non-Color"
    px = []
    for y in range(size):
        for x in range(size):
            px += [*colours[(x // 2 + (y // 2 if checker else 0)) % 2], 1.0]
    img.pixels[:] = px
    img.pack()
    return img


def imagetex():
    import bpy
    for i, (name, colours) in enumerate((("stripes", [(1.0, 0.0, 0.0), (0.0, 0.0, 1.0)]),
                                         ("checker", [(0.2, 0.8, 0.2), (0.9, 0.9, 0.9)]))):
        bpy.ops.mesh.primitive_plane_add(size=4, location=((i - 0.5) * 4.0, 0, 0), rotation=(1.5708, 0, 0))
        mat = _principled(name, Roughness=0.35)
        nt = mat.node_tree
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.image = _packed_image(name, 16, colours, checker=name == "checker")
        tex.interpolation = "Closest"
        nt.links.new(tex.outputs["Color"], nt.nodes["Principled BSDF"].inputs["Base Color"])
        if name == "checker":
            data = nt.nodes.new("ShaderNodeTexImage")
            data.image = _packed_image("checker_height", 16, [(0.0, 0.0, 0.0), (1.0, 1.0, 1.0)], checker=True,
                                       non_color=True)
            bump = nt.nodes.new("ShaderNodeBump")
            nt.links.new(data.outputs["Color"], bump.inputs["Height"])
            nt.links.new(bump.outputs["Normal"], nt.nodes["Principled BSDF"].inputs["Normal"])
        bpy.context.object.data.materials.append(mat)
    _world((0.5, 0.5, 0.5))
    cam = _camera(animated=False)
    cam.location, cam.rotation_euler = (0, -3.2, 0), (1.5708, 0, 0)


def _checker_wall(scale):
    """The 'wall' material of glasspane and cutout: roughness 0.6, a checker of orange and blue base colour."""
    wall = _principled("wall", Roughness=0.6)
    chk = wall.node_tree.nodes.new("ShaderNodeTexChecker")
    chk.inputs["Scale"].default_value = scale
    chk.inputs["Color1"].default_value = (0.8, 0.3, 0.1, 1)
    chk.inputs["Color2"].default_value = (0.1, 0.4, 0.8, 1)
    wall.node_tree.links.new(chk.outputs["Color"], wall.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
    return wall


def glasspane(panes=True):
    """Wall (checker, tilted) 8 m away, the sky above it; 4 mm panes 3 m from the camera: Principled glass covering
    x < 0, a Glass BSDF in x 0.6..1.6; the wall and the sky are also seen beside them."""
    import bpy
    bpy.ops.mesh.primitive_plane_add(size=6, location=(0, 2, -2.2), rotation=(1.5708 + 0.35, 0, 0.25),
                                     scale=(3, 1, 1))
    bpy.context.object.data.materials.append(_checker_wall(12))
    if panes:
        bpy.ops.mesh.primitive_cube_add(location=(-1.5, -3, -0.3), scale=(1.5, 0.002, 1.2))
        bpy.context.object.data.materials.append(_principled(
            "glass", **{"Base Color": (0.8, 0.95, 1.0, 1)}, Roughness=0.05, **{"Transmission Weight": 1.0}))
        bpy.ops.mesh.primitive_cube_add(location=(1.1, -3, 0.0), scale=(0.5, 0.002, 0.5))
        mat = bpy.data.materials.new("glass_bsdf")
        nt = mat.node_tree
        nt.nodes.remove(nt.nodes["Principled BSDF"])
        glass = nt.nodes.new("ShaderNodeBsdfGlass")
        nt.links.new(glass.outputs["BSDF"], nt.nodes["Material Output"].inputs["Surface"])
        bpy.context.object.data.materials.append(mat)
    bpy.ops.object.light_add(type="SUN", rotation=(0.6, 0.2, 0.3))
    bpy.context.object.data.energy = 3.0
    _world((0.5, 0.5, 0.5))
    cam = _camera(animated=False)
    cam.location, cam.rotation_euler = (0, -6, 0), (1.5708, 0, 0)
    cam.keyframe_insert("location", frame=0)
    cam.location = (0.05, -6, 0.03)
    cam.keyframe_insert("location", frame=10)


def cutout(pane=True):
    """A wall 8 m away filling the view (checker albedo, roughness 0.6) behind a 4 mm pane 3 m from the camera
    (green, roughness 0.9, metallic 1, two faces): its Principled Alpha is a thresholded checker (0 or 1, as the
    glTF importer cuts a MASK material) left of x = 0 and 0.25 right of it. ``pane=False``: the wall alone."""
    import bpy
    bpy.ops.mesh.primitive_plane_add(size=20, location=(0, 2, 0), rotation=(1.5708, 0, 0))
    bpy.context.object.data.materials.append(_checker_wall(10))
    if pane:
        bpy.ops.mesh.primitive_cube_add(location=(0, -3, 0), scale=(0.6, 0.002, 0.3))
        mat = _principled("cutout", **{"Base Color": (0.2, 0.8, 0.3, 1)}, Roughness=0.9, Metallic=1.0)
        nt = mat.node_tree
        coords, sep = nt.nodes.new("ShaderNodeTexCoord"), nt.nodes.new("ShaderNodeSeparateXYZ")
        nt.links.new(coords.outputs["Object"], sep.inputs[0])
        flat = nt.nodes.new("ShaderNodeCombineXYZ")  # the same cells on both faces
        nt.links.new(sep.outputs["X"], flat.inputs["X"])
        nt.links.new(sep.outputs["Z"], flat.inputs["Z"])
        cells = nt.nodes.new("ShaderNodeTexChecker")
        cells.inputs["Scale"].default_value = 3.0
        nt.links.new(flat.outputs[0], cells.inputs["Vector"])
        mask = nt.nodes.new("ShaderNodeMath")
        mask.operation = "GREATER_THAN"
        mask.inputs[1].default_value = 0.5
        nt.links.new(cells.outputs["Fac"], mask.inputs[0])
        right = nt.nodes.new("ShaderNodeMath")
        right.operation = "GREATER_THAN"
        right.inputs[1].default_value = 0.0
        nt.links.new(sep.outputs["X"], right.inputs[0])
        mix = nt.nodes.new("ShaderNodeMix")
        mix.data_type = "FLOAT"
        nt.links.new(right.outputs[0], mix.inputs["Factor"])
        nt.links.new(mask.outputs[0], mix.inputs["A"])
        mix.inputs["B"].default_value = 0.25
        nt.links.new(mix.outputs["Result"], nt.nodes["Principled BSDF"].inputs["Alpha"])
        bpy.context.object.data.materials.append(mat)
    _world((0.5, 0.5, 0.5))
    cam = _camera(animated=False)
    cam.location, cam.rotation_euler = (0, -6, 0), (1.5708, 0, 0)


def main(kind: str, out: str) -> None:
    import bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    if kind == "basic":
        basic()
    elif kind == "furnace":
        furnace()
    elif kind == "finetex":
        finetex()
    elif kind == "nocamera":
        basic(camera=False)
    elif kind == "empty":
        _world((0.5, 0.5, 0.5))
        _camera()
    elif kind == "ortho":
        basic(ortho=True)
    elif kind == "occluder":
        occluder()
    elif kind == "imagetex":
        imagetex()
    elif kind in ("glasspane", "nopane"):
        glasspane(panes=kind == "glasspane")
    elif kind in ("cutout", "nocutout"):
        cutout(pane=kind == "cutout")
    elif kind == "dimlamp":
        basic()
        sc.world.node_tree.nodes["Background"].inputs[1].default_value = 1e-4
        bpy.ops.object.light_add(type="POINT", location=(0.0, -3.0, 4.0))
        bpy.context.object.data.energy = 0.01
    elif kind in ("colours", "acescg"):
        basic()
        bpy.ops.mesh.primitive_cube_add(location=(-2.5, 0, 0.5), size=1)
        bpy.context.object.data.materials.append(_principled(
            "lamp", **{"Base Color": (0.7, 0.15, 0.05, 1), "Emission Color": (1.0, 0.35, 0.1, 1),
                       "Emission Strength": 3.0}))
        if kind == "acescg":
            bpy.ops.wm.set_working_color_space(working_space="ACEScg", convert_colors=True)
            assert bpy.data.colorspace.working_space == "ACEScg"
    else:
        raise SystemExit(f"unknown kind {kind}")
    sc.frame_start, sc.frame_end = 1, 10
    sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage = 64, 36, 100
    bpy.ops.wm.save_as_mainfile(filepath=out)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
