"""``blendsr bench models``: error against time for several models on the same clips.

For every model (a non-learned name, or NAME:CHECKPOINT) it runs the evaluation of ``training.evaluate`` and
reports PSNR/SSIM (declared tonemap), PSNR-HDR, tPSNR, warping error, optionally HDR-FLIP, the median ms per frame,
the parameter count and the multiply-accumulates per output pixel (convolutions and matrix products counted by
``torch.utils.flop_counter``; interpolation and element-wise operations are not counted). Writes
OUT/bench_models.json, OUT/bench_models.csv, OUT/bench_models.md and the Pareto plot OUT/pareto.png (PSNR against
ms per frame, the non-dominated models joined). torch and matplotlib are imported inside ``run``.
"""
from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

COLUMNS = ("model", "params", "macs_per_px", "ms_per_frame", "psnr", "ssim", "psnr_hdr", "flip", "tpsnr",
           "warp_error")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", nargs="+", required=True, metavar="CLIP",
                        help="clip directories, or dataset folders (their --split)")
    parser.add_argument("--split", default="test", choices=("train", "val", "test"),
                        help="split of dataset folders given to --data")
    parser.add_argument("--models", default="bilinear,bicubic,demod-bilinear,demod-jbu",
                        help="comma-separated: model names, or NAME:CHECKPOINT for learned models")
    parser.add_argument("--frames", metavar="A:B", help="inclusive frame range (default: all)")
    parser.add_argument("-o", "--output", default="bench-models", metavar="DIR", help="output directory")
    parser.add_argument("--flip", action="store_true", help="also compute HDR-FLIP (slow on CPU)")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"), help="where models run")
    parser.add_argument("--amp", default="none", choices=("none", "bf16", "fp16", "auto"), help="autocast")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed runs before timing")


def parse_models(text: str) -> list[tuple[str, str]]:
    """'bicubic,fusesr:runs/a/checkpoints/last.pt,pretrained:fusesr' -> [('bicubic', 'bicubic'),
    ('fusesr (a)', 'runs/a/...'), ('pretrained:fusesr', 'pretrained:fusesr')]."""
    from training.models import MODELS
    out = []
    for item in (t.strip() for t in text.split(",")):
        if not item:
            continue
        if item.startswith("pretrained:"):  # a shipped model (training/pretrained.py)
            out.append((item, item))
            continue
        name, sep, path = item.partition(":")
        if name not in MODELS:
            raise ValueError(f"--models: unknown model {name!r}; choose among {', '.join(MODELS)}")
        if MODELS[name].learned and not sep:
            raise ValueError(f"--models: {name!r} is learned; write {name}:CHECKPOINT")
        out.append((checkpoint_label(name, path) if sep else name, path if sep else name))
    if not out:
        raise ValueError("--models: no model given")
    return out


def checkpoint_label(name: str, path: str) -> str:
    """'fusesr' + 'runs/a/checkpoints/last.pt' -> 'fusesr (a)'; other files -> 'fusesr (file stem)'."""
    p = Path(path)
    tag = p.parent.parent.name if p.parent.name == "checkpoints" and p.parent.parent.name else p.stem
    return f"{name} ({tag})"


