"""Render cost: seconds per frame of the HR ground truth, the HR G-buffer pass, the LR render and the rest.

Renders the built-in default scene (or SCENE) into a temporary clip with ``blendsr render`` in a subprocess and
reads the per-pass wall-clock seconds from its manifest. Reports medians over the frames and the cost of
everything beyond the ground truth as a fraction of it (goal: < 10%); with ``--scales`` the LR render of every
level ('lr', 'lr_x<s>') as a fraction of the ground truth."""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ..errors import BlendSRError


def add_arguments(p) -> None:
    p.add_argument("scene", nargs="?", default=None, help=".blend to benchmark (default: the built-in scene)")
    p.add_argument("--hr-size", default="640x360", help="HR resolution WxH in pixels")
    p.add_argument("--scale", type=int, default=4, help="upscaling factor")
    p.add_argument("--scales", default=None, metavar="S1,S2,...",
                   help="several LR levels (see blendsr render --help); reports each level's LR render")
    p.add_argument("--frames", default="1:3", help="inclusive frame range A:B")
    p.add_argument("--hr-spp", type=int, default=64, help="samples per pixel of the ground truth")
    p.add_argument("--lr-spp", type=int, default=4, help="samples per pixel of the LR render")
    p.add_argument("--buffers", default="default", help="buffers to write (see blendsr render --help)")
    p.add_argument("--extra", default="", help="further 'blendsr render' arguments, quoted as one string")
    p.add_argument("--for-models", default=None, metavar="M1,M2",
                   help="render twice, with only the buffers these models read (plus radiance and motion) and with "
                        "--buffers all, and report the bytes and seconds per frame saved")
    p.add_argument("--json", type=Path, default=None, help="also write the results as JSON here")


