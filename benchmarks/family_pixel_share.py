"""How much of the frame a built-in generator family's objects cover (issue 54: material classes on surfaces as large
as a game shows them). For each seed: the default scene with the family alone (``build_default_scene``, 8 frames),
one Cycles sample of the Object Index pass at frame 4, and the percentage of pixels each of the family's objects
(``blendsr_family``) covers; seeds render in this process, one Cycles thread.

    .venv/bin/python benchmarks/family_pixel_share.py mat_surfaces mat_noise --seeds 1:6 --size 256x144 \\
        -o docs/bench/families/pixel_share.json

    .venv/bin/python benchmarks/family_pixel_share.py motion_character --beside boolean,motion_objects,mat_surfaces \\
        -o docs/bench/families/walker_pixel_share_crowd.json

Prints one line per family and object (median and range over the seeds) and writes the per-seed table as JSON.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def shares(family: str, seed: int, size: tuple[int, int], tmp: Path, beside=()) -> dict[str, float]:
    """Percent of the frame each object of ``family`` covers in seed ``seed`` at ``size`` (``beside``: other props
    in the scene too, their objects counted as background)."""
    import bpy
    from gbuffer_export.blender.default_scene import build_default_scene
    from gbuffer_export.exr import read_exr_channels
    scene = build_default_scene(seed=seed, frames=(1, 8), resolution=size, props=(*beside, family))
    names = {}
    for i, ob in enumerate(o for o in scene.objects if o.get("blendsr_family") == family):
        ob.pass_index, names[i + 1] = i + 1, ob.name
    scene.render.engine = "CYCLES"
    scene.cycles.samples, scene.cycles.use_denoising = 1, False
    scene.render.threads_mode, scene.render.threads = "FIXED", 1
    scene.view_layers[0].use_pass_object_index = True
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = str(tmp / f"{family}-{seed}.exr")
    scene.frame_set(4)
    bpy.ops.render.render(write_still=True)
    index = next(v for k, v in read_exr_channels(scene.render.filepath).items() if k.endswith("Object Index.X"))
    return {name: round(float(np.mean(np.rint(index) == i) * 100), 2) for i, name in names.items()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("families", nargs="+", help="built-in generator families (props of a builtin source)")
    p.add_argument("--seeds", default="1:6", help="inclusive seed range A:B (default 1:6)")
    p.add_argument("--size", default="256x144", help="frame size WxH in pixels (default 256x144, the scale set's)")
    p.add_argument("--beside", default="", metavar="FAM,FAM",
                   help="other props in every scene (their objects are not counted; default none)")
    p.add_argument("-o", "--out", type=Path, help="write {family: {seed: {object: percent}}} here (JSON)")
    a = p.parse_args(argv)
    lo, hi = (int(x) for x in a.seeds.split(":"))
    size = tuple(int(x) for x in a.size.lower().split("x"))
    table = {}
    beside = tuple(filter(None, a.beside.split(",")))
    with tempfile.TemporaryDirectory() as tmp:
        for family in a.families:
            table[family] = {str(s): shares(family, s, size, Path(tmp), beside) for s in range(lo, hi + 1)}
    for family, per_seed in table.items():
        for name in sorted({n for v in per_seed.values() for n in v}):
            v = [d.get(name, 0.0) for d in per_seed.values()]
            print(f"{family:>14} {name:<22} median {np.median(v):6.2f} %  range {min(v):.2f}-{max(v):.2f} %")
    if a.out:
        a.out.write_text(json.dumps({"command": " ".join(sys.argv), "size": list(size), "shares": table}, indent=1)
                         + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
