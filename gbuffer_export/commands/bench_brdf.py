"""Accuracy and cost of the F_beta sources (cycles, lut, lut-paper, model) against a white furnace.

Builds a furnace scene (uniform world of radiance 1, a grid of spheres with one Principled material each, invisible
to secondary rays) with bpy in a subprocess, renders it with 'blendsr render' (one clip per seed, in subprocesses),
and compares each source's F_beta, computed from the clip's G-buffers, with the furnace truth radiance - emission
(the mean over seeds) per material at both levels. Pixels are assigned to materials by casting the clip camera's
rays against the known sphere layout; only pixels whose whole pixel-filter footprint lies on one sphere count.

Metrics per material and level, over pixels and channels: rel-MAE = mean |F - T| / max(mean T, 0.01),
bias = (mean F - mean T) / max(mean T, 0.01); the truth's own noise floor (mean |T_seed1 - T_seed2| / 2, same
denominator: what noise adds to rel-MAE) is reported beside them. At HR also after a second-order model of the HR
pixel filter (the truth is filtered, the G-buffers are point-sampled). Also the per-frame time of each table source. Writes JSON, a PNG chart and (optionally) the
results block of a markdown file (--docs docs/brdf.md in a checkout; never by default).
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from ..errors import BlendSRError

from ..extras import HelpFormatter

SOURCES = ("cycles", "lut", "lut-paper", "model")
DOC_BEGIN = "<!-- bench-brdf:begin (written by 'blendsr bench brdf') -->"
DOC_END = "<!-- bench-brdf:end -->"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = HelpFormatter
    p.add_argument("--out", type=Path, default=Path("bench_results/brdf"),
                   help="folder for brdf.json and brdf.png")
    p.add_argument("--work", type=Path, default=None,
                   help="folder for the .blend and the clips (kept); default: a temporary folder, deleted")
    p.add_argument("--reuse", action="store_true", help="reuse the scene and clips already in --work")
    p.add_argument("--hr-size", default="640x480", metavar="WxH", help="HR size in pixels (8 x 6 spheres)")
    p.add_argument("--scale", type=int, default=4, help="LR = HR / scale")
    p.add_argument("--spp", type=int, default=1024, help="samples per pixel per seed, both levels")
    p.add_argument("--seeds", type=int, default=2, help="independent renders (>= 2 measures the truth's noise)")
    p.add_argument("--sources", default=",".join(SOURCES), help="comma-separated F_beta sources to compare")
    p.add_argument("--docs", type=Path, default=None, metavar="FILE.md",
                   help="also replace the results block of this markdown file (the project's is docs/brdf.md); "
                        "default: no file is rewritten")
    p.add_argument("--threads", type=int, default=0,
                   help="render threads (0 = OMP_NUM_THREADS where set, else all cores)")


# ----------------------------------------------------------------------------------------------
# Rendering (subprocesses; bpy never enters this process)
# ----------------------------------------------------------------------------------------------

def _run(cmd: list[str], log: Path) -> float:
    t = time.perf_counter()
    with open(log, "a") as f:
        f.write("$ " + shlex.join(cmd) + "\n")
        f.flush()
        proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT)
    if proc.returncode != 0:
        raise RuntimeError(f"{shlex.join(cmd)} failed with exit code {proc.returncode}; see {log}")
    return time.perf_counter() - t


def render_furnace(work: Path, size: tuple[int, int], scale: int, spp: int, seeds: int, threads: int,
                   reuse: bool) -> dict:
    """Build the scene and render one clip per seed; returns paths, commands and wall times."""
    work.mkdir(parents=True, exist_ok=True)
    log = work / "render.log"
    blend, layout = work / "furnace.blend", work / "layout.json"
    info = {"blend": str(blend), "layout": str(layout), "clips": [], "commands": [], "seconds": {}}
    py = sys.executable
    if not (reuse and blend.is_file() and layout.is_file()):
        cmd = [py, "-m", "gbuffer_export.blender.furnace", str(blend), str(layout), "--size", str(size[0]),
               str(size[1])]
        info["seconds"]["scene"] = _run(cmd, log)
        info["commands"].append(shlex.join(cmd))
    for s in range(seeds):
        clip = work / f"clip_seed{s}"
        cmd = [py, "-m", "gbuffer_export.cli", "render", str(blend), "-o", str(clip), "--frames", "1:1",
               "--hr-size", f"{size[0]}x{size[1]}", "--scale", str(scale), "--hr-spp", str(spp), "--lr-spp", str(spp),
               "--buffers", "all", "--jitter", "none", "--seed", str(s), "--threads", str(threads), "--no-progress"]
        if not (reuse and (clip / "manifest.json").is_file()):
            info["seconds"][f"render_seed{s}"] = _run(cmd, log)
        info["commands"].append(shlex.join(cmd))
        info["clips"].append(str(clip))
    return info


# ----------------------------------------------------------------------------------------------
# Material masks from the layout (pure numpy)
# ----------------------------------------------------------------------------------------------

def sphere_ids(layout: dict, world_from_camera: np.ndarray, k, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Index of the sphere each camera ray through image positions (xs, ys) hits first (-1: none)."""
    from ..conventions import rays_camera

    m = np.asarray(world_from_camera, dtype=np.float64)
    d = rays_camera(xs, ys, k) @ m[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = m[:3, 3]
    best = np.full(xs.shape, np.inf)
    ids = np.full(xs.shape, -1, dtype=np.int64)
    for i, sph in enumerate(layout["spheres"]):
        oc = o - np.asarray(sph["centre"], dtype=np.float64)
        b = d @ oc
        disc = b * b - (oc @ oc - sph["radius"] ** 2)
        with np.errstate(invalid="ignore"):
            t = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        hit = (t > 0) & (t < best)
        best = np.where(hit, t, best)
        ids = np.where(hit, i, ids)
    return ids


def material_map(layout: dict, camera: dict, size: tuple[int, int], margin: float) -> np.ndarray:
    """H x W sphere index of pixels whose centre and the 8 points at +-margin px all hit the same sphere
    (-1 elsewhere: background, silhouettes, pixels the pixel filter mixes)."""
    from ..conventions import pixel_grid

    w, h = size
    xs, ys = pixel_grid(h, w)
    k = tuple(float(v) for v in camera["intrinsics"])
    jit = camera.get("jitter", (0.0, 0.0))
    xs, ys = xs + float(jit[0]), ys + float(jit[1])
    ids = sphere_ids(layout, camera["world_from_camera"], k, xs, ys)
    for dx in (-margin, 0.0, margin):
        for dy in (-margin, 0.0, margin):
            if dx == 0.0 and dy == 0.0:
                continue
            ids = np.where(sphere_ids(layout, camera["world_from_camera"], k, xs + dx, ys + dy) == ids, ids, -1)
    return ids


# ----------------------------------------------------------------------------------------------
# Evaluation
# ----------------------------------------------------------------------------------------------

def _gbuf(clip, level: str) -> dict:
    return {b: clip.read(1, f"{level}/{b}") for b in ("albedo", "normal", "roughness", "metallic", "specular",
                                                    "flags")}


def time_source(source: str, gbuf: dict, camera: dict, repeats: int = 3) -> tuple[np.ndarray, float]:
    """F_beta of a table source and the median wall time of ``repeats`` evaluations (after one warm-up)."""
    from ..brdf import compute_fbeta

    k = tuple(float(v) for v in camera["intrinsics"])
    jit = tuple(float(v) for v in camera["jitter"])
    f = compute_fbeta(source, gbuf, k, jit)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        f = compute_fbeta(source, gbuf, k, jit)
        times.append(time.perf_counter() - t)
    return f, float(np.median(times))


def first_use_seconds(sources) -> dict:
    """Seconds to generate each table source's tables from scratch (empty cache)."""
    from .. import brdf, brdf_model

    out = {}
    with tempfile.TemporaryDirectory() as d:
        old = os.environ.get("BLENDSR_CACHE")
        os.environ["BLENDSR_CACHE"] = d
        try:
            for src in sources:
                if src in ("lut", "lut-paper"):
                    t = time.perf_counter()
                    brdf.generate_lut(brdf.default_spec("ibl" if src == "lut" else "paper"))
                    out[src] = time.perf_counter() - t
                elif src == "model":
                    t = time.perf_counter()
                    brdf_model.generate_model_tables(brdf_model.ModelSpec())
                    out[src] = time.perf_counter() - t
        finally:
            if old is None:
                os.environ.pop("BLENDSR_CACHE", None)
            else:
                os.environ["BLENDSR_CACHE"] = old
    return out


def blackman_harris_variance(filter_width: float = 1.5) -> float:
    """Per-axis variance (px^2) of Cycles' separable Blackman-Harris pixel filter. Cycles doubles the user
    ``filter_width`` before building the filter table, so the support is +-filter_width pixels."""
    full = 2.0 * filter_width
    x = np.linspace(-full / 2, full / 2, 20001)
    a = 2 * np.pi * (x / full + 0.5)
    w = 0.35875 - 0.48829 * np.cos(a) + 0.14128 * np.cos(2 * a) - 0.01168 * np.cos(3 * a)
    return float(np.sum(x * x * w) / np.sum(w))


def filter_matched(f: np.ndarray, variance: float) -> np.ndarray:
    """Second-order model of what a pixel filter of per-axis ``variance`` does to a smooth image f (H x W x C):
    f + variance / 2 * Laplacian(f) (5-point stencil; only meaningful where the +-1 px neighbours are valid)."""
    lap = (np.roll(f, 1, 0) + np.roll(f, -1, 0) + np.roll(f, 1, 1) + np.roll(f, -1, 1) - 4 * f)
    return f + 0.5 * variance * lap


#: Floor of the denominator of relative errors (the default demodulation eps): black materials report absolute
#: errors in units of 0.01 instead of exploding.
REL_FLOOR = 0.01


def _metrics(f: np.ndarray, t: np.ndarray, noise: np.ndarray | None) -> dict:
    mean_t = float(t.mean())
    denom = max(mean_t, REL_FLOOR)
    out = {"truth_mean": mean_t, "mean": float(f.mean()),
           "rel_mae": float(np.abs(f - t).mean() / denom), "bias": float((f.mean() - t.mean()) / denom)}
    if noise is not None:
        out["noise_floor"] = float(noise.mean() / denom)
    return out


def evaluate(layout: dict, clips: list, sources) -> dict:
    """Per level and material: truth, each source's metrics, pixel counts; plus per-source timings."""
    from ..brdf import compute_nov

    res = {"levels": {}, "timing_s": {}}
    for level in ("lr", "hr"):
        clip0 = clips[0]
        w, h = clip0.sizes[level]
        cam = clip0.camera(1, level)
        # LR: Gaussian 0.01 px (support +-0.015 px); HR: Blackman-Harris filter_width 1.5 (support +-1.5 px)
        margin = 0.5 if level == "lr" else 1.6
        ids = material_map(layout, cam, (w, h), margin)
        truths = [c.read(1, f"{level}/radiance") - c.read(1, f"{level}/emission") for c in clips]
        truth = np.mean(truths, axis=0)
        noise = np.abs(truths[0] - truths[1]) / 2 if len(truths) >= 2 else None
        flags = clip0.read(1, f"{level}/flags")[..., 0]
        bg = (flags & 1) != 0
        layout_mismatch = int(np.sum((ids >= 0) & bg))
        gbuf = _gbuf(clip0, level)
        nov = compute_nov(gbuf["normal"], cam["intrinsics"], cam["jitter"])
        fb, times = {}, {}
        for src in sources:
            if src == "cycles":
                fb[src] = clip0.read(1, f"{level}/fbeta")
            else:
                fb[src], times[src] = time_source(src, gbuf, cam)
        res["timing_s"][level] = {"size": [w, h], **times}
        # HR radiance is filtered (Blackman-Harris 1.5 px), the G-buffers are point-sampled: model the filter
        var = blackman_harris_variance(1.5)
        fbf = {src: filter_matched(f.astype(np.float64), var) for src, f in fb.items()} if level == "hr" else {}
        mats = []
        for i, sph in enumerate(layout["spheres"]):
            sel = ids == i
            n = int(sel.sum())
            entry = {"material": sph["material"], "group": sph["group"], "pixels": n,
                     "roughness": float(sph["spec"]["inputs"].get("Roughness", 0.5)), "sources": {}}
            if n == 0:
                mats.append(entry)
                continue
            t = truth[sel]
            nz = noise[sel] if noise is not None else None
            entry["nov_range"] = [float(nov[sel].min()), float(nov[sel].max())]
            for src in sources:
                entry["sources"][src] = _metrics(fb[src][sel], t, nz)
                if level == "hr":
                    entry["sources"][src]["filter_matched"] = _metrics(fbf[src][sel], t, nz)
            entry["noise_floor"] = entry["sources"][sources[0]].get("noise_floor")
            mats.append(entry)
        res["levels"][level] = {"size": [w, h], "materials": mats, "layout_mismatch_pixels": layout_mismatch}
    return res


def summarise(res: dict, sources) -> dict:
    """Median and max rel-MAE per source and level over groups: 'standard' materials with roughness <= 0.8,
    all 'standard', 'layered', 'hard'."""
    out = {}
    for level, lv in res["levels"].items():
        out[level] = {}
        groups = {
            "standard_r<=0.8": [m for m in lv["materials"] if m["group"] == "standard" and m["roughness"] <= 0.8],
            "standard": [m for m in lv["materials"] if m["group"] == "standard"],
            "layered": [m for m in lv["materials"] if m["group"] == "layered"],
            "hard": [m for m in lv["materials"] if m["group"] == "hard"],
        }
        if level == "hr":
            groups["standard_r<=0.8 filter-matched"] = groups["standard_r<=0.8"]
        for g, ms in groups.items():
            ms = [m for m in ms if m["pixels"] > 0]
            out[level][g] = {}
            for src in sources:
                key = (lambda d: d["filter_matched"]) if g.endswith("filter-matched") else (lambda d: d)
                v = np.array([key(m["sources"][src])["rel_mae"] for m in ms])
                b = np.array([key(m["sources"][src])["bias"] for m in ms])
                out[level][g][src] = {"median_rel_mae": float(np.median(v)) if v.size else None,
                                      "max_rel_mae": float(v.max()) if v.size else None,
                                      "max_abs_bias": float(np.abs(b).max()) if b.size else None,
                                      "within_1pct": int(np.sum(v <= 0.01)), "count": int(v.size)}
            nf = np.array([m["noise_floor"] for m in ms if m.get("noise_floor") is not None])
            out[level][g]["noise_floor_max"] = float(nf.max()) if nf.size else None
    return out


# ----------------------------------------------------------------------------------------------
# Reporting
# ----------------------------------------------------------------------------------------------

def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.2f}"


