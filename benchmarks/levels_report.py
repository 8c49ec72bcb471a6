"""Per-level table of a levels dataset (docs/results.md): clips, cameras, clearance, background, depth, speed, time.

    .venv/bin/python benchmarks/levels_report.py datasets/levels

Reads each clip manifest's ``camera`` record and validates every clip (background and median depth measured on the
rendered HR depth of every frame).
"""
import json, sys, numpy as np
from pathlib import Path
from gbuffer_export.clip import load_manifest
from gbuffer_export.dataset.build import clip_dir, read_index
from gbuffer_export.validate import validate_clip
root = Path(sys.argv[1])
idx = read_index(root)
rows = {}
for c in idx["clips"]:
    folder = clip_dir(root, c)  # the one rule for index paths
    m = load_manifest(folder)
    cam = m["camera"]
    r = validate_clip(folder)
    views = r.stats.get("camera_view", {})
    bg = max(v["background_fraction"] for v in views.values())
    med = [v["median_depth_m"] for v in views.values()]
    secs = [m["frame_data"][k]["seconds_total"] for k in m["frame_data"]]
    lvl = c["source"]
    d = rows.setdefault(lvl, {"clips": 0, "kinds": set(), "splits": {}, "clear": [], "bg": [], "med": [], "speed": [], "secs": [], "extent": cam["level_extent_m"], "tris": cam["triangles"]})
    d["clips"] += 1; d["kinds"].add(c["camera"]); d["splits"][c["split"]] = d["splits"].get(c["split"], 0) + 1
    d["clear"].append(cam["clearance_m"]); d["bg"].append(bg); d["med"] += med; d["speed"].append((c["camera"], cam["speed_mps"])); d["secs"] += secs
print("| level | triangles | extent (m) | clips (train/val/test) | cameras | least clearance (m) | worst background | median depth (m) | speed (m/s) walk / fly | s per frame |")
print("|---|---|---|---|---|---|---|---|---|---|")
for lvl, d in rows.items():
    sp = d["splits"]
    w = [s for k, s in d["speed"] if k == "walk"]; f = [s for k, s in d["speed"] if k == "fly"]
    print(f"| {lvl} | {d['tris']:,} | {d['extent']:.1f} | {d['clips']} ({sp.get('train',0)}/{sp.get('val',0)}/{sp.get('test',0)}) | {', '.join(sorted(d['kinds']))} | {min(d['clear']):.2f} | {100*max(d['bg']):.0f}% | {min(d['med']):.1f} - {max(d['med']):.1f} | {np.median(w):.2f} / {np.median(f):.2f} | {np.median(d['secs']):.1f} |")
