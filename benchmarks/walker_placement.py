"""How often the built-in walkers (``motion_character``) find a place clear of another family's objects (issue 54:
a walker passes through nothing; one without room is left out). For each family and seed: the default scene with
that family and the walkers (``build_default_scene`` as an 8-frame dataset clip builds it, nothing rendered), and
how many of the walkers drawn (the family's first draw, ``count``) were placed, where (behind the table, behind the
fence, in front), and the share of the frame each placed walker covers as placement measured it (``frame_share`` of
its walk start: ``placement.frame_share``, the mean of the first, middle and last frames shown), the number that
``families.SEEN_MIN`` and ``SEEN_FLOOR`` bound.

    .venv/bin/python benchmarks/walker_placement.py --seeds 1:6 --crowd boolean,motion_objects,mat_surfaces \\
        --crowd mat_brick,mat_wave,wires,railing -o docs/bench/families/walker_placement.json

Prints one line per family (placed of drawn over the seeds) and writes the per-seed table as JSON.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def drawn(seed: int) -> int:
    """The number of walkers the family draws for ``seed`` (its stream's first draw)."""
    from gbuffer_export.blender.default_scene.families import FAMILIES, RANGES
    lo, hi = RANGES["motion_character"]["count"]
    return int(np.random.default_rng([seed & 0xFFFFFFFF, FAMILIES["motion_character"][1]]).integers(lo, hi + 1))


def placed(families: tuple[str, ...], seed: int) -> dict[str, dict]:
    """The walkers placed in seed ``seed`` beside ``families``: name -> its walk start (``lane_m``: its lane's y in
    m, ``frame_share``)."""
    from gbuffer_export.blender.default_scene import build_default_scene
    from gbuffer_export.blender.default_scene.families import WALK_START
    scene = build_default_scene(seed=seed, frames=(1, 48), resolution=(64, 36), props=(*families, "motion_character"),
                                shown=(1, 8))     # as blendsr dataset builds an 8-frame builtin clip
    return {o.name: json.loads(o[WALK_START]) for o in scene.objects
            if o.get("blendsr_family") == "motion_character" and o.type == "MESH"}


def main(argv=None) -> int:
    from gbuffer_export.blender.default_scene import OPTIONAL_PROPS
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="1:6", help="first:last seed, inclusive (default 1:6)")
    ap.add_argument("--families", nargs="*", help="props beside the walkers (default: every other one, the panes too)")
    ap.add_argument("--crowd", action="append", default=[], metavar="FAM,FAM",
                    help="also a row of these families together (repeatable)")
    ap.add_argument("-o", "--output", type=Path, help="write the per-seed table here (JSON)")
    args = ap.parse_args(argv)
    first, last = map(int, args.seeds.split(":"))
    families = args.families or [f for f in OPTIONAL_PROPS if f != "motion_character"]
    from gbuffer_export.blender.default_scene.families import FENCE_LANE_Y
    table = {}
    for fams in [(), *((f,) for f in families), *(tuple(c.split(",")) for c in args.crowd)]:
        rows = [{"seed": s, "drawn": drawn(s), "placed": placed(fams, s)} for s in range(first, last + 1)]
        name = ",".join(fams) or "(alone)"
        table[name] = rows
        starts = [s for r in rows for s in r["placed"].values()]
        lanes, shares = [s["lane_m"] for s in starts], [100 * s["frame_share"] for s in starts]
        print(f"{name}: {len(lanes)} of {sum(r['drawn'] for r in rows)} placed, "
              f"{sum(y > FENCE_LANE_Y for y in lanes)} behind the fence, {sum(y < 0 for y in lanes)} in front; "
              f"frame share {min(shares, default=0):.2f}-{max(shares, default=0):.2f} %", flush=True)
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.output.with_suffix(".tmp")
        record = {"seeds": [first, last], "frames": [1, 48], "shown": [1, 8], "families": table}
        tmp.write_text(json.dumps(record, indent=1) + "\n")
        tmp.replace(args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
