"""Does demodulation work on sheen pixels? Measurements of docs/results-history.md, "Sheen: why FuseSR lost on velvet".

    .venv/bin/python benchmarks/sheen_diagnosis.py DATASET [--images EVAL_DIR] [--frames N]

For every clip of DATASET (a dataset folder) and level (hr, lr), over the interior (5x5 erosion) of the sheen
pixels (``Flag.SHEEN``) and of the other trusted surface pixels: mean F_beta and radiance - emission (I), mean
L_D = I / max(F_beta, 0.01), the RMS of a 5x5 high-pass of log I, log F_beta and log L_D (texture left in L_D),
the regression slope of I's high-pass on F_beta's (1: every texture of the radiance is in F_beta) and the
correlation of L_D's high-pass with F_beta's (0: demodulation left no F_beta texture). With ``--images EVAL_DIR``
(holding ``img-MODEL/CLIP/FRAME.exr`` from ``blendsr evaluate --save-images EVAL_DIR/img-MODEL``) also the PSNR of
each model on the evaluation tonemap over all, sheen and other surface pixels (mean over frames). Markdown on stdout.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.ndimage import uniform_filter

from gbuffer_export.clip import ClipError, open_clip
from gbuffer_export.conventions import UNTRUSTED, Flag
from gbuffer_export.exr import read_exr

STATS = ("F", "I", "LD", "hf_I", "hf_F", "hf_LD", "slope", "corr_LD_F")


def masks(flags: np.ndarray) -> dict[str, np.ndarray]:
    """{'sheen', 'other'}: (H, W) bool surface masks from an (H, W) uint32 flags buffer."""
    surf = (flags & np.uint32(Flag.BACKGROUND)) == 0
    sheen = surf & ((flags & np.uint32(Flag.SHEEN)) != 0)
    return {"sheen": sheen, "other": surf & ~sheen & ((flags & np.uint32(UNTRUSTED)) == 0)}


def frame_stats(clip, frame: int, level: str) -> dict[str, dict[str, float]]:
    """STATS per pixel class of one frame and level (classes with under 20 interior pixels are left out)."""
    rd = {b: clip.read(frame, f"{level}/{b}")[..., :3].astype(np.float64) for b in ("radiance", "emission", "fbeta")}
    i_, f_ = (rd["radiance"] - rd["emission"]).mean(-1), rd["fbeta"].mean(-1)
    ld = i_ / np.clip(f_, 0.01, None)
    hp = {k: (lambda x: x - uniform_filter(x, 5, mode="nearest"))(np.log(np.clip(v, 1e-4, None)))
          for k, v in (("I", i_), ("F", f_), ("LD", ld))}
    out = {}
    for name, m in masks(clip.read(frame, f"{level}/flags")[..., 0].astype(np.uint32)).items():
        mi = uniform_filter(m.astype(np.float64), 5) > 0.999
        if mi.sum() < 20:
            continue
        hi, hf, hl = hp["I"][mi], hp["F"][mi], hp["LD"][mi]
        out[name] = {"F": f_[m].mean(), "I": i_[m].mean(), "LD": ld[m].mean(),
                     "hf_I": np.sqrt((hi ** 2).mean()), "hf_F": np.sqrt((hf ** 2).mean()),
                     "hf_LD": np.sqrt((hl ** 2).mean()), "slope": (hi * hf).sum() / max((hf ** 2).sum(), 1e-12),
                     "corr_LD_F": float(np.corrcoef(hl, hf)[0, 1])}
    return out


def clip_psnr(clip, frames, images: Path, model: str) -> dict[str, float] | None:
    """Mean PSNR (evaluation tonemap) of a model's saved SR frames over all / sheen / other pixels; None if absent."""
    from training import metrics
    rows: dict[str, list] = {"all": [], "sheen": [], "other": []}
    for f in frames:
        p = images / f"img-{model}" / clip.path.name / f"{f:06d}.exr"
        if not p.is_file():
            return None
        sr, gt = read_exr(p, ("R", "G", "B")), clip.read(f, "hr/radiance")[..., :3]
        rows["all"].append(metrics.psnr_tm(sr, gt))
        for name, m in masks(clip.read(f, "hr/flags")[..., 0].astype(np.uint32)).items():
            rows[name].append(metrics.psnr_tm(sr, gt, m))
    return {k: float(np.mean([v for v in r if v is not None])) if any(v is not None for v in r) else float("nan")
            for k, r in rows.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--images", type=Path, help="folder of img-MODEL/ folders from blendsr evaluate --save-images")
    ap.add_argument("--frames", type=int, default=0, help="first N frames of each clip (0: all)")
    a = ap.parse_args(argv)
    clips_dir = a.dataset / "clips"
    try:
        if not clips_dir.is_dir():
            raise ClipError(f"{a.dataset}: not a dataset folder (no clips/)")
        clips = [open_clip(p) for p in sorted(clips_dir.iterdir()) if p.is_dir()]
    except ClipError as e:
        print(f"sheen_diagnosis: {e}", file=sys.stderr)
        return 2
    print("| clip | level | pixels | " + " | ".join(STATS) + " |\n|" + "---|" * (len(STATS) + 3))
    for c in clips:
        frames = sorted(c.manifest["frames"])[: a.frames or None]
        for level in ("hr", "lr"):
            per = [frame_stats(c, f, level) for f in frames]
            for name in ("sheen", "other"):
                vals = [p[name] for p in per if name in p]
                if vals:
                    cells = " | ".join(f"{np.mean([v[k] for v in vals]):.3f}" for k in STATS)
                    print(f"| {c.path.name} | {level} | {name} | {cells} |")
    if a.images is not None:
        models = sorted(p.name[4:] for p in a.images.glob("img-*") if p.is_dir())
        print("\n| clip | model | PSNR all | sheen | other surface |\n|---|---|---|---|---|")
        for c in clips:
            frames = sorted(c.manifest["frames"])[: a.frames or None]
            for m in models:
                r = clip_psnr(c, frames, a.images, m)
                if r is not None:
                    print(f"| {c.path.name} | {m} | {r['all']:.2f} | {r['sheen']:.2f} | {r['other']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
