"""The library of ``blendsr bench models`` (its command line: ``training.commands.bench_models``): speed against
error, or speed alone against the hardware's limit.

With ``--data`` (clips), for every model (a non-learned name, or NAME:CHECKPOINT) it runs the evaluation of
``training.evaluate`` and reports PSNR/SSIM (declared tonemap), PSNR-HDR, tPSNR, warping error, optionally HDR-FLIP,
the median ms per frame, the parameter count and the multiply-accumulates per output pixel (convolutions and matrix
products counted by ``torch.utils.flop_counter``; interpolation and element-wise operations are not counted), and
the worst case beside the means (``training.evaluate``: the margin over ``demod-jbu`` and its smallest per-clip
value, the worst 1 % share, artifact pixels; ``demod-jbu`` scored once for all rows). A model whose inputs a clip
lacks is left out with a one-line note instead of failing the table. Models are ``InferenceModel``s
(``load_models``); the options of a run are ``BenchOptions`` (``SpeedOptions`` for the speed mode). With
``-o OUT`` it writes OUT/bench_models.json, OUT/bench_models.csv, OUT/bench_models.md and the Pareto plot
OUT/pareto.png (PSNR against ms per frame, the non-dominated models joined, the data stated: ``plot``), with the
roofline columns of the speed mode (below) for one frame of the clips.

Without ``--data`` it times every model on random inputs of the right shapes (``export.example_inputs``) at
``--size`` (HR, default 1920x1080) and ``--scale``, batch 1, for each precision of ``--precision`` and each
``--compile`` setting (the inference fast path, ``training.inference.fastpath``); learned models named without a checkpoint
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

import csv
import json
import statistics
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from gbuffer_export.errors import BlendSRError

COLUMNS = ("model", "params", "macs_per_px", "ms_per_frame", "psnr", "margin", "margin_min", "ssim", "psnr_hdr",
           "flip", "cvvdp", "tpsnr", "warp_error", "worst_share", "artifact_fraction", "artifact_fraction_max", "roofline_ms",
           "ratio")


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
GRAPH_COLUMNS = ("spread", "replays", "timing")  # a graph variant's row: frame_graph.time_replays
SPEED_COLUMNS = ("model", "variant", "params", "macs_per_px", "gmacs", "mbytes", "ms", "ms_min", "roofline_ms",
                 "ratio", "kernels", "max_rel_err", "tolerance", *GRAPH_COLUMNS)


def parse_models(text: str, need_checkpoints: bool = True) -> list[tuple[str, str]]:
    """'bicubic,fusesr:runs/a/checkpoints/last.pt,pretrained:fusesr' -> [('bicubic', 'bicubic'),
    ('fusesr (a)', 'runs/a/...'), ('pretrained:fusesr', 'pretrained:fusesr')]. Without ``need_checkpoints`` a
    learned model may be named alone (initial weights: speed only)."""
    from training.models import MODELS
    out = []  # (label, spec, the model's name when spec is a checkpoint path)
    for item in (t.strip() for t in text.split(",")):
        if not item:
            continue
        if item.startswith("pretrained:"):  # a shipped model (training/pretrained.py)
            out.append((item, item, None))
            continue
        name, sep, path = item.partition(":")
        if name not in MODELS:
            raise BlendSRError(f"--models: unknown model {name!r}; choose among {', '.join(MODELS)}")
        if MODELS[name].learned and not sep and need_checkpoints:
            raise BlendSRError(f"--models: {name!r} is learned; write {name}:CHECKPOINT")
        out.append((checkpoint_label(name, path), path, name) if sep else (name, name, None))
    if not out:
        raise BlendSRError("--models: no model given")
    # checkpoints of runs whose model folders share a name (runs/a/fusesr, runs/b/fusesr) are labelled by path
    short = [label for label, _, _ in out]
    rows = [(f"{name} ({spec})" if name and short.count(label) > 1 else label, spec) for label, spec, name in out]
    labels = [label for label, _ in rows]
    twice = sorted({label for label in labels if labels.count(label) > 1})
    if twice:
        raise BlendSRError(f"--models: {twice[0]!r} is given twice")
    return rows


def checkpoint_label(name: str, path: str) -> str:
    """'fusesr' + 'runs/a/checkpoints/last.pt' -> 'fusesr (a)'; other files -> 'fusesr (file stem)'; inference
    options after '?' stay in the label ('fusesr (a?residual_clamp=none)'), so two rows of one file differ."""
    path, q, options = str(path).partition("?")
    p = Path(path)
    tag = p.parent.parent.name if p.parent.name == "checkpoints" and p.parent.parent.name else p.stem
    return f"{name} ({tag}{q}{options})"


def macs_per_pixel(model, inputs: dict) -> float:
    """Multiply-accumulates per HR output pixel of one forward pass of ``model`` (an ``InferenceModel``) on its
    device (flop counter / 2)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode
    needs = set(model.module.needs())
    batch = {k: torch.from_numpy(v).to(model.device) for k, v in inputs.items() if k in needs}
    counter = FlopCounterMode(display=False)
    with torch.inference_mode(), counter:
        sr = model.module(batch)
    return counter.get_total_flops() / 2.0 / (sr.shape[-1] * sr.shape[-2])


