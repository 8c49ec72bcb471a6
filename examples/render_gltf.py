"""Render a BlendSR clip from a glTF/GLB model: import, normalise, light, save a .blend, run ``blendsr render``.

    python examples/render_gltf.py ../shared/scenes/gltf/WaterBottle/glTF/WaterBottle.gltf -o clips/bottle \\
        [--hdri ../shared/scenes/hdri/venice_sunset_1k.hdr] [--frames 1:24] [--hr-size 640x360] [--seed 3] ...

The model is scaled so that its largest side is 1.5 m (assets range from 7 cm toys to a 100 m-sized fox), set on a
ground plane at z = 0, and lit by the HDR environment (default: bpy's bundled ``courtyard``). The scene is saved,
with every image packed into it, as ``OUT_CLIP.blend`` beside the clip, then rendered by
``python -m gbuffer_export.cli render THAT.blend -o OUT_CLIP --camera-path orbit --frames A:B --hr-size WxH``;
any further arguments (``--seed``, ``--hr-spp``, ``--scale``, ``--camera-path walk`` ...) go to ``blendsr render``.
"""
from __future__ import annotations

import argparse
import math
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from gbuffer_export.config import parse_frames, parse_size  # noqa: E402  (pure Python)

TARGET_SIZE_M = 1.5      # largest side of the normalised model
DEFAULT_STUDIOLIGHT = "courtyard"


def _world_from_hdri(scene, hdri: Path | None) -> None:
    import bpy
    from gbuffer_export.blender.default_scene import studiolight_path
    path = Path(hdri) if hdri is not None else studiolight_path(DEFAULT_STUDIOLIGHT)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: HDRI not found")
    world = bpy.data.worlds.new("BlendSR World")
    nt = world.node_tree
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.load(str(path.resolve()), check_existing=True)
    nt.links.new(env.outputs["Color"], nt.nodes["Background"].inputs["Color"])
    world["blendsr_hdri"] = str(path.resolve())
    scene.world = world


def _ground(scene, size: float):
    """A square ground at z = 0 (top face), ``size`` metres wide, light grey 25 cm tiles with 3 mm joints."""
    from gbuffer_export.blender.assets import tiled_ground
    return tiled_ground(scene, size, colors=((0.42, 0.42, 0.40), (0.50, 0.49, 0.46)), roughness=0.6)


def build_gltf_scene(gltf_path, hdri=None, frames: tuple[int, int] = (1, 24),
                     resolution: tuple[int, int] = (640, 360), blend_path=None, ground: bool = True,
                     seed: int = 0) -> Path:
    """Import ``gltf_path`` into an empty factory scene, scale it so its largest side is 1.5 m with its bottom
    centre at the origin, add a ground (unless ``ground`` is False) and the HDRI world, set the frame range and
    resolution (100%), add an orbit camera (``blendsr render --camera-path scene`` can use it), pack the images and
    save. ``blend_path`` defaults to the model's name in the system temp folder. Returns the saved path."""
    import tempfile

    import bpy
    import numpy as np
    from gbuffer_export.blender.camera_paths import make_camera_path, object_boxes
    from gbuffer_export.blender.gltf_import import import_gltf

    gltf_path = Path(gltf_path).resolve()
    if not gltf_path.is_file():
        raise FileNotFoundError(f"{gltf_path}: glTF file not found")
    start, end = int(frames[0]), int(frames[1])
    if end < start:
        raise ValueError(f"frames {start}:{end}: end is before start")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    before = set(bpy.data.objects)
    result = import_gltf(gltf_path)  # Blender's importer, plus the material extensions BlendSR applies
    if "FINISHED" not in result:
        raise ValueError(f"{gltf_path}: the glTF importer failed ({result})")
    imported = [ob for ob in bpy.data.objects if ob not in before]
    if not imported:
        raise ValueError(f"{gltf_path}: no objects imported")

    scene.frame_start, scene.frame_end = start, end
    scene.render.resolution_x, scene.render.resolution_y = int(resolution[0]), int(resolution[1])
    scene.render.resolution_percentage = 100
    scene.frame_set(start)

    boxes = object_boxes(scene)
    if not boxes:
        raise ValueError(f"{gltf_path}: no renderable geometry")
    lo = np.min([b.lo for b in boxes], axis=0)
    hi = np.max([b.hi for b in boxes], axis=0)
    size = float((hi - lo).max())
    if not math.isfinite(size) or size <= 0:
        raise ValueError(f"{gltf_path}: degenerate bounds {lo} .. {hi}")
    scale = TARGET_SIZE_M / size

    root = bpy.data.objects.new("glTF Root", None)
    scene.collection.objects.link(root)
    for ob in imported:
        if ob.parent is None:
            ob.parent = root
    root.scale = (scale, scale, scale)
    root.location = (-scale * 0.5 * (lo[0] + hi[0]), -scale * 0.5 * (lo[1] + hi[1]), -scale * lo[2])
    root["blendsr_source"] = gltf_path.name
    root["blendsr_scale"] = scale
    scene.frame_set(start)

    if ground:
        _ground(scene, max(10.0, 8.0 * TARGET_SIZE_M))
    _world_from_hdri(scene, hdri)
    make_camera_path(scene, "orbit", (start, end), seed)

    if blend_path is None:
        blend_path = Path(tempfile.gettempdir()) / f"blendsr_{gltf_path.stem}.blend"
    blend_path = Path(blend_path).resolve()
    blend_path.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.file.pack_all()
    bpy.ops.wm.save_as_mainfile(filepath=str(blend_path), check_existing=False, compress=True)
    return blend_path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter,
                                epilog="Unknown arguments are passed on to 'blendsr render'.")
    p.add_argument("gltf", type=Path, help=".gltf or .glb file")
    p.add_argument("-o", "--output", type=Path, required=True, help="clip directory (the .blend goes beside it)")
    p.add_argument("--hdri", type=Path, default=None,
                   help=f"equirectangular .hdr/.exr environment; default: bpy's studiolight {DEFAULT_STUDIOLIGHT!r}")
    p.add_argument("--frames", default="1:24", metavar="A:B", help="inclusive frame range")
    p.add_argument("--hr-size", default="640x360", metavar="WxH", help="HR resolution in pixels")
    p.add_argument("--no-ground", action="store_true", help="do not add a ground plane under the model")
    p.add_argument("--camera-path", default="orbit", choices=("scene", "orbit", "walk"),
                   help="camera path passed to blendsr render")
    p.add_argument("--seed", type=int, default=0, help="seed of the camera path (passed to blendsr render too)")
    args, extra = p.parse_known_args(argv)
    frames = parse_frames(args.frames)
    size = parse_size(args.hr_size)
    out = args.output.resolve()
    blend = build_gltf_scene(args.gltf, hdri=args.hdri, frames=frames, resolution=size,
                             blend_path=out.with_name(out.name + ".blend"), ground=not args.no_ground, seed=args.seed)
    print(f"render_gltf: saved {blend}", flush=True)
    cmd = [sys.executable, "-m", "gbuffer_export.cli", "render", str(blend), "-o", str(out),
           "--camera-path", args.camera_path, "--frames", f"{frames[0]}:{frames[1]}",
           "--hr-size", f"{size[0]}x{size[1]}", "--seed", str(args.seed), *extra]
    print("render_gltf: " + " ".join(cmd), flush=True)
    return subprocess.run(cmd, cwd=str(REPO)).returncode


if __name__ == "__main__":
    sys.exit(main())