def markdown_tables(res: dict, summary: dict, sources, meta: dict) -> str:
    lines = []
    lines.append(f"Command: `{meta['command']}`  ")
    lines.append(f"Furnace: {meta['hr_size'][0]}x{meta['hr_size'][1]} HR / scale {meta['scale']}, "
                 f"{meta['spp']} spp x {meta['seeds']} seeds = {meta['spp'] * meta['seeds']} spp of truth per "
                 f"pixel at both levels, Blender {meta.get('blender_version')}, {meta['date']}.  ")
    lines.append("rel-MAE = mean |F - T| / max(mean T, 0.01) in %, bias = (mean F - mean T) / max(mean T, 0.01) "
                 "in %, per material over its interior pixels (NoV range in the JSON); noise = the truth's own noise "
                 "floor in % (what noise adds to rel-MAE; the bias is far less affected).")
    lines.append("")
    for level in ("lr", "hr"):
        lv = res["levels"][level]
        lines.append(f"### {level.upper()} ({lv['size'][0]}x{lv['size'][1]})")
        lines.append("")
        lines.append("| group | " + " | ".join(f"{s} median / max rel-MAE, within 1%" for s in sources) + " |")
        lines.append("|---|" + "---|" * len(sources))
        for g, row in summary[level].items():
            cells = [f"{_pct(row[s]['median_rel_mae'])} / {_pct(row[s]['max_rel_mae'])}, "
                     f"{row[s]['within_1pct']}/{row[s]['count']}" for s in sources]
            lines.append(f"| {g} (noise max {_pct(row.get('noise_floor_max'))}) | " + " | ".join(cells) + " |")
        lines.append("")
        pick = (lambda d: d["filter_matched"]) if level == "hr" else (lambda d: d)
        if level == "hr":
            lines.append("Per material at HR: filter-matched (each source's F_beta passed through a second-order model "
                         "of the Blackman-Harris pixel filter of the HR truth, F + var/2 Laplacian(F)).")
            lines.append("")
        lines.append("| material | px | NoV min | T mean | noise | "
                     + " | ".join(f"{s} rel-MAE (bias)" for s in sources) + " |")
        lines.append("|---|---|---|---|---|" + "---|" * len(sources))
        for m in lv["materials"]:
            if not m["pixels"]:
                lines.append(f"| {m['material']} | 0 | - | - | - |" + " - |" * len(sources))
                continue
            s0 = m["sources"][sources[0]]
            cells = [f"{_pct(pick(m['sources'][s])['rel_mae'])} ({'+' if pick(m['sources'][s])['bias'] >= 0 else ''}"
                     f"{_pct(pick(m['sources'][s])['bias'])})" for s in sources]
            lines.append(f"| {m['material']} | {m['pixels']} | {m['nov_range'][0]:.2f} | {s0['truth_mean']:.4f} | "
                         f"{_pct(m.get('noise_floor'))} | "
                         + " | ".join(cells) + " |")
        lines.append("")
    lines.append("### Cost of the table sources (seconds)")
    lines.append("")
    lines.append("| source | first use (table generation) | per frame LR | per frame HR |")
    lines.append("|---|---|---|---|")
    for s in sources:
        if s == "cycles":
            lines.append("| cycles | - (Diffuse/Glossy/Transmission Color passes of the render) | - | - |")
            continue
        lines.append(f"| {s} | {res['first_use_s'].get(s, float('nan')):.2f} | "
                     f"{res['timing_s']['lr'].get(s, float('nan')):.4f} | {res['timing_s']['hr'].get(s, float('nan')):.4f} |")
    lines.append("")
    return "\n".join(lines)