def load_models(models: list[tuple[str, str]], scale: float, fast: bool = True) -> list[tuple[str, object]]:
    """(label, spec) pairs of ``parse_models`` -> (label, ``InferenceModel``) on the CPU at ``scale``. A
    NAME:CHECKPOINT must hold model NAME; a learned model named alone (speed only) gets its initial weights.
    ``fast``: prepared for the fast path (``load_model``)."""
    from training.checkpoint import load_checkpoint
    from training.config import ModelConfig
    from training.inference.loading import InferenceModel, load_model, split_spec
    from training.models import MODELS, build_model
    out = []
    for label, spec in models:
        name = label.split(" ")[0]
        if spec == name and name in MODELS and MODELS[name].learned:
            out.append((label, InferenceModel(build_model(ModelConfig(name=name, scale=scale), scale).eval(), name)))
            continue
        if spec != name:
            ck_name = load_checkpoint(split_spec(spec)[0])["model_name"]  # the file, without its '?' options
            if ck_name != name:
                raise BlendSRError(f"{spec}: checkpoint holds model {ck_name!r}, not {name!r}")
        out.append((label, load_model(spec, scale, fast=fast)))
    return out


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of points not dominated (lower time and higher quality), sorted by time."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], float("-inf")
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


@dataclass
class BenchData:
    """What a speed-against-error plot states about its data: the clips (paths), their HR sizes, the scale, the
    frames scored per model, the device, the precisions that ran and the metric's tonemap."""
    clips: list[str]
    hr_sizes: list[tuple[int, int]]
    scale: float
    frames: int
    device: str
    precision: str
    transform: str = "reinhard-srgb"

    @classmethod
    def of(cls, clips, result: dict, precisions) -> "BenchData":
        """From ``benchmark``'s clips and first model's result (``evaluate_model``) and the dtypes that ran."""
        from gbuffer_export.clip import open_clip
        sizes = list(dict.fromkeys(open_clip(c).sizes["hr"] for c in clips))
        return cls([str(c) for c in clips], sizes, float(result["scale"]), len(result["per_frame"]),
                   result["device"], ", ".join(precisions), result["transform"].split(":")[0])

    def lines(self) -> list[str]:
        """Two lines: the data (clips, sizes, frames), then how it was measured (device, precision, metric)."""
        names = [Path(c).name for c in self.clips]
        parents = {Path(c).parent for c in self.clips}
        where = ""
        if len(parents) == 1 and next(iter(parents)).name == "clips":  # DATASET/clips/ID
            where = f" of {next(iter(parents)).parent.name}"
        shown = ", ".join(names) if len(names) <= 3 else f"{len(names)} clips{where} ({names[0]}, ..., {names[-1]})"
        if len(names) <= 3 and where:
            shown += where
        sizes = ", ".join(f"{w}x{h}" for w, h in self.hr_sizes)
        lr = ", ".join(f"{round(w / self.scale)}x{round(h / self.scale)}" for w, h in self.hr_sizes)
        return [f"{shown}: HR {sizes}, LR {lr} (x{self.scale:g}); {self.frames} frames per model",
                f"{self.device}; {self.precision}; PSNR of the {self.transform} tonemap, mean over the frames"]


