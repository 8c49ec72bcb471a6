"""Fit the export-time cost model of ``blender_addon/estimate.py`` on this machine (not shipped in the extension).

    python -m blender_addon.calibrate [-o DIR] [--frames 1:3]

Renders the built-in default scene with ``blendsr render`` at a few sizes and sample counts, reads the per-pass
wall-clock seconds from the manifests' frame records and fits, by least squares,
    path-traced render  t = RENDER_OVERHEAD_S  + K_PATH_S * samples         (HR ground truth and LR renders)
    G-buffer render     t = GBUFFER_OVERHEAD_S + K_GBUFFER_S * samples      (HR G-buffer pass)
    convert + write     t = K_WRITE_S * values                              (pixels x channels, both levels)
    rest of a frame     FRAME_OVERHEAD_S (mean of seconds_total minus the parts)
    first frame         STARTUP_S: the first frame's extra time (Cycles' scene sync and kernel setup), the mean
                        of its measured minus its modelled seconds
The fits use the frames after the first. Then prints the constants and each configuration's measured and
predicted seconds per frame.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

#: (hr size, hr spp, lr spp, gbuffer spp) of the calibration renders (scale 4).
CONFIGS = (("256x144", 16, 4, 1), ("256x144", 64, 16, 4), ("512x288", 32, 8, 8))


def render(out: Path, size: str, hr: int, lr: int, g: int, frames: str) -> dict:
    cmd = [sys.executable, "-m", "gbuffer_export.cli", "render", "-o", str(out), "--frames", frames,
           "--hr-size", size, "--hr-spp", str(hr), "--lr-spp", str(lr), "--gbuffer-spp", str(g), "--no-progress"]
    subprocess.run(cmd, check=True)
    return json.loads((out / "manifest.json").read_text())


def fit_line(x, y) -> tuple[float, float]:
    """(intercept, slope) of the least-squares line, intercept clamped at 0."""
    a = np.stack([np.ones(len(x)), np.asarray(x, float)], axis=1)
    c, k = np.linalg.lstsq(a, np.asarray(y, float), rcond=None)[0]
    if c < 0:
        c, k = 0.0, float(np.dot(x, y) / np.dot(x, x))
    return float(c), float(k)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("-o", "--output", type=Path, default=None, help="folder for the clips (default: a temp dir)")
    p.add_argument("--frames", default="1:3", help="frames A:B of each calibration clip")
    a = p.parse_args(argv)
    root = a.output or Path(tempfile.mkdtemp(prefix="blendsr-calibrate-"))
    from gbuffer_export.conventions import BUFFERS
    path_pts, gbuf_pts, io_pts, rows = [], [], [], []
    for i, (size, hr, lr, g) in enumerate(CONFIGS):
        m = render(root / f"c{i}", size, hr, lr, g, a.frames)
        w, h = m["levels"]["hr"]["width"], m["levels"]["hr"]["height"]
        lw, lh = m["levels"]["lr"]["width"], m["levels"]["lr"]["height"]
        chans = sum(len(BUFFERS[b].channels) for b in m["buffers"])
        totals, first = [], None
        for fkey in sorted(m["frame_data"], key=int):
            rec = m["frame_data"][fkey]
            hs, ls = rec["hr"]["seconds"], rec["lr"]["seconds"]
            if first is None:
                first = rec["seconds_total"]
                continue
            path_pts += [(w * h * hr, hs["radiance"]), (lw * lh * lr, ls["radiance"])]
            gbuf_pts.append((w * h * g, hs["gbuffer"]))
            io = hs["convert"] + hs["write"] + ls["convert"] + ls["write"]
            io_pts.append(((w * h + lw * lh) * chans, io))
            totals.append((rec["seconds_total"], hs["radiance"] + ls["radiance"] + hs["gbuffer"] + io))
        rows.append(dict(name=f"{size} hr{hr} lr{lr} g{g}", dims=(w, h, lw, lh, hr, lr, g, chans),
                         totals=totals, first=first))
    c0, k = fit_line(*zip(*path_pts))
    cg, kg = fit_line(*zip(*gbuf_pts))
    xs, ys = np.array([v for v, _ in io_pts], float), np.array([t for _, t in io_pts], float)
    kw = float(np.dot(xs, ys) / np.dot(xs, xs))
    frame_overhead = float(np.mean([tot - parts for r in rows for tot, parts in r["totals"]]))

    def model(w, h, lw, lh, hr, lr, g, chans):
        return (2 * c0 + k * (w * h * hr + lw * lh * lr) + cg + kg * w * h * g
                + kw * (w * h + lw * lh) * chans + frame_overhead)
    startup = float(np.mean([r["first"] - model(*r["dims"]) for r in rows]))
    print(f"RENDER_OVERHEAD_S = {c0:.3g}\nK_PATH_S = {k:.3g}\nGBUFFER_OVERHEAD_S = {cg:.3g}\nK_GBUFFER_S = {kg:.3g}"
          f"\nK_WRITE_S = {kw:.3g}\nFRAME_OVERHEAD_S = {frame_overhead:.3g}\nSTARTUP_S = {startup:.3g}")
    for r in rows:
        pred, first = model(*r["dims"]), r["first"]
        meas = [t for t, _ in r["totals"]]
        print(f"{r['name']}: measured {np.mean(meas):.2f} s/frame after the first "
              f"(frames {', '.join(f'{t:.2f}' for t in meas)}; first {first:.2f}), model {pred:.2f} s/frame")
    print(f"clips in {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