def write_chart(res: dict, sources, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(16, 13))
    for ax, level in zip(axes, ("lr", "hr")):
        mats = [m for m in res["levels"][level]["materials"] if m["pixels"]]
        pick = (lambda d: d["filter_matched"]) if level == "hr" else (lambda d: d)
        y = np.arange(len(mats))
        hgt = 0.8 / len(sources)
        for j, s in enumerate(sources):
            v = [max(100 * pick(m["sources"][s])["rel_mae"], 1e-3) for m in mats]
            ax.barh(y + j * hgt, v, height=hgt, label=s)
        nf = [max(100 * (m.get("noise_floor") or 0), 1e-3) for m in mats]
        ax.scatter(nf, y + 0.4 - hgt / 2, marker="|", color="k", s=60, label="truth noise floor", zorder=3)
        ax.axvline(1.0, color="grey", lw=0.8, ls="--")
        ax.set_xscale("log")
        ax.set_yticks(y + 0.4 - hgt / 2)
        ax.set_yticklabels([m["material"] for m in mats], fontsize=7)
        ax.invert_yaxis()
        ax.set_xlabel("rel-MAE vs white furnace (%)")
        ax.set_title(f"{level.upper()} {res['levels'][level]['size'][0]}x{res['levels'][level]['size'][1]}"
                     + (" (filter-matched)" if level == "hr" else " (point-sampled)"))
        ax.grid(axis="x", which="both", alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def update_docs(path: Path, block: str) -> None:
    """Replace the results block between DOC_BEGIN and DOC_END (appended when absent)."""
    text = path.read_text() if path.is_file() else "# Pre-integrated BRDF (F_beta)\n\n"
    new = f"{DOC_BEGIN}\n{block}\n{DOC_END}"
    if DOC_BEGIN in text and DOC_END in text:
        a = text.index(DOC_BEGIN)
        b = text.index(DOC_END) + len(DOC_END)
        text = text[:a] + new + text[b:]
    else:
        text = text.rstrip("\n") + "\n\n## Measured accuracy\n\n" + new + "\n"
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def run(args) -> int:
    from ..clip import open_clip
    from ..config import parse_size
    from ..extras import require
    require("blendsr bench brdf", "render")  # renders in subprocesses with bpy
    require("blendsr bench brdf (its chart)", "train", modules=("matplotlib",))

    sources = tuple(s.strip() for s in args.sources.split(",") if s.strip())
    bad = [s for s in sources if s not in SOURCES]
    if bad or not sources:
        raise BlendSRError(f"--sources {args.sources!r}: choose from {', '.join(SOURCES)}")
    from . import flags_named
    with flags_named(args):
        size = parse_size(args.hr_size)
    if size[0] % args.scale or size[1] % args.scale:
        raise BlendSRError(f"--hr-size {args.hr_size} is not divisible by --scale {args.scale}")
    if args.seeds < 1 or args.spp < 1:
        raise BlendSRError("--seeds and --spp must be >= 1")
    if args.reuse and args.work is None:
        raise BlendSRError("--reuse needs --work")
    tmp = None
    work = args.work
    if work is None:
        tmp = tempfile.TemporaryDirectory(prefix="blendsr-furnace-")
        work = Path(tmp.name)
    try:
        t0 = time.perf_counter()
        info = render_furnace(work, size, args.scale, args.spp, args.seeds, args.threads, args.reuse)
        print(f"bench brdf: rendered {len(info['clips'])} clip(s) in {time.perf_counter() - t0:.0f} s "
              f"({info['seconds']})", file=sys.stderr)
        layout = json.loads(Path(info["layout"]).read_text())
        clips = [open_clip(c) for c in info["clips"]]
        res = evaluate(layout, clips, sources)
        res["first_use_s"] = first_use_seconds([s for s in sources if s != "cycles"])
        summary = summarise(res, sources)
        meta = {"command": "blendsr bench brdf " + " ".join(shlex.quote(a) for a in sys.argv[3:])
                if sys.argv[1:3] == ["bench", "brdf"] else shlex.join(sys.argv),
                "hr_size": list(size), "scale": args.scale, "spp": args.spp, "seeds": args.seeds,
                "blender_version": clips[0].manifest.get("blender_version"),
                "date": time.strftime("%Y-%m-%d"), "render": info}
        res.update(summary=summary, meta=meta, sources=list(sources))
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "brdf.json").write_text(json.dumps(res, indent=1))
        write_chart(res, sources, args.out / "brdf.png")
        block = markdown_tables(res, summary, sources, meta)
        print(block)
        if args.docs:
            update_docs(Path(args.docs), block + f"\nChart: `{args.out / 'brdf.png'}`, data: `{args.out / 'brdf.json'}`.\n")
        print(f"bench brdf: wrote {args.out / 'brdf.json'}, {args.out / 'brdf.png'}"
              + (f", {args.docs}" if args.docs else ""), file=sys.stderr)
    finally:
        if tmp is not None:
            tmp.cleanup()
    return 0