def _overlap(a, b, gap: float = 1.0) -> bool:
    """Two matplotlib Bboxes (display pixels) closer than ``gap``."""
    return not (a.x1 + gap <= b.x0 or b.x1 + gap <= a.x0 or a.y1 + gap <= b.y0 or b.y1 + gap <= a.y0)


def _line_boxes(line, px: float) -> list:
    """Small boxes (display pixels) every 3 px along a Line2D, for labels to keep off it."""
    from matplotlib.transforms import Bbox
    xy = line.get_transform().transform(line.get_xydata())
    out = []
    for (x0, y0), (x1, y1) in zip(xy[:-1], xy[1:]):
        n = max(1, int(np.hypot(x1 - x0, y1 - y0) / (3 * px)))
        out += [Bbox.from_bounds(x0 + (x1 - x0) * k / n - px, y0 + (y1 - y0) * k / n - px, 2 * px, 2 * px)
                for k in range(n + 1)]
    return out


def _put(ann, ox: float, oy: float, dx: int, dy: int) -> None:
    """Set a label ``(ox, oy)`` points from its point, aligned away from it in the direction ``(dx, dy)``."""
    ann.set_position((ox, oy))
    ann.set_ha({1: "left", -1: "right", 0: "center"}[dx])
    ann.set_va({1: "bottom", -1: "top", 0: "center"}[dy])


def place_labels(ax, points: list[tuple[float, float]], texts: list[str], fontsize: float = 8,
                 avoid=()) -> list:
    """Annotate ``points`` (data coordinates) with ``texts`` so that no two labels overlap each other, a marker,
    the artists ``avoid`` (the legend; a line: along its path) or the axes' edge: each label takes the first free
    place of 8 directions at growing distances (offset points), with a leader line when it sits away from its
    point; a label with no free place takes the place that overlaps least. The figure's layout must be final (no
    tight_layout afterwards). Returns the labels, in the order of ``points``."""
    fig = ax.figure
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    inside = ax.get_window_extent(renderer).padded(-2)
    px = fig.dpi / 72.0
    from matplotlib.transforms import Bbox
    taken = [Bbox.from_bounds(x - 4 * px, y - 4 * px, 8 * px, 8 * px)
             for x, y in ax.transData.transform(points)]
    for art in avoid:
        taken += _line_boxes(art, px) if hasattr(art, "get_xydata") else [art.get_window_extent(renderer)]
    dirs = [(1, 0), (1, 1), (1, -1), (-1, 0), (-1, 1), (-1, -1), (0, 1), (0, -1)]
    tries = [(r * dx / (1.4 if dx and dy else 1), r * dy / (1.4 if dx and dy else 1), dx, dy)
             for r in (6, 14, 24, 36, 50, 66, 84) for dx, dy in dirs]
    labels = []
    order = sorted(range(len(points)), key=lambda i: -points[i][1])
    for i in order:
        ann = ax.annotate(texts[i], points[i], xytext=(0, 0), textcoords="offset points", fontsize=fontsize,
                          zorder=4, annotation_clip=False)
        best = None
        for place in tries:
            _put(ann, *place)
            box = ann.get_window_extent(renderer)
            clash = sum(_overlap(box, t) for t in taken) + (0 if inside.contains(box.x0, box.y0) and
                                                            inside.contains(box.x1, box.y1) else 1)
            if best is None or clash < best[0]:
                best = (clash, place)
            if clash == 0:
                break
        _put(ann, *best[1])
        ox, oy = best[1][:2]
        if abs(ox) + abs(oy) > 14:  # a leader line from the label to its point
            ax.annotate("", points[i], xytext=(ox, oy), textcoords="offset points",
                        arrowprops={"arrowstyle": "-", "color": "0.55", "lw": 0.6, "shrinkA": 0, "shrinkB": 3})
        taken.append(ann.get_window_extent(renderer))
        labels.append(ann)
    return [labels[order.index(i)] for i in range(len(points))]


