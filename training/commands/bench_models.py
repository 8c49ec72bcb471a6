"""``blendsr bench models``: its command line (flags and ``run``); the benchmark itself is ``training.bench``.

What each mode measures and writes: ``training.bench``'s module doc and docs/evaluation.md. torch and matplotlib are
imported inside ``run``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from gbuffer_export.errors import BlendSRError
from training.bench import (BenchOptions, SpeedOptions, benchmark, load_models, parse_models,  # noqa: F401
                            speed_benchmark)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", nargs="*", default=[], metavar="CLIP",
                        help="clip directories or dataset folders (their --split); none: speed only, on random "
                             "inputs of --size")
    parser.add_argument("--split", default="test", choices=("train", "val", "test"),
                        help="split of dataset folders given to --data")
    parser.add_argument("--models", default=None,
                        help="comma-separated: model names, or NAME:CHECKPOINT for learned models (default: the "
                             "non-learned models with --data, every model without)")
    parser.add_argument("--size", default="x".join(map(str, SpeedOptions.size)), metavar="WxH",
                        help="HR size of the random inputs")
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
    parser.add_argument("--repeats", type=int, default=SpeedOptions.repeats, help="timed runs per variant (speed mode)")
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
    parser.add_argument("--cvvdp", action="store_true",
                        help="also ColorVideoVDP per clip (JOD, display model 'standard_fhd'; docs/evaluation.md): "
                             "the [video] extra")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"), help="where models run")
    parser.add_argument("--amp", default="none", choices=("none", "bf16", "fp16", "auto"),
                        help="autocast (with --data; --precision takes precedence)")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: the cores this process may use)")
    parser.add_argument("--warmup", type=int, default=BenchOptions.warmup, help="untimed runs before timing")
    parser.add_argument("--no-progress", action="store_true",
                        help="no progress bars on stderr (per model and clip with --data; preparing and timing "
                             "without)")
    parser.add_argument("--path", default=None, metavar="PATHS",
                        help="speed mode: comma-separated inference paths timed side by side: reference (fp32 eager, "
                             "= --eager-reference), fast (fast ops, autocast; the default), fused (fused HR stage, "
                             "weights held in the precision's dtype), graph (fused as one frozen inductor graph on "
                             "the CPU, one CUDA graph per frame on a GPU, timed as N >= 100 replays between two CUDA "
                             "events in 5 rounds: median and spread); adds kernels per frame and each output's "
                             "error to the fp32 reference, checked against the precision's tolerance")


def run(args) -> int:
    from gbuffer_export.extras import require
    require("blendsr bench models", "train")
    import torch

    from gbuffer_export.config import parse_frames
    from training.clip_sets import dataset_clips, scale_of
    from training.device import amp_dtype, resolve_device, set_threads

    set_threads(args.threads)
    device = resolve_device(args.device)
    args.data = [str(c) for c in dataset_clips(args.data, args.split)]
    precisions = _precisions(args.precision)
    compiles = {"off": [False], "on": [True], "both": [False, True], "off,on": [False, True]}[args.compile]
    if not args.data:
        from training.models import MODELS
        w, h = _size(args.size)
        if w % args.scale or h % args.scale:
            raise BlendSRError(f"--size {w}x{h} is not divisible by the scale {args.scale}")
        models = load_models(parse_models(args.models or ",".join(MODELS), need_checkpoints=False), args.scale,
                             fast=False)
        speed_benchmark([(label, m.to(device)) for label, m in models], args.output, SpeedOptions(
            size=(w, h), precisions=tuple(precisions or ["none"]), compiles=tuple(compiles), warmup=args.warmup,
            repeats=args.repeats, peak_tflops=args.peak_tflops, bandwidth_gbs=args.bandwidth_gbs,
            reference=args.eager_reference, progress=not args.no_progress, paths=_paths(args.path)))
        if args.output:
            print(f"wrote {Path(args.output) / 'bench_speed.json'}, {Path(args.output) / 'bench_speed.md'}")
        return 0
    if len(precisions or []) > 1 or len(compiles) > 1:
        raise BlendSRError("--data: one --precision and one --compile setting at a time")
    rng = parse_frames(args.frames)
    frames = {str(c): list(range(rng[0], rng[1] + 1)) for c in args.data} if rng else None
    models = load_models(parse_models(args.models or "bilinear,bicubic,demod-bilinear,demod-jbu"),
                         scale_of(args.data))
    benchmark([(label, m.to(device)) for label, m in models], list(args.data), args.output, BenchOptions(
        frames=frames, amp=amp_dtype(args.amp, device), flip=args.flip, cvvdp=args.cvvdp, warmup=args.warmup,
        precision=precisions[0] if precisions else None, compile=compiles[0], peak_tflops=args.peak_tflops,
        bandwidth_gbs=args.bandwidth_gbs, progress=not args.no_progress))
    if args.output:
        print(f"wrote {Path(args.output) / 'bench_models.json'}, {Path(args.output) / 'pareto.png'}")
    return 0


def _paths(text: str | None) -> tuple[str, ...] | None:
    """--path: None (the fast path alone) or the paths among reference, fast, fused, graph."""
    if not text:
        return None
    from training.inference.fastpath import PATHS
    out = [p.strip() for p in text.split(",") if p.strip()]
    bad = [p for p in out if p not in ("reference",) + PATHS]
    if bad or not out:
        raise BlendSRError(f"--path {text!r}: comma-separated reference, {', '.join(PATHS)}")
    return tuple(out)


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
