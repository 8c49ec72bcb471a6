"""``blendsr bench models``: speed against error, or speed alone against the hardware's limit.

With ``--data`` (clips), for every model (a non-learned name, or NAME:CHECKPOINT) it runs the evaluation of
``training.evaluate`` and reports PSNR/SSIM (declared tonemap), PSNR-HDR, tPSNR, warping error, optionally HDR-FLIP,
the median ms per frame, the parameter count and the multiply-accumulates per output pixel (convolutions and matrix
products counted by ``torch.utils.flop_counter``; interpolation and element-wise operations are not counted). With
``-o OUT`` it writes OUT/bench_models.json, OUT/bench_models.csv, OUT/bench_models.md and the Pareto plot
OUT/pareto.png (PSNR against ms per frame, the non-dominated models joined), with the roofline columns of the speed
mode (below) for one frame of the clips.

Without ``--data`` it times every model on random inputs of the right shapes (``export.example_inputs``) at
``--size`` (HR, default 1920x1080) and ``--scale``, batch 1, for each precision of ``--precision`` and each
``--compile`` setting (the inference fast path, ``training.fastpath``); learned models named without a checkpoint
run with their initial weights (speed does not depend on the weights). Times are medians of ``--repeats`` runs after
``--warmup`` (CUDA events on a GPU; all models and variants are prepared first and then timed round-robin, so
their ratios are measured side by side). The table gives MACs, the bytes a frame must move (inputs read once,
output written once) and the roofline estimate max(2 MACs / peak, bytes / bandwidth) with the measured/roofline
ratio; peak and bandwidth come from ``--peak-tflops``/``--bandwidth-gbs``, by default from ``DEVICE_PEAKS`` for
known GPUs and measured (a large matmul and a large copy) elsewhere. With ``-o OUT`` it writes
OUT/bench_speed.json, .csv and .md; without ``-o`` nothing is written. torch and matplotlib are imported inside
``run``.
"""
from __future__ import annotations

import argparse
import csv
import json
import statistics
from pathlib import Path

import numpy as np
from gbuffer_export.errors import BlendSRError

COLUMNS = ("model", "params", "macs_per_px", "ms_per_frame", "psnr", "ssim", "psnr_hdr", "flip", "tpsnr",
           "warp_error", "roofline_ms", "ratio")