def plot(rows: list[dict], path: Path, device: str, data: BenchData | None = None) -> dict:
    """OUT/pareto.png: PSNR against median ms per frame (log scale) of every row, the non-dominated rows joined,
    each point labelled with its model where no other label, marker or the axes' edge is (``place_labels``);
    ``data``'s lines (clips, sizes, frames, device, precision) under the title. Returns {'labels': [(model,
    (x0, y0, x1, y1))], 'points', 'axes', 'legend', 'texts', 'size'}: the labels', markers', axes' and legend's
    places in the PNG's pixels (from the bottom, as matplotlib's renderer measured them) and the lines stated."""
    import matplotlib
    matplotlib.use("Agg")
    import textwrap

    import matplotlib.pyplot as plt
    pts = [(max(r["ms_per_frame"], 1e-3), r["psnr"]) for r in rows]
    front = pareto_front(pts)
    about = data.lines() if data is not None else [device]
    wrapped = [ln for text in about for ln in textwrap.wrap(text, 105)]
    fig, ax = plt.subplots(figsize=(7.2, 4.6 + 0.14 * len(wrapped)), dpi=120)
    ax.scatter([p[0] for p in pts], [p[1] for p in pts], c="tab:blue", s=18, zorder=3)
    line, = ax.plot([pts[i][0] for i in front], [pts[i][1] for i in front], "--", c="tab:orange",
                    label="Pareto front", zorder=2)
    ax.set_xscale("log")
    ax.margins(x=0.25, y=0.18)
    ax.set_xlabel("ms per frame (median, log scale)")
    ax.set_ylabel(f"PSNR (dB, {data.transform if data else 'reinhard-srgb'} tonemap)")
    fig.suptitle(f"Error against time per frame, {len(rows)} models", fontsize=10, x=0.02, ha="left")
    ax.set_title("\n".join(wrapped), fontsize=7.5, loc="left", color="0.25")
    ax.grid(True, which="both", alpha=0.3)
    legend = ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    labels = place_labels(ax, pts, [r["model"] for r in rows], avoid=[legend, line])
    renderer = fig.canvas.get_renderer()
    out = {"labels": [(r["model"], tuple(lab.get_window_extent(renderer).extents)) for r, lab in zip(rows, labels)],
           "points": [tuple(p) for p in ax.transData.transform(pts)],
           "axes": tuple(ax.get_window_extent(renderer).extents), "texts": wrapped,
           "legend": tuple(legend.get_window_extent(renderer).extents),
           "size": tuple(int(v) for v in fig.canvas.get_width_height())}
    fig.savefig(path)
    plt.close(fig)
    return out


@dataclass(frozen=True)
class BenchOptions:
    """How ``benchmark`` scores: ``frames`` (clip path -> frames; default all), ``amp`` (autocast dtype), ``flip``,
    ``warmup``, ``precision`` and ``compile`` (the fast path's, ``prepare_inference``; None/False: as loaded),
    ``peak_tflops`` and ``bandwidth_gbs`` (the roofline's device peaks; 0: ``device_peaks``), ``progress`` (bars on
    stderr), ``baseline`` (the worst-case columns against ``metrics.BASELINE``; False: none) and ``log`` (where
    each row's line goes)."""

    frames: dict | None = None
    amp: object = None
    flip: bool = False
    cvvdp: bool = False
    warmup: int = 2
    precision: str | None = None
    compile: bool = False
    peak_tflops: float = 0.0
    bandwidth_gbs: float = 0.0
    progress: bool = False
    baseline: bool = True
    log: Callable = print


