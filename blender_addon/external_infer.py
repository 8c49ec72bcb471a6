"""Upscale one frame of a clip with the training helper's inference API and score it against the ground truth.

Used two ways:
  * in Blender's Python when torch is importable there: ``run_inference(clip_dir, frame, spec)``;
  * with an external Python that has torch and the library (add-on preferences, ``python_path``):
        python external_infer.py --clip DIR --frame F --model SPEC --out DIR [--sys-path D ...] [--reference]
    writes OUT/sr.exr, OUT/bilinear.exr (and OUT/reference.exr with --reference) as linear RGB float32 and
    OUT/result.json {ms, warmup_ms, repeats, runtime, psnr, metric, size, inference}; exit 0, or 2 with {error} in
    result.json;
  * in Blender's Python without torch, through ONNX Runtime and the zip's graphs: ``run_onnx_inference``.

Times: the first call (with the model's loading or the ONNX Runtime sessions' creation) is ``warmup_ms``; ``ms`` is
the median of the ``REPEATS`` calls after it (the model's time per frame, as ``blendsr bench models`` reports it).

The torch model runs on the inference path ``--path`` (default ``auto``: the fastest that passes the reference check,
``training.inference.fastpath.AutoPath``), as ``blendsr upscale`` does; ``inference`` records the path that ran.

PSNR is the evaluation's: ``training.metrics.psnr_tm`` (PSNR, peak 1, of the tonemapped images: sRGB OETF of
Reinhard x/(1+x)); if training.metrics cannot be imported, the same transform from ``gbuffer_export.preview.tonemap``
and PSNR on [0, 1] floats. ``metric`` in the result names which one was used. Standard library only at import time.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import traceback


def psnr_function():
    """(callable(sr, ref) -> dB, description) of the evaluation's PSNR for linear HDR H x W x 3 images:
    ``training.metrics.psnr_tm`` (tonemapped, peak 1) when it imports, else ``tonemapped_psnr``."""
    try:
        from training import metrics
        fn = metrics.psnr_tm
    except (ImportError, AttributeError):
        return tonemapped_psnr, "PSNR of gbuffer_export.preview.tonemap (Reinhard x/(1+x), sRGB), peak 1"
    desc = f"training.metrics.psnr_tm, {getattr(metrics, 'TRANSFORM', 'tonemapped')}"
    return (lambda sr, ref: float(fn(sr, ref))), desc


def tonemapped_psnr(sr, ref) -> float:
    """PSNR in dB between the display encodings (``gbuffer_export.preview.tonemap``) of two linear images."""
    import numpy as np
    from gbuffer_export.preview import tonemap
    mse = float(np.mean((tonemap(sr) - tonemap(ref)) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)


_MODELS: dict = {}


def load_model_cached(spec: str, scale: int, path: str | None = None):
    """``training.inference.loading.load_model`` prepared for inference path ``path`` (``fastpath.prepare_inference``, on
    the GPU when there is one), with a cache keyed on the spec, scale, path and checkpoint file time (the path
    ``auto`` chooses on the first frame is kept with the model); None: ``fastpath.default_path``."""
    from training.device import resolve_device
    from training.inference.fastpath import default_path, prepare_inference
    from training.inference.loading import load_model
    path = path or default_path()
    mtime = os.path.getmtime(spec) if os.path.isfile(spec) else None
    key = (spec, scale, path, mtime)
    if key not in _MODELS:
        _MODELS.clear()
        _MODELS[key] = prepare_inference(load_model(spec, scale, fast=False), resolve_device("auto"), path=path)
    return _MODELS[key]


#: Calls after the first one whose median is the preview's per-frame time (the first call, with the model's or
#: session's creation, is reported apart as the warm-up).
REPEATS = 3


def timed_calls(call, load_ms: float = 0.0, repeats: int = REPEATS) -> tuple[dict, dict]:
    """(the first call's result, {'ms': median of ``repeats`` more calls' 'ms', 'warmup_ms': ``load_ms`` + the
    first call's, 'repeats'})."""
    import statistics
    first = call()
    later = [call()["ms"] for _ in range(repeats)]
    return first, {"ms": float(statistics.median(later)) if later else float(first["ms"]),
                   "warmup_ms": float(load_ms) + float(first["ms"]), "repeats": len(later)}


def _result(out: dict, times: dict, runtime: str, with_reference: bool) -> dict:
    import numpy as np
    res = {"sr": np.asarray(out["sr"], np.float32), "bilinear": np.asarray(out["bilinear"], np.float32),
           **times, "runtime": runtime}
    ref = out.get("reference")
    if with_reference and ref is not None:
        fn, desc = psnr_function()
        res["reference"] = np.asarray(ref, np.float32)
        res["psnr"] = float(fn(res["sr"], res["reference"]))
        res["metric"] = desc
    return res


def run_inference(clip_dir: str, frame: int, spec: str, with_reference: bool, path: str | None = None) -> dict:
    """Upscale ``frame`` of the clip with model ``spec`` (a model name or a checkpoint path) through torch, on
    inference path ``path`` ('inference' in the result: the path that ran, ``fastpath.path_record``).

    Returns {'sr', 'bilinear': HxWx3 float32 linear, 'reference': HxWx3 or absent, 'ms': median milliseconds of
    the calls after the first, 'warmup_ms': loading plus the first call, 'runtime', 'psnr': dB or absent,
    'metric': how PSNR was computed}."""
    import time

    import torch
    from gbuffer_export import open_clip
    from training.inference.fastpath import path_record
    from training.inference.loading import upscale_frame
    clip = open_clip(clip_dir)
    t0 = time.perf_counter()
    model = load_model_cached(spec, clip.scale, path)
    load_ms = 1000.0 * (time.perf_counter() - t0)
    out, times = timed_calls(lambda: upscale_frame(model, clip, frame), load_ms)
    return {**_result(out, times, f"torch {torch.__version__}", with_reference), "inference": path_record(model)}


def run_onnx_inference(clip_dir: str, frame: int, spec: str, with_reference: bool, graphs_dir: str) -> dict:
    """``run_inference`` through ONNX Runtime with the graphs in ``graphs_dir`` (the zip's ``onnx/``): no torch.
    'warmup_ms' holds the sessions' creation and the first call."""
    from gbuffer_export import open_clip
    from training.inference import onnx_infer
    clip = open_clip(clip_dir)
    path = onnx_infer.find_graph(graphs_dir, spec, clip.scale)
    bil_path = onnx_infer.find_graph(graphs_dir, "bilinear", clip.scale)
    if path is None or bil_path is None:
        raise FileNotFoundError(f"{graphs_dir}: no ONNX graph of {spec if path is None else 'bilinear'} for scale "
                                f"{clip.scale}")
    model, bil = onnx_infer.OnnxModel(path), onnx_infer.OnnxModel(bil_path)
    source = onnx_infer.ClipFrames(clip, eps=model.demod_eps)
    out, times = timed_calls(lambda: onnx_infer.upscale_frame(model, source, frame, bilinear=bil),
                             model.load_ms + bil.load_ms)
    return _result(out, times, f"{onnx_infer.runtime_version()} (CPU)", with_reference)


def _write_rgb(path: str, img) -> None:
    from gbuffer_export.exr import write_exr
    write_exr(path, {c: img[..., i] for i, c in enumerate("RGB")})


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clip", required=True, help="clip directory")
    p.add_argument("--frame", type=int, required=True, help="frame number")
    p.add_argument("--model", required=True, help="model name (e.g. demod-bilinear) or checkpoint path")
    p.add_argument("--out", required=True, help="output folder for sr.exr, bilinear.exr, result.json")
    p.add_argument("--reference", action="store_true", help="also write reference.exr and the PSNR")
    p.add_argument("--path", default=None, choices=("auto", "reference", "fast", "fused", "graph"),
                   help="inference path (training.inference.fastpath; default $BLENDSR_INFERENCE_PATH, else auto: the fastest "
                        "that passes the reference check)")
    p.add_argument("--sys-path", action="append", default=[], help="folder to put on sys.path (repeatable)")
    p.add_argument("--site-dir", action="append", default=[], help="site folder to add (repeatable)")
    a = p.parse_args(argv)
    import site
    here = os.path.dirname(os.path.abspath(__file__))
    sys.path[:] = [d for d in sys.path if os.path.abspath(d or os.curdir) != here]
    for d in a.site_dir:
        site.addsitedir(d)
    for d in reversed(a.sys_path):
        sys.path.insert(0, d)
    os.makedirs(a.out, exist_ok=True)
    result: dict = {}
    try:
        res = run_inference(a.clip, a.frame, a.model, a.reference, a.path)
        _write_rgb(os.path.join(a.out, "sr.exr"), res["sr"])
        _write_rgb(os.path.join(a.out, "bilinear.exr"), res["bilinear"])
        if "reference" in res:
            _write_rgb(os.path.join(a.out, "reference.exr"), res["reference"])
        result = {"ok": True, "ms": res["ms"], "warmup_ms": res["warmup_ms"], "repeats": res["repeats"],
                  "runtime": res["runtime"], "psnr": res.get("psnr"), "metric": res.get("metric", ""),
                  "size": [int(res["sr"].shape[1]), int(res["sr"].shape[0])], "inference": res.get("inference")}
    except Exception as exc:
        traceback.print_exc()
        result = {"ok": False, "error": str(exc).splitlines()[0] if str(exc) else type(exc).__name__}
    with open(os.path.join(a.out, "result.json"), "w") as f:
        json.dump(result, f)
    return 0 if result["ok"] else 2


if __name__ == "__main__":
    sys.exit(main())