#: Dense datasheet peaks per device kind: name substring -> (TFLOPS fp32 convolutions (TF32 tensor cores, torch's
#: cuDNN default), TFLOPS bf16/fp16 tensor cores, GB/s memory bandwidth). The first match wins; others: measured.
DEVICE_PEAKS = {
    "H100 PCIe": (378.0, 756.0, 2000.0),
    "H100 NVL": (417.0, 835.0, 3900.0),
    "H100": (494.0, 989.0, 3350.0),        # SXM5 (e.g. "NVIDIA H100 80GB HBM3")
    "H200": (494.0, 989.0, 4800.0),
    "A100": (156.0, 312.0, 2039.0),
    "RTX 4090": (82.6, 165.2, 1008.0),
    "RTX 3090": (35.6, 71.0, 936.0),
}
SPEED_COLUMNS = ("model", "variant", "params", "macs_per_px", "gmacs", "mbytes", "ms", "ms_min", "roofline_ms",
                 "ratio", "kernels", "max_rel_err", "tolerance")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", nargs="*", default=[], metavar="CLIP",
                        help="clip directories or dataset folders (their --split); none: speed only, on random "
                             "inputs of --size")
    parser.add_argument("--split", default="test", choices=("train", "val", "test"),
                        help="split of dataset folders given to --data")
    parser.add_argument("--models", default=None,
                        help="comma-separated: model names, or NAME:CHECKPOINT for learned models (default: the "
                             "non-learned models with --data, every model without)")
    parser.add_argument("--size", default="1920x1080", metavar="WxH", help="HR size of the random inputs")
    parser.add_argument("--scale", type=int, default=4, help="scale of the random inputs")
    parser.add_argument("--precision", default=None,
                        help="comma-separated precisions to time: none (float32), bf16, fp16, auto (default none; "
                             "with --data one precision, default from --amp); tables name the dtype that ran")
    parser.add_argument("--compile", nargs="?", const="on", default="off", choices=("off", "on", "both", "off,on"),
                        metavar="{off,on,both}",
                        help="torch.compile the fast path (on CUDA: reduce-overhead, CUDA graphs); both (or off,on): "
                             "measure without and with")
    parser.add_argument("--eager-reference", action="store_true",
                        help="speed mode: also time the reference path (fp32 eager, no fast ops, NCHW)")
    parser.add_argument("--repeats", type=int, default=30, help="timed runs per variant (speed mode)")
    parser.add_argument("--peak-tflops", type=float, default=0.0,
                        help="device peak for the roofline, TFLOPS in the timed precision (0: DEVICE_PEAKS, else "
                             "measured)")
    parser.add_argument("--bandwidth-gbs", type=float, default=0.0,
                        help="device memory bandwidth for the roofline, GB/s (0: DEVICE_PEAKS, else measured)")
    parser.add_argument("--frames", metavar="A:B", help="inclusive frame range (default: all)")
    parser.add_argument("-o", "--output", default=None, metavar="DIR",
                        help="write the JSON, CSV and markdown tables (and pareto.png with --data) here; default: "
                             "print the table only, write nothing")
    parser.add_argument("--flip", action="store_true", help="also compute HDR-FLIP (slow on CPU)")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"), help="where models run")
    parser.add_argument("--amp", default="none", choices=("none", "bf16", "fp16", "auto"),
                        help="autocast (with --data; --precision takes precedence)")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed runs before timing")
    parser.add_argument("--no-progress", action="store_true",
                        help="no progress bars on stderr (per model and clip with --data; preparing and timing "
                             "without)")
    parser.add_argument("--path", default=None, metavar="PATHS",
                        help="speed mode: comma-separated inference paths timed side by side: reference (fp32 eager, "
                             "= --eager-reference), fast (fast ops, autocast; the default), fused (fused HR stage, "
                             "weights held in the precision's dtype); adds kernels per frame and each output's "
                             "error to the fp32 reference, checked against the precision's tolerance")