def benchmark(models: list[tuple[str, object]], clips, out, options: BenchOptions = BenchOptions()) -> dict:
    """Evaluate ``models`` ((label, ``InferenceModel``) pairs, ``load_models``, all on one device) on ``clips`` at
    the clips' 'lr' level (every model at the same scale); write the table files and ``pareto.png`` under ``out``
    (None: nothing written); return {device, scale, rows, results, left_out, table}. A model whose inputs a clip
    lacks is left out with a one-line note (``left_out``) instead of failing the table."""
    from training.clip_sets import scale_of
    from training.evaluate import Baseline, EvalOptions, evaluate_model
    o = options
    scale = scale_of(clips)
    # scored once, shared by every model, on their device
    baseline = Baseline(device=models[0][1].device) if o.baseline and models else None
    rows, results, left_out = [], [], []
    peaks: dict = {}
    for label, model in models:
        note = _lacking(label, model, clips)
        if note:
            o.log(note)
            left_out.append(note)
            continue
        if o.precision is not None or o.compile:
            from training.inference.fastpath import prepare_inference
            prepare_inference(model, None, o.precision or "none", compile=o.compile)
        amp = None if o.precision is not None or o.compile else o.amp
        res = evaluate_model(model, clips, EvalOptions(frames=o.frames, amp=amp, flip=o.flip, warmup=o.warmup,
                                                       label=label, progress=o.progress, scale=scale,
                                                       baseline=baseline, cvvdp=o.cvvdp))
        rows.append(_row(label, model, res, clips, o, peaks, amp))
        results.append(res)
        r = rows[-1]
        o.log(f"{label:24s} {r['ms_per_frame']:9.2f} ms  PSNR {r['psnr']:6.2f} dB  SSIM {r['ssim']:.4f}"
              + (f"  margin {r['margin']:+.2f} dB (min {r['margin_min']:+.2f})" if r.get("margin") is not None
                 else "") + (f"  ColorVideoVDP {r['cvvdp']:.3f} JOD" if r.get("cvvdp") is not None else ""))
    if not rows:
        raise BlendSRError("bench models: no model could be scored on these clips (" + "; ".join(left_out) + ")")
    device_name = results[0]["device"]
    md = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        md.append("| " + " | ".join(_fmt(r.get(k)) for k in COLUMNS) + " |")
    table = "\n".join(md + [""] + [f"- {n}" for n in left_out]).rstrip()
    o.log(table)
    result = {"device": device_name, "scale": scale, "rows": rows, "results": results, "left_out": left_out,
              "table": table}
    if out is not None:  # nothing written where nobody asked (blendsr bench models without -o)
        _write_bench(Path(out), result, peaks, clips)
    return result


def _lacking(label: str, model, clips) -> str | None:
    """A one-line note when a clip lacks inputs of ``model`` (it is then left out of the table), else None."""
    from training.inference.loading import ClipFrames, missing_keys
    for c in clips:
        lacking = missing_keys(model, ClipFrames(c, eps=model.demod_eps))
        if lacking:
            return f"left out {label}: {c} lacks {', '.join(lacking)}, which it reads"
    return None


def _row(label: str, model, res: dict, clips, o: BenchOptions, peaks: dict, amp) -> dict:
    """The table row of one evaluated model, with its roofline on one frame of these clips (bytes: the model's
    inputs read once, the output written once)."""
    from training.device import dtype_label
    from training.inference.loading import ClipFrames, model_inputs
    src = ClipFrames(clips[0], eps=model.demod_eps)
    first = (o.frames or {}).get(str(clips[0])) or src.frames
    m = res["mean"]
    inputs = model_inputs(model, src, first[0])
    row = {"model": label, "params": model.n_params, "macs_per_px": macs_per_pixel(model, inputs),
           **{k: m[k] for k in COLUMNS if k in m}, "margin_min_clip": m.get("margin_min_clip"),
           "per_clip": [{k: c[k] for k in ("clip", "margin", "worst_share", "artifact_pixels", "artifact_fraction",
                                           "cvvdp")} for c in res["per_clip"]]}
    scale = src.scale
    hw = inputs["lr/radiance"].shape[-2] * inputs["lr/radiance"].shape[-1] * scale * scale
    nbytes = sum(v.nbytes for k, v in inputs.items() if k in set(model.module.needs())) + 3 * hw * 4
    dt = model.settings.get("dtype") or amp
    key = dtype_label(dt)
    if key not in peaks:
        peaks[key] = device_peaks(model.device, dt, o.peak_tflops, o.bandwidth_gbs)
    row["roofline_ms"] = 1000 * max(2 * row["macs_per_px"] * hw / (peaks[key]["tflops"] * 1e12),
                                    nbytes / (peaks[key]["gbs"] * 1e9))
    row["ratio"] = row["ms_per_frame"] / row["roofline_ms"]
    return row