def _median(xs):
    xs = sorted(xs)
    n = len(xs)
    return 0.0 if n == 0 else (xs[n // 2] if n % 2 else 0.5 * (xs[n // 2 - 1] + xs[n // 2]))


def summarize(manifest: dict) -> dict:
    """Median seconds per frame of each pass from a clip manifest. ``lr_render`` sums the LR renders of every
    level; ``levels`` holds each LR level's render seconds and their fraction of the ground truth."""
    rows = {"hr_ground_truth": [], "hr_gbuffer": [], "lr_render": [], "convert_and_write": [], "other": [],
            "total": []}
    lr_levels = [lvl for lvl in manifest["levels"] if lvl != "hr"]
    per_level: dict[str, list[float]] = {lvl: [] for lvl in lr_levels}
    for rec in manifest["frame_data"].values():
        hr = rec["hr"]["seconds"]
        gt, gb = hr.get("radiance", 0.0), hr.get("gbuffer", 0.0)
        cw = hr.get("convert", 0.0) + hr.get("write", 0.0)
        lrr = 0.0
        for lvl in lr_levels:
            sec = rec[lvl]["seconds"]
            per_level[lvl].append(sec.get("radiance", 0.0))
            lrr += sec.get("radiance", 0.0)
            cw += sec.get("convert", 0.0) + sec.get("write", 0.0)
        total = rec.get("seconds_total", gt + gb + lrr + cw)
        for k, v in (("hr_ground_truth", gt), ("hr_gbuffer", gb), ("lr_render", lrr), ("convert_and_write", cw),
                     ("other", max(total - gt - gb - lrr - cw, 0.0)), ("total", total)):
            rows[k].append(v)
    med = {k: _median(v) for k, v in rows.items()}
    gt = med["hr_ground_truth"]
    med["beyond_ground_truth_fraction"] = (med["total"] - gt) / gt if gt > 0 else float("nan")
    med["levels"] = {lvl: {"scale": float(manifest["levels"][lvl].get("scale", manifest["scale"])),
                           "size": [manifest["levels"][lvl]["width"], manifest["levels"][lvl]["height"]],
                           "render_s": _median(v), "fraction_of_ground_truth": _median(v) / gt if gt > 0 else None}
                     for lvl, v in per_level.items()}
    return med


def _render(args, buffers: str):
    """Render the benchmark clip with ``buffers``; returns (manifest, bytes of EXR per frame, wall s, command)."""
    with tempfile.TemporaryDirectory(prefix="blendsr-bench-") as tmp:
        out = Path(tmp) / "clip"
        cmd = [sys.executable, "-m", "gbuffer_export.cli", "render", *([args.scene] if args.scene else []),
               "-o", str(out), "--hr-size", args.hr_size, "--scale", str(args.scale),
               *(["--scales", args.scales] if getattr(args, "scales", None) else []), "--frames", args.frames,
               "--hr-spp", str(args.hr_spp), "--lr-spp", str(args.lr_spp), "--buffers", buffers,
               *args.extra.split()]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            last = proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "render failed"
            raise (BlendSRError if proc.returncode == 2 else RuntimeError)(last)  # 2: the render refused its input
        manifest = json.loads((out / "manifest.json").read_text())
        nbytes = sum(p.stat().st_size for p in out.rglob("*.exr"))
    return manifest, nbytes / max(len(manifest["frame_data"]), 1), wall, cmd


def run_for_models(args) -> int:
    """Bytes and seconds per frame of the buffers some models read against ``--buffers all``."""
    from ..dataset.buffers import buffers_for_models
    need = buffers_for_models([m for m in args.for_models.split(",") if m.strip()])
    rows = {}
    for label, buffers in (("for-models", ",".join(need)), ("all", "all")):
        manifest, per_frame, wall, cmd = _render(args, buffers)
        med = summarize(manifest)
        rows[label] = {"buffers": manifest["buffers"], "bytes_per_frame": per_frame,
                       "seconds_per_frame": med["total"], "beyond_ground_truth_s": med["total"] - med["hr_ground_truth"],
                       "hr_gbuffer_s": med["hr_gbuffer"], "command": " ".join(cmd[1:])}
    a, b = rows["for-models"], rows["all"]
    result = {"scene": args.scene or "built-in default", "hr_size": args.hr_size, "frames": args.frames,
              "models": args.for_models, **rows,
              "bytes_saved_fraction": 1 - a["bytes_per_frame"] / b["bytes_per_frame"],
              "seconds_saved_per_frame": b["seconds_per_frame"] - a["seconds_per_frame"]}
    print(f"buffers for {args.for_models} against --buffers all, {result['scene']} at {args.hr_size} "
          f"(median per frame)")
    for label, r in rows.items():
        print(f"  {label:<11} {r['bytes_per_frame'] / 1e6:8.3f} MB  {r['seconds_per_frame']:7.3f} s "
              f"(beyond ground truth {r['beyond_ground_truth_s']:.3f} s)  {','.join(r['buffers'])}")
    print(f"  saved: {100 * result['bytes_saved_fraction']:.1f}% of the bytes, "
          f"{result['seconds_saved_per_frame']:.3f} s per frame")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
    return 0


def run(args) -> int:
    from ..extras import require
    require("blendsr bench render", "render")
    if args.for_models:
        return run_for_models(args)
    try:
        manifest, _, wall, cmd = _render(args, args.buffers)
    except RuntimeError as exc:
        print(f"blendsr: error: bench render: {exc}", file=sys.stderr)
        return 1
    med = summarize(manifest)
    nframes = len(manifest["frame_data"])
    result = {"scene": args.scene or "built-in default", "hr_size": args.hr_size, "scale": args.scale,
              "scales": args.scales,
              "hr_spp": args.hr_spp, "lr_spp": args.lr_spp, "frames": nframes, "buffers": manifest["buffers"],
              "median_seconds_per_frame": med, "process_wall_seconds": wall,
              "startup_seconds": wall - sum(r.get("seconds_total", 0) for r in manifest["frame_data"].values()),
              "command": " ".join(cmd[1:])}
    print(f"render cost, {result['scene']} at {args.hr_size}, scale {args.scales or args.scale}, {nframes} frames "
          f"(median seconds per frame)")
    gt = med["hr_ground_truth"]
    for k in ("hr_ground_truth", "hr_gbuffer", "lr_render", "convert_and_write", "other", "total"):
        pct = f"{100 * med[k] / gt:6.1f}% of GT" if gt > 0 else ""
        print(f"  {k:<20} {med[k]:8.3f} s  {pct}")
        if k == "lr_render" and len(med["levels"]) > 1:
            for lvl, lv in med["levels"].items():
                w, h = lv["size"]
                frac = f"{100 * lv['fraction_of_ground_truth']:6.1f}% of GT" if gt > 0 else ""
                print(f"    {lvl:<18} {lv['render_s']:8.3f} s  {frac}  (x{lv['scale']:g}, {w}x{h})")
    print(f"  beyond ground truth: {100 * med['beyond_ground_truth_fraction']:.1f}% (goal < 10%)")
    print(f"  process startup and scene setup: {result['startup_seconds']:.1f} s once per clip")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
    return 0