def parse_models(text: str, need_checkpoints: bool = True) -> list[tuple[str, str]]:
    """'bicubic,fusesr:runs/a/checkpoints/last.pt,pretrained:fusesr' -> [('bicubic', 'bicubic'),
    ('fusesr (a)', 'runs/a/...'), ('pretrained:fusesr', 'pretrained:fusesr')]. Without ``need_checkpoints`` a
    learned model may be named alone (initial weights: speed only)."""
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
            raise BlendSRError(f"--models: unknown model {name!r}; choose among {', '.join(MODELS)}")
        if MODELS[name].learned and not sep and need_checkpoints:
            raise BlendSRError(f"--models: {name!r} is learned; write {name}:CHECKPOINT")
        out.append((checkpoint_label(name, path) if sep else name, path if sep else name))
    if not out:
        raise BlendSRError("--models: no model given")
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
              flip: bool = False, warmup: int = 2, log=print, precision: str | None = None,
              compile: bool = False, peak_tflops: float = 0.0, bandwidth_gbs: float = 0.0,
              progress: bool = False) -> dict:
    """Evaluate ``models`` ((label, spec) pairs, spec a name or a checkpoint) on ``clips`` at the clips' 'lr' level
    (every model at the same scale); write the table files and ``pareto.png`` under ``out``; return {device,
    scale, rows, results}."""
    from training.commands import _scale_of
    from training.evaluate import evaluate_model
    from training.inference import ClipFrames, load_model, model_inputs
    from training.checkpoint import load_checkpoint
    from training.device import dtype_label, resolve_device

    scale = _scale_of(clips)
    device = device or resolve_device("auto")
    rows, results = [], []
    peaks: dict = {}
    for label, spec in models:
        name = label.split(" ")[0]
        if spec != name:
            ck_name = load_checkpoint(spec)["model_name"]
            if ck_name != name:
                raise BlendSRError(f"{spec}: checkpoint holds model {ck_name!r}, not {name!r}")
        model = load_model(spec, scale).to(device)
        if precision is not None or compile:
            from training.fastpath import prepare_inference
            prepare_inference(model, device, precision or "none", compile=compile)
            amp = None
        res = evaluate_model(model, clips, frames=frames, device=device, amp=amp, flip=flip, warmup=warmup,
                             label=label, progress=progress, scale=scale)
        src = ClipFrames(clips[0], eps=model.demod_eps)
        first = (frames or {}).get(str(clips[0])) or src.frames
        m = res["mean"]
        inputs = model_inputs(model, src, first[0])
        row = {"model": label, "params": model.n_params,
               "macs_per_px": macs_per_pixel(model, inputs, device),
               **{k: m[k] for k in COLUMNS if k in m}}
        # roofline of one frame of these clips (bytes: the model's inputs read once, the output written once)
        hw = inputs["lr/radiance"].shape[-2] * inputs["lr/radiance"].shape[-1] * scale * scale
        nbytes = sum(v.nbytes for k, v in inputs.items() if k in set(model.needs())) + 3 * hw * 4
        dt = model.inference.get("dtype") or amp
        key = dtype_label(dt)
        if key not in peaks:
            peaks[key] = device_peaks(device, dt, peak_tflops, bandwidth_gbs)
        row["roofline_ms"] = 1000 * max(2 * row["macs_per_px"] * hw / (peaks[key]["tflops"] * 1e12),
                                        nbytes / (peaks[key]["gbs"] * 1e9))
        row["ratio"] = row["ms_per_frame"] / row["roofline_ms"]
        rows.append(row)
        results.append(res)
        log(f"{label:24s} {row['ms_per_frame']:9.2f} ms  PSNR {row['psnr']:6.2f} dB  SSIM {row['ssim']:.4f}")
    device_name = results[0]["device"]
    md = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        md.append("| " + " | ".join(_fmt(r.get(k)) for k in COLUMNS) + " |")
    table = "\n".join(md)
    log(table)
    result = {"device": device_name, "scale": scale, "rows": rows, "results": results, "table": table}
    if out is None:  # nothing written where nobody asked (blendsr bench models without -o)
        return result
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_models.json").write_text(json.dumps({"device": device_name, "scale": scale, "peaks": peaks,
                                                       "clips": [str(c) for c in clips], "rows": rows,
                                                       "transform": results[0]["transform"]}, indent=1) + "\n")
    with open(out / "bench_models.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k) for k in COLUMNS})
    (out / "bench_models.md").write_text(f"Device: {device_name}; scale {scale}\n\n{table}\n")
    plot(rows, out / "pareto.png", device_name)
    return result


def run(args) -> int:
    from gbuffer_export.extras import require
    require("blendsr bench models", "train")
    import torch

    from gbuffer_export.config import parse_frames
    from training.device import amp_dtype, resolve_device

    if args.threads:
        torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    from training.commands import _dataset_clips
    args.data = [str(c) for c in _dataset_clips(args.data, args.split)]
    precisions = _precisions(args.precision)
    compiles = {"off": [False], "on": [True], "both": [False, True], "off,on": [False, True]}[args.compile]
    if not args.data:
        from training.models import MODELS
        models = parse_models(args.models or ",".join(MODELS), need_checkpoints=False)
        speed_benchmark(models, args.output, size=_size(args.size), scale=args.scale, device=device,
                        precisions=precisions or ["none"], compiles=compiles, warmup=args.warmup,
                        repeats=args.repeats, peak_tflops=args.peak_tflops, bandwidth_gbs=args.bandwidth_gbs,
                        reference=args.eager_reference, progress=not args.no_progress, paths=_paths(args.path))
        if args.output:
            print(f"wrote {Path(args.output) / 'bench_speed.json'}, {Path(args.output) / 'bench_speed.md'}")
        return 0
    if len(precisions or []) > 1 or len(compiles) > 1:
        raise BlendSRError("--data: one --precision and one --compile setting at a time")
    rng = parse_frames(args.frames)
    frames = {str(c): list(range(rng[0], rng[1] + 1)) for c in args.data} if rng else None
    benchmark(parse_models(args.models or "bilinear,bicubic,demod-bilinear,demod-jbu"), list(args.data),
              args.output, frames=frames, device=device, amp=amp_dtype(args.amp, device), flip=args.flip,
              warmup=args.warmup, precision=precisions[0] if precisions else None, compile=compiles[0],
              peak_tflops=args.peak_tflops, bandwidth_gbs=args.bandwidth_gbs, progress=not args.no_progress)
    if args.output:
        print(f"wrote {Path(args.output) / 'bench_models.json'}, {Path(args.output) / 'pareto.png'}")
    return 0


def _bar(items, desc: str, unit: str, on: bool):
    """``items``, under a tqdm bar on stderr when ``on``."""
    if not on:
        return items
    import sys

    from tqdm import tqdm
    return tqdm(items, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True, leave=False)


def _paths(text: str | None) -> list[str] | None:
    """--path: None (the fast path alone) or the paths among reference, fast, fused."""
    if not text:
        return None
    from training.fastpath import PATHS
    out = [p.strip() for p in text.split(",") if p.strip()]
    bad = [p for p in out if p not in ("reference",) + PATHS]
    if bad or not out:
        raise BlendSRError(f"--path {text!r}: comma-separated reference, {', '.join(PATHS)}")
    return out


def _precisions(text: str | None) -> list[str] | None:
    if not text:
        return None
    from training.device import PRECISIONS
    out = [p.strip() for p in text.split(",") if p.strip()]
    bad = [p for p in out if p not in PRECISIONS]
    if bad or not out:
        raise BlendSRError(f"--precision {text!r}: comma-separated {', '.join(PRECISIONS)}")
    return out


def _size(text: str) -> tuple[int, int]:
    from gbuffer_export.config import parse_size
    try:
        return parse_size(text)
    except ValueError as exc:
        raise BlendSRError(str(exc).replace("--hr-size", "--size")) from None


# ------------------------------------------------------------------------------------------------ speed mode
def device_peaks(device, dtype, peak_tflops: float = 0.0, bandwidth_gbs: float = 0.0) -> dict:
    """{'tflops', 'gbs', 'source'} for the roofline: the options when given, else ``DEVICE_PEAKS`` for a known GPU
    (bf16/fp16 tensor-core peak under autocast, TF32 otherwise), else measured here."""
    import torch
    src = []
    tf, gb = peak_tflops, bandwidth_gbs
    if device.type == "cuda" and (not tf or not gb):
        name = torch.cuda.get_device_name(device)
        for key, (f32, f16, bw) in DEVICE_PEAKS.items():
            if key in name:
                tf = tf or (f32 if dtype is None else f16)
                gb = gb or bw
                src.append(f"datasheet {key}")
                break
    if not tf:
        tf = measure_tflops(device, dtype)
        src.append("measured matmul")
    if not gb:
        gb = measure_bandwidth(device)
        src.append("measured copy")
    if peak_tflops or bandwidth_gbs:
        src.append("options")
    return {"tflops": float(tf), "gbs": float(gb), "source": ", ".join(src)}


def _sync(device) -> None:
    import torch
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measure_tflops(device, dtype, n: int = 0) -> float:
    """Best of 5 square matmuls in ``dtype`` (None: float32), TFLOPS."""
    import time

    import torch
    n = n or (8192 if device.type == "cuda" else 1024)
    a = torch.randn(n, n, device=device, dtype=dtype or torch.float32)
    b = torch.randn(n, n, device=device, dtype=dtype or torch.float32)
    best = float("inf")
    for _ in range(6):
        _sync(device)
        t = time.perf_counter()
        a @ b
        _sync(device)
        best = min(best, time.perf_counter() - t)
    return 2 * n ** 3 / best / 1e12


def measure_bandwidth(device, mbytes: int = 0) -> float:
    """Best of 5 copies of a large float32 tensor (read + write counted), GB/s."""
    import time

    import torch
    mbytes = mbytes or (2048 if device.type == "cuda" else 256)
    a = torch.empty(mbytes * 2 ** 18, device=device)
    b = torch.empty_like(a)
    best = float("inf")
    for _ in range(6):
        _sync(device)
        t = time.perf_counter()
        b.copy_(a)
        _sync(device)
        best = min(best, time.perf_counter() - t)
    return 2 * a.numel() * 4 / best / 1e9


def _timer(device):
    """start() / stop() -> ms: CUDA events on a GPU, perf_counter elsewhere."""
    import time

    import torch
    if device.type == "cuda":
        def run(fn):
            s, e = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            s.record()
            fn()
            e.record()
            e.synchronize()
            return s.elapsed_time(e)
        return run

    def run(fn):
        t = time.perf_counter()
        fn()
        return 1000 * (time.perf_counter() - t)
    return run


def _speed_record(r: dict, pk: dict, pixels: int, log) -> dict:
    """One timed (model, variant) as a row of bench_speed: median and minimum ms, MACs, bytes and its roofline
    time on the device's peaks ``pk`` ({tflops, gbs}); logs one line."""
    macs = r["macs"]
    roof = 1000 * max(2 * macs / (pk["tflops"] * 1e12), r["bytes"] / (pk["gbs"] * 1e9))
    ms = statistics.median(r["times"])
    rec = {"model": r["model"], "variant": r["variant"], "params": r["params"], "macs_per_px": macs / pixels,
           "gmacs": macs / 1e9, "mbytes": r["bytes"] / 1e6, "ms": ms, "ms_min": min(r["times"]),
           "roofline_ms": roof, "ratio": ms / roof,
           **{k: r[k] for k in ("kernels", "max_rel_err", "tolerance") if k in r}}
    log(f"{r['model']:24s} {r['variant']:22s} {ms:10.3f} ms (min {rec['ms_min']:.3f}; roofline {roof:.4f} ms, "
        f"x{rec['ratio']:.0f})")
    return rec


def _write_speed(out: Path, meta: dict, records: list[dict], table: str) -> None:
    """OUT/bench_speed.json, .csv and .md."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_speed.json").write_text(json.dumps({**meta, "rows": records}, indent=1) + "\n")
    with open(out / "bench_speed.csv", "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=SPEED_COLUMNS)
        wr.writeheader()
        for r in records:
            wr.writerow(r)
    peak_txt = "; ".join(f"{k}: {v['tflops']:.4g} TFLOPS, {v['gbs']:.4g} GB/s ({v['source']})"
                         for k, v in meta["peaks"].items())
    w, h = meta["size"]
    (out / "bench_speed.md").write_text(f"Device: {meta['device']}; HR {w}x{h}, scale {meta['scale']}, batch 1; "
                                        f"{meta['timing']} of {meta['repeats']} after {meta['warmup']} warm-up; "
                                        f"roofline peaks: {peak_txt}\n\n{table}\n")


def speed_benchmark(models: list[tuple[str, str]], out, *, size=(1920, 1080), scale: int = 4, device=None,
                    precisions=("none",), compiles=(False,), warmup: int = 2, repeats: int = 30,
                    peak_tflops: float = 0.0, bandwidth_gbs: float = 0.0, reference: bool = False,
                    log=print, progress: bool = False, paths: list[str] | None = None) -> dict:
    """Time ``models`` on random inputs (module doc); write OUT/bench_speed.{json,csv,md} (``out`` None: nothing);
    return the result. ``progress``: bars on stderr while the models are prepared and while they are timed.
    ``paths`` (``--path``): the inference paths to time (reference, fast, fused; default fast); given, every
    variant's kernels per frame and output error to the fp32 reference are measured too, and a variant outside
    its precision's tolerance (``fastpath.TOLERANCE``) fails the run (BlendSRError, after the files are written)."""
    import copy
    import statistics

    import torch

    from training.config import ModelConfig
    from training.evaluate import describe_device
    from training.export import example_inputs
    from training.device import amp_dtype, dtype_label
    from training.fastpath import forward, prepare_inference, prepared_batch
    from training.inference import InferenceModel, load_model
    from training.models import build_model
    from training.device import resolve_device

    device = device or resolve_device("auto")
    w, h = size
    if w % scale or h % scale:
        raise BlendSRError(f"--size {w}x{h} is not divisible by the scale {scale}")
    checked = paths is not None
    paths = paths or ["fast"]
    reference = reference or "reference" in paths
    variants = ([("fp32 eager reference", None)] if reference else []) + \
        [(f"{dtype_label(amp_dtype(p, device))}{' compiled' if c else ''}{' fused' if fp == 'fused' else ''}",
          (p, c, fp)) for fp in paths if fp != "reference" for c in compiles for p in precisions]
    # labelled by the dtype that runs ("auto" resolved)
    if checked and device.type == "cpu":  # inductor's C++ kernels appear in the profiler (kernels per frame)
        import torch._inductor.config as inductor_config
        inductor_config.cpp.enable_kernel_profile = True
    peaks = {}
    for _, v in variants:
        dt = None if v is None else amp_dtype(v[0], device)
        key = dtype_label(dt)
        if key not in peaks:
            peaks[key] = device_peaks(device, dt, peak_tflops, bandwidth_gbs)
    timer = _timer(device)
    runners = []  # every (model, variant) is prepared first, then all are timed round-robin: side by side
    for label, spec in _bar(models, "prepare", "model", progress):
        name = label.split(" ")[0]
        if spec == name:
            base = InferenceModel(build_model(ModelConfig(name=name, scale=scale), scale).eval(), name)
        else:
            base = load_model(spec, scale, fast=False)
        n_params = sum(p.numel() for p in base.parameters())
        base.to(device)
        inputs = example_inputs(base, None, (w, h))
        batch = {k: torch.from_numpy(v).to(device) for k, v in inputs.items()}
        info = {"model": label, "params": n_params, "bytes": sum(v.nbytes for v in inputs.values()) + 3 * w * h * 4,
                "macs": macs_per_pixel(base, inputs, device) * w * h if n_params else 0.0}
        if checked:  # the fp32 eager reference's output, every variant's is compared with
            with torch.inference_mode():
                info["want"] = base(batch).float()
        for vlabel, v in variants:
            m = copy.deepcopy(base).to(device)
            if v is not None:
                prepare_inference(m, device, v[0], compile=v[1], path=v[2])
            settings = m.inference
            dt = settings.get("dtype")
            # inputs on the device in the layout the variant reads (as evaluate times the forward pass)
            b = prepared_batch(m, batch)
            runners.append({**info, "variant": vlabel, "module": m, "batch": b, "times": [],
                            "key": settings.get("precision") or dtype_label(dt)})
        del base, batch
    with torch.inference_mode():
        for r in runners:
            for _ in range(max(warmup, 1)):
                forward(r["module"], r["batch"])
            _sync(device)
        for _ in _bar(range(repeats), f"time {len(runners)} variants", "round", progress):  # round-robin: every
            # model and variant sees the same machine state
            for r in runners:
                r["times"].append(timer(lambda: forward(r["module"], r["batch"])))
        if checked:
            for r in runners:
                r.update(_check_variant(r, device))
    records = [_speed_record(r, peaks[r["key"]], w * h, log) for r in runners]
    del runners
    device_name = describe_device(device)
    meta = {"device": device_name, "size": [w, h], "scale": scale, "batch": 1, "warmup": warmup,
            "repeats": repeats, "timing": "median of the repeats; " + ("CUDA events" if device.type == "cuda"
                                                                       else "perf_counter"),
            "threads": torch.get_num_threads() if device.type == "cpu" else None, "peaks": peaks,
            "torch": torch.__version__}
    table = speed_table(records, [vl for vl, _ in variants])
    if checked:
        table += "\n\n" + check_table(records)
    log(table)
    result = {**meta, "rows": records, "table": table}
    if out is not None:  # nothing written where nobody asked (blendsr bench models without -o)
        _write_speed(Path(out), meta, records, table)
    _refuse_out_of_tolerance(records)
    return result


def _check_variant(r: dict, device) -> dict:
    """{kernels, max_rel_err, tolerance} of a prepared variant: kernels per frame (``kernels_per_frame``) and
    max |out - reference| / max |reference| against the fp32 reference output ``r['want']``."""
    import torch

    from training.fastpath import TOLERANCE, forward
    with torch.inference_mode():
        got = forward(r["module"], r["batch"]).float()
        kernels = kernels_per_frame(lambda: forward(r["module"], r["batch"]), device)
    want = r.pop("want")
    err = float((got - want).abs().max()) / max(float(want.abs().max()), 1e-30)
    return {"kernels": kernels, "max_rel_err": err, "tolerance": TOLERANCE[r["key"]]}


#: CPU operators that only make views or allocate (no loop over data): not counted as kernels.
_NO_WORK = {"aten::" + n for n in ("view", "as_strided", "reshape", "_reshape_alias", "permute", "expand", "slice",
                                    "select", "unsqueeze", "squeeze", "t", "transpose", "empty", "empty_strided",
                                    "empty_like", "alias", "detach", "lift_fresh", "_unsafe_view", "unbind",
                                    "split", "chunk", "narrow", "contiguous", "to", "resolve_conj", "resolve_neg",
                                    "view_as", "expand_as", "unflatten", "flatten", "set_", "zeros")}


def kernels_per_frame(fn, device, frames: int = 2) -> float:
    """Kernels one call of ``fn`` launches, from torch.profiler over ``frames`` calls. CUDA: device-side events
    (kernels, memcpy, memset). CPU: the operators that loop over data, counted at the top level (an operator's own
    sub-operators are not counted again; views and allocations are not counted) plus each C++ kernel of a
    compiled graph (inductor's kernel profiling is switched on by the speed mode)."""
    import torch
    from torch.profiler import ProfilerActivity, profile
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    _sync(device)
    with profile(activities=acts) as prof:
        for _ in range(frames):
            fn()
        _sync(device)
    if device.type == "cuda":
        n = sum(1 for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA)
        return n / frames

    def counted(e):
        return e.name.startswith("aten::") or "cpp_fused" in e.name

    def top(e):
        p = e.cpu_parent
        while p is not None:
            if counted(p):
                return False
            p = p.cpu_parent
        return True
    n = sum(1 for e in prof.events() if counted(e) and e.name not in _NO_WORK and top(e))
    return n / frames


def check_table(records: list[dict]) -> str:
    """Markdown: per model and variant, ms, kernels per frame, ratio to the roofline and the output's error to the
    fp32 reference against the precision's tolerance."""
    head = ["model", "variant", "ms", "kernels/frame", "roofline ms", "ms / roofline", "max rel. error", "tolerance",
            "ok"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in records:
        ok = r["max_rel_err"] <= r["tolerance"]
        lines.append("| " + " | ".join([r["model"], r["variant"], _ms(r["ms"]), f"{r['kernels']:.0f}",
                                        f"{r['roofline_ms']:.3g}", f"{r['ratio']:.1f}", f"{r['max_rel_err']:.2e}",
                                        f"{r['tolerance']:.0e}", "yes" if ok else "NO"]) + " |")
    return "\n".join(lines)


def _refuse_out_of_tolerance(records: list[dict]) -> None:
    bad = [r for r in records if "max_rel_err" in r and not r["max_rel_err"] <= r["tolerance"]]
    if bad:
        r = bad[0]
        raise BlendSRError(f"bench models: {r['model']} {r['variant']} differs from the fp32 reference by "
                           f"{r['max_rel_err']:.2e} of its peak (tolerance {r['tolerance']:.0e}); "
                           f"{len(bad)} variant(s) out of tolerance")


def speed_table(records: list[dict], variants: list[str]) -> str:
    """Markdown: one row per model, ms per variant, then the best variant's ratio to the roofline."""
    models = list(dict.fromkeys(r["model"] for r in records))
    head = ["model", "params", "MACs/px", "GMAC", "MB", *[f"{v} ms" for v in variants], "roofline ms",
            "best / roofline"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in models:
        rs = {r["variant"]: r for r in records if r["model"] == m}
        first = next(iter(rs.values()))
        best = min(rs.values(), key=lambda r: r["ms"])
        cells = [m, str(first["params"]), f"{first['macs_per_px']:.0f}", f"{first['gmacs']:.2f}",
                 f"{first['mbytes']:.1f}", *[_ms(rs[v]["ms"]) if v in rs else "-" for v in variants],
                 f"{best['roofline_ms']:.3g}", f"{best['ratio']:.0f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _ms(v: float) -> str:
    return f"{v:.3g}" if v < 100 else f"{v:.0f}"


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)