def _write_bench(out: Path, result: dict, peaks: dict, clips) -> None:
    """OUT/bench_models.json, .csv, .md and pareto.png."""
    out.mkdir(parents=True, exist_ok=True)
    rows, device_name, scale = result["rows"], result["device"], result["scale"]
    (out / "bench_models.json").write_text(json.dumps(
        {"device": device_name, "scale": scale, "peaks": peaks, "clips": [str(c) for c in clips], "rows": rows,
         "left_out": result["left_out"], "transform": result["results"][0]["transform"],
         "cvvdp": result["results"][0]["cvvdp"],
         "worst_case": result["results"][0]["worst_case"]}, indent=1) + "\n")
    with open(out / "bench_models.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k) for k in COLUMNS})
    (out / "bench_models.md").write_text(f"Device: {device_name}; scale {scale}\n\n{result['table']}\n")
    plot(rows, out / "pareto.png", device_name, BenchData.of(clips, result["results"][0], list(peaks)))


def _bar(items, desc: str, unit: str, on: bool):
    """``items``, under a tqdm bar on stderr when ``on``."""
    if not on:
        return items
    import sys

    from tqdm import tqdm
    return tqdm(items, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True, leave=False)


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
    if "graph_timing" in r:  # frame_graph.time_replays: the spread of its rounds and the replays per round
        rec.update(zip(GRAPH_COLUMNS, (r["graph_timing"]["spread"], r["graph_timing"]["n"],
                                       "CUDA graph replays between two CUDA events")))
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


@dataclass(frozen=True)
class SpeedOptions:
    """How ``speed_benchmark`` times: HR ``size`` (W, H) of the random inputs, the ``precisions`` and ``compiles``
    settings of the fast path, ``warmup`` and ``repeats``, the roofline's ``peak_tflops`` and ``bandwidth_gbs`` (0:
    ``device_peaks``), ``reference`` (also the fp32 eager reference path), ``progress`` and ``log``; ``paths``
    (``--path``): the inference paths to time (reference, fast, fused, graph; None: fast): given, every variant's
    kernels per frame and output error to the fp32 reference are measured too, and a variant outside its precision's
    tolerance (``fastpath.TOLERANCE``) fails the run (BlendSRError, after the files are written)."""

    size: tuple[int, int] = (1920, 1080)
    precisions: tuple[str, ...] = ("none",)
    compiles: tuple[bool, ...] = (False,)
    warmup: int = 2
    repeats: int = 30
    peak_tflops: float = 0.0
    bandwidth_gbs: float = 0.0
    reference: bool = False
    progress: bool = False
    log: Callable = print
    paths: tuple[str, ...] | None = None


def speed_benchmark(models: list[tuple[str, object]], out, options: SpeedOptions = SpeedOptions()) -> dict:
    """Time ``models`` ((label, ``InferenceModel``) pairs, not yet prepared, all on one device and at one scale;
    ``load_models(..., fast=False)``) on random inputs (module doc); write OUT/bench_speed.{json,csv,md} (``out``
    None: nothing); return the result."""
    import torch

    from training.device import amp_dtype, dtype_label
    from training.evaluate import describe_device

    o = options
    device = models[0][1].device
    scale = models[0][1].module.scale
    w, h = o.size
    if w % scale or h % scale:
        raise BlendSRError(f"--size {w}x{h} is not divisible by the scale {scale}")
    checked = o.paths is not None
    paths = o.paths or ("fast",)
    variants = ([("fp32 eager reference", None)] if o.reference or "reference" in paths else []) + \
        [(f"{dtype_label(amp_dtype(p, device))}{' compiled' if c else ''}{'' if fp == 'fast' else ' ' + fp}",
          (p, c, fp)) for fp in paths if fp != "reference" for c in o.compiles for p in o.precisions]
    # labelled by the dtype that runs ("auto" resolved)
    peaks = {}
    for _, v in variants:
        dt = None if v is None else amp_dtype(v[0], device)
        if dtype_label(dt) not in peaks:
            peaks[dtype_label(dt)] = device_peaks(device, dt, o.peak_tflops, o.bandwidth_gbs)
    import contextlib
    profiled = contextlib.nullcontext()
    if checked and device.type == "cpu":  # inductor's C++ kernels appear in the profiler (kernels per frame), for
        import torch._inductor.config as inductor_config  # this run only: the setting is process-wide
        profiled = inductor_config.patch({"cpp.enable_kernel_profile": True})
    with profiled:
        runners = _speed_runners(models, variants, o, checked)
        _time_runners(runners, device, o)
        if checked:
            for r in runners:
                r.update(_check_variant(r, device))
    records = [_speed_record(r, peaks[r["key"]], w * h, o.log) for r in runners]
    del runners
    meta = {"device": describe_device(device), "size": [w, h], "scale": scale, "batch": 1, "warmup": o.warmup,
            "repeats": o.repeats, "timing": "median of the repeats; " + ("CUDA events" if device.type == "cuda"
                                                                         else "perf_counter"),
            "threads": torch.get_num_threads() if device.type == "cpu" else None, "peaks": peaks,
            "torch": torch.__version__}
    table = speed_table(records, [vl for vl, _ in variants])
    if checked:
        table += "\n\n" + check_table(records)
    o.log(table)
    result = {**meta, "rows": records, "table": table}
    if out is not None:  # nothing written where nobody asked (blendsr bench models without -o)
        _write_speed(Path(out), meta, records, table)
    _refuse_out_of_tolerance(records)
    return result


def _speed_runners(models, variants, o: SpeedOptions, checked: bool = False) -> list[dict]:
    """Every (model, variant) prepared, with its inputs on the device in the layout the variant reads (as
    evaluate times the forward pass), before any is timed; ``checked``: with the fp32 eager reference's output
    (``want``) every variant's is compared with."""
    import copy

    import torch

    from training.device import dtype_label
    from training.inference.export import example_inputs
    from training.inference.fastpath import prepare_inference, prepared_batch
    w, h = o.size
    runners = []
    for label, base in _bar(models, "prepare", "model", o.progress):
        device = base.device
        inputs = example_inputs(base, None, (w, h))
        batch = {k: torch.from_numpy(v).to(device) for k, v in inputs.items()}
        info = {"model": label, "params": base.n_params,
                "bytes": sum(v.nbytes for v in inputs.values()) + 3 * w * h * 4,
                "macs": macs_per_pixel(base, inputs) * w * h if base.n_params else 0.0}
        if checked:
            with torch.inference_mode():
                info["want"] = base.forward(batch).float()
        for vlabel, v in variants:
            m = copy.deepcopy(base)
            if v is not None:
                prepare_inference(m, device, v[0], compile=v[1], path=v[2])
            runners.append({**info, "variant": vlabel, "module": m, "batch": prepared_batch(m, batch), "times": [],
                            "key": m.settings.get("precision") or dtype_label(m.settings.get("dtype"))})
    return runners


def _time_runners(runners: list[dict], device, o: SpeedOptions) -> None:
    """Warm every runner up, then time them round-robin ``o.repeats`` times: every model and variant sees the same
    machine state."""
    import torch

    from training.inference.fastpath import forward
    timer = _timer(device)
    with torch.inference_mode():
        for r in runners:
            for _ in range(max(o.warmup, 1)):
                forward(r["module"], r["batch"])
            _sync(device)
        graphs = [r for r in runners if r["module"].settings.get("frame_graph")]
        for r in graphs:  # one CUDA graph per frame: N replays between two CUDA events, several rounds
            from training.inference.frame_graph import time_replays
            r["graph_timing"] = time_replays(r["module"].settings["graphs"]["forward"].replay_last(),
                                             n=max(100, o.repeats), rounds=5)
            r["times"] = list(r["graph_timing"]["rounds"])
        timed = [r for r in runners if r not in graphs]
        for _ in _bar(range(o.repeats if timed else 0), f"time {len(timed)} variants", "round", o.progress):
            for r in timed:
                r["times"].append(timer(lambda: forward(r["module"], r["batch"])))


def _check_variant(r: dict, device) -> dict:
    """{kernels, max_rel_err, tolerance} of a prepared variant: kernels per frame (``kernels_per_frame``) and
    max |out - reference| / max |reference| against the fp32 reference output ``r['want']``."""
    import torch

    from training.inference.fastpath import TOLERANCE, forward
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
