"""PSNR against scale: score models on clips with several LR levels, each at every level it can take.

    python benchmarks/scale_curve.py CLIP [CLIP ...] -o OUT --models bicubic,demod-jbu,fourier-sr:RUN/last.pt

A model named NAME or NAME:CHECKPOINT; an arbitrary-scale model (``SCALES is None``: bicubic, fourier-sr) is scored
at every level of the clips, a fixed-scale one (demod-jbu at 2 and 4, a checkpoint at its trained scale) at the
levels it takes. Writes OUT/scale_curve.json (per model and scale: PSNR, SSIM, FLIP, ms per frame, frames),
OUT/scale_curve.md (the table) and OUT/scale_curve.png (PSNR against scale). Used by benchmarks/scales.sh.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def score(spec: str, clips: list[str], clip_scales: list[float], flip: bool) -> tuple[str, dict]:
    """(label, {scale: means}) of one model over the clips, at every level it takes: a checkpoint of a fixed-scale
    model at its trained scale, an arbitrary-scale one at every level, a non-learned model at every level it
    supports (one instance per scale)."""
    from training.checkpoint import load_checkpoint
    from training.evaluate import EvalOptions, evaluate_model
    from training.inference.loading import load_model
    from training.models import model_class
    if spec.startswith("pretrained:"):  # shipped weights (pretrained:NAME, NAME the model): every level it takes
        name, label = spec.split(":", 1)[1], spec
        fixed = model_class(name).SCALES is not None  # the fixed-scale weights are 4x
        models = {s: load_model(spec, s) for s in clip_scales if not fixed or s == 4}
    elif ":" in spec:  # NAME:CHECKPOINT
        name, ck = spec.split(":", 1)
        trained = load_checkpoint(ck)
        label = f"{name} (trained at {', '.join(f'{s:g}' for s in trained.get('scales') or [trained['scale']])})"
        model = load_model(ck, trained["scale"])
        scales = clip_scales if model_class(name).SCALES is None else [float(trained["scale"])]
        models = {s: model for s in scales}
    else:  # a non-learned model
        cls, label = model_class(spec), spec
        models = {s: load_model(spec, s) for s in clip_scales if cls.supports_scale(s)}
    per = {}
    for s, model in models.items():
        res = evaluate_model(model, clips, EvalOptions(flip=flip, warmup=1, scale=s))
        per[f"{s:g}"] = {k: res["mean"].get(k) for k in ("psnr", "ssim", "flip", "ms_per_frame", "frames")}
    return label, per


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("clips", nargs="+")
    p.add_argument("-o", "--out", required=True, type=Path)
    p.add_argument("--models", required=True, help="comma-separated NAME or NAME:CHECKPOINT")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--no-flip", action="store_true")
    a = p.parse_args(argv)
    import torch
    torch.set_num_threads(a.threads)
    from gbuffer_export import open_clip
    clip_scales = sorted(set.intersection(*(set(open_clip(c).scales) for c in a.clips)))
    rows = {}
    for spec in a.models.split(","):
        label, per = score(spec, a.clips, clip_scales, not a.no_flip)
        rows[label] = per
        print(label, {s: round(v["psnr"], 2) for s, v in per.items()}, flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "scale_curve.json").write_text(json.dumps({"clips": a.clips, "scales": clip_scales, "models": rows},
                                                       indent=1))
    cols = [f"{s:g}" for s in clip_scales]
    lines = ["| model | " + " | ".join(f"x{c} PSNR / SSIM / FLIP" for c in cols) + " |",
             "|---|" + "---|" * len(cols)]
    for label, per in rows.items():
        cells = []
        for c in cols:
            v = per.get(c)
            cells.append("-" if v is None else f"{v['psnr']:.2f} / {v['ssim']:.4f} / "
                         + ("-" if v["flip"] is None else f"{v['flip']:.4f}"))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    ms = ["", "| model | " + " | ".join(f"x{c} ms/frame" for c in cols) + " |", "|---|" + "---|" * len(cols)]
    for label, per in rows.items():
        ms.append(f"| {label} | " + " | ".join("-" if c not in per else f"{per[c]['ms_per_frame']:.1f}"
                                               for c in cols) + " |")
    (a.out / "scale_curve.md").write_text("\n".join(lines + ms) + "\n")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, per in rows.items():
        xs = sorted(float(s) for s in per)
        ax.plot(xs, [per[f"{x:g}"]["psnr"] for x in xs], marker="o", label=label)
    ax.set_xlabel("scale factor")
    ax.set_ylabel("PSNR (dB, evaluation tonemap)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(a.out / "scale_curve.png", dpi=120)
    print((a.out / "scale_curve.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
