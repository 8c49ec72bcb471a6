"""Per level of a levels dataset, what issue 39's acceptance measures on each clip: the light chosen, the exposure,
the exposed log-average luminance and the share of dark pixels (HR radiance times the clip's exposure, Rec. 709 Y,
dark below 1e-3), the background share, the frames with near and far content (HR depth p90/p10 >= 3, background
as infinitely far), magenta pixels (red and blue both above 4x green: Cycles' missing-texture colour), metres per
unit and the render time per frame (the manifests' seconds_total; wall times of a shared machine).

    .venv/bin/python benchmarks/levels_usable.py DATASET      # a markdown table (docs/results.md)
"""
import json, sys, math
from pathlib import Path
import numpy as np
from gbuffer_export import open_clip
from gbuffer_export.dataset.build import read_index, clip_dir
root = Path(sys.argv[1]); idx = read_index(root)
per = {}
for c in idx["clips"]:
    clip = open_clip(clip_dir(root, c)); m = clip.manifest
    L = m.get("light", {})
    choice = "+".join(["file's" if L.get("kept") == "scene" else ""] + [a.get("kind", a) if isinstance(a, dict) else a for a in L.get("added", [])]).strip("+") or "file's"
    lum, dark, bg, nf, mag = [], [], [], [], 0
    for f in clip.frames:
        r = clip.read(f, "hr/radiance", exposed=True); y = r @ np.array([0.2126, 0.7152, 0.0722])
        lum.append(math.exp(np.log(np.maximum(y, 1e-8)).mean())); dark.append(float((y < 1e-3).mean()))
        d = clip.read(f, "hr/depth")[..., 0]; fin = np.isfinite(d) & (d > 0); bg.append(1 - fin.mean())
        dd = np.where(fin, d, np.inf); p10, p90 = np.quantile(dd, [0.1, 0.9], method="nearest")
        nf.append(bool(p90 / p10 >= 3) if np.isfinite(p10) else True)
        mag += int(((r[..., 0] > 4 * r[..., 1] + 1e-3) & (r[..., 2] > 4 * r[..., 1] + 1e-3)).sum())
    secs = [v["seconds_total"] for v in m["frame_data"].values()]
    p = per.setdefault(m["scene"]["file"], {"choice": set(), "exp": [], "lum": [], "dark": [], "bg": [], "nf": [], "mag": 0, "s": [], "unit": m["camera"].get("metres_per_unit"), "n": 0, "missing": len(m["scene"].get("missing_textures", []) or [])})
    p["choice"].add(choice); p["exp"].append(clip.exposure); p["lum"] += lum; p["dark"].append(max(dark)); p["bg"].append(max(bg)); p["nf"].append(float(np.mean(nf))); p["mag"] += mag; p["s"] += secs; p["n"] += 1
print("| level | clips | light chosen (per clip) | exposure | exposed log-average (min-max) | worst dark pixels | worst background | frames with near and far (worst clip) | magenta pixels | metres per unit | s per frame (median) |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for k, p in per.items():
    print(f"| {k} | {p['n']} | {', '.join(sorted(p['choice']))} | {min(p['exp']):.3g}-{max(p['exp']):.3g} | {min(p['lum']):.2f}-{max(p['lum']):.2f} | {max(p['dark']):.1%} | {max(p['bg']):.0%} | {min(p['nf']):.0%} | {p['mag']} | {p['unit']:.4g} | {np.median(p['s']):.1f} |")
