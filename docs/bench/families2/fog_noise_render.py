import sys, json, time
sys.path.insert(0, ".")
import bpy, numpy as np
from gbuffer_export.blender.default_scene import build_default_scene
mode = sys.argv[1]
scene = build_default_scene(seed=1, frames=(1, 2), resolution=(64, 36))
if mode == "world":
    w = scene.world.node_tree
    v = w.nodes.new("ShaderNodeVolumePrincipled"); v.inputs["Density"].default_value = 0.05
    out = next(n for n in w.nodes if n.type == "OUTPUT_WORLD")
    w.links.new(v.outputs[0], out.inputs["Volume"])
if mode == "box":
    import bmesh
    from gbuffer_export.blender.default_scene.geometry import add_object, box
    m = bpy.data.materials.new("Fog"); nt = m.node_tree
    for n in list(nt.nodes):
        if n.type != "OUTPUT_MATERIAL": nt.nodes.remove(n)
    v = nt.nodes.new("ShaderNodeVolumePrincipled"); v.inputs["Density"].default_value = float(sys.argv[2])
    v.inputs["Anisotropy"].default_value = 0.4
    nt.links.new(v.outputs[0], nt.nodes["Material Output"].inputs["Volume"])
    bm = bmesh.new(); box(bm, (0, 0.5, 1.75), (8, 8, 3.5)); add_object(scene, "Fog", bm, m)
scene.cycles.seed = int(sys.argv[3]) if len(sys.argv) > 3 else 0
scene.render.engine = "CYCLES"; scene.cycles.device = "CPU"; scene.cycles.samples = 32
scene.cycles.use_denoising = False; scene.render.threads_mode = "FIXED"; scene.render.threads = 2
scene.view_layers[0].use_pass_z = True
scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
scene.render.image_settings.color_depth = "32"
scene.render.filepath = f"/tmp/{mode}_{sys.argv[2] if len(sys.argv)>2 else 0}_{sys.argv[3] if len(sys.argv)>3 else 0}.exr"
t = time.time(); bpy.ops.render.render(write_still=True); print("T", time.time() - t)