def macs_per_pixel(model, inputs: dict, device) -> float:
    """Multiply-accumulates per HR output pixel of one forward pass (flop counter / 2)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode
    needs = set(model.needs())
    batch = {k: torch.from_numpy(v).to(device) for k, v in inputs.items() if k in needs}
    counter = FlopCounterMode(display=False)
    with torch.inference_mode(), counter:
        sr = model(batch)
    return counter.get_total_flops() / 2.0 / (sr.shape[-1] * sr.shape[-2])


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of points not dominated (lower time and higher quality), sorted by time."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], float("-inf")
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def plot(rows: list[dict], path: Path, device: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    pts = [(max(r["ms_per_frame"], 1e-3), r["psnr"]) for r in rows]
    front = pareto_front(pts)
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=120)
    ax.scatter([p[0] for p in pts], [p[1] for p in pts], c="tab:blue", zorder=3)
    placed: list[tuple[float, float]] = []
    for r, p in zip(rows, pts):  # labels of near-coincident points are stacked downwards instead of overprinted
        k = sum(1 for q in placed if abs(q[1] - p[1]) < 0.25 and abs(np.log10(q[0] / p[0])) < 0.3)
        placed.append(p)
        ax.annotate(r["model"], p, textcoords="offset points", xytext=(5, 4 - 10 * k), fontsize=8)
    ax.plot([pts[i][0] for i in front], [pts[i][1] for i in front], "--", c="tab:orange", label="Pareto front")
    ax.set_xscale("log")
    ax.set_xlabel("ms per frame (median, log scale)")
    ax.set_ylabel("PSNR (dB, reinhard-srgb tonemap)")
    ax.set_title(f"Error against time ({device})", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def benchmark(models: list[tuple[str, str]], clips, out, *, frames: dict | None = None, device=None, amp=None,
              flip: bool = False, warmup: int = 2, log=print) -> dict:
    """Evaluate ``models`` ((label, spec) pairs, spec a name or a checkpoint) on ``clips``; write the table files
    and ``pareto.png`` under ``out``; return {device, scale, rows, results}."""
    from training.commands import _scale_of
    from training.evaluate import evaluate_model
    from training.inference import ClipFrames, load_model, model_inputs
    from training.checkpoint import load_checkpoint
    from training.train import resolve_device

    scale = _scale_of(clips)
    device = device or resolve_device("auto")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows, results = [], []
    for label, spec in models:
        name = label.split(" ")[0]
        if spec != name:
            ck_name = load_checkpoint(spec)["model_name"]
            if ck_name != name:
                raise ValueError(f"{spec}: checkpoint holds model {ck_name!r}, not {name!r}")
        model = load_model(spec, scale).to(device)
        res = evaluate_model(model, clips, frames=frames, device=device, amp=amp, flip=flip, warmup=warmup,
                             label=label)
        src = ClipFrames(clips[0], eps=model.demod_eps)
        first = (frames or {}).get(str(clips[0])) or src.frames
        m = res["mean"]
        row = {"model": label, "params": sum(p.numel() for p in model.parameters()),
               "macs_per_px": macs_per_pixel(model, model_inputs(model, src, first[0]), device),
               **{k: m[k] for k in COLUMNS if k in m}}
        rows.append(row)
        results.append(res)
        log(f"{label:24s} {row['ms_per_frame']:9.2f} ms  PSNR {row['psnr']:6.2f} dB  SSIM {row['ssim']:.4f}")
    device_name = results[0]["device"]
    (out / "bench_models.json").write_text(json.dumps({"device": device_name, "scale": scale,
                                                       "clips": [str(c) for c in clips], "rows": rows,
                                                       "transform": results[0]["transform"]}, indent=1) + "\n")
    with open(out / "bench_models.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k) for k in COLUMNS})
    md = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        md.append("| " + " | ".join(_fmt(r.get(k)) for k in COLUMNS) + " |")
    table = "\n".join(md)
    (out / "bench_models.md").write_text(f"Device: {device_name}; scale {scale}\n\n{table}\n")
    plot(rows, out / "pareto.png", device_name)
    log(table)
    return {"device": device_name, "scale": scale, "rows": rows, "results": results, "table": table}


def run(args) -> int:
    import torch

    from gbuffer_export.config import parse_frames
    from training.train import amp_dtype, resolve_device

    if args.threads:
        torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    from training.commands import _dataset_clips
    args.data = [str(c) for c in _dataset_clips(args.data, args.split)]
    rng = parse_frames(args.frames)
    frames = {str(c): list(range(rng[0], rng[1] + 1)) for c in args.data} if rng else None
    benchmark(parse_models(args.models), list(args.data), args.output, frames=frames, device=device,
              amp=amp_dtype(args.amp, device), flip=args.flip, warmup=args.warmup)
    print(f"wrote {Path(args.output) / 'bench_models.json'}, {Path(args.output) / 'pareto.png'}")
    return 0


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)
