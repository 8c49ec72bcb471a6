"""ONNX export of a model and a check of onnxruntime against torch (torch, onnx, onnxruntime).

The exported graph takes the model's inputs as separate tensors in the order of ``model.needs()`` (each
(B, T, C, H, W), 'depth_ref' (B, T), 'lr_jitter' (B, T, 2)) with dynamic batch, height and width, and returns SR (B, 3, H_hr, W_hr) linear
radiance. A JSON sidecar ``OUT.onnx.json`` lists the inputs, their shapes and the scale. Uses the TorchScript-based
exporter (``dynamo=False``): the dynamo exporter needs onnxscript, which is not a dependency.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import torch

from training.data import FRAME_KEYS, BatchSpec, frame_window


class PositionalWrapper(torch.nn.Module):
    """Calls ``model(dict(zip(keys, tensors)))``."""

    def __init__(self, model, keys):
        super().__init__()
        self.model = model
        self.keys = list(keys)

    def forward(self, *tensors):
        return self.model(dict(zip(self.keys, tensors)))


def example_inputs(model, clip: str | None, hr_size: tuple[int, int] | None, seed: int = 0) -> dict[str, np.ndarray]:
    """Inputs of the model for one frame of ``clip`` (its last frame) or random plausible values."""
    keys = list(model.needs())
    if clip:
        from training.inference import ClipFrames
        src = ClipFrames(clip, eps=getattr(model, "demod_eps", 0.01))
        spec = BatchSpec.for_model(model, targets=())
        inputs = frame_window(src, src.frames[-1], spec)
        for k in keys:  # optional keys absent from the clip
            if k not in inputs:
                ref = inputs[next(x for x in inputs if x.startswith(k.split("/")[0] + "/"))]
                inputs[k] = np.zeros(ref.shape[:2] + (3,) + ref.shape[3:], np.float32)
        return {k: inputs[k] for k in keys}
    w, h = hr_size or (128, 72)
    s = model.scale
    if w % s or h % s:
        raise ValueError(f"--hr-size {w}x{h} is not divisible by the scale {s}")
    rng = np.random.default_rng(seed)
    t = model.window
    out = {}
    for k in keys:
        if k == "depth_ref":
            out[k] = np.full((1, t), 5.0, np.float32)
            continue
        if k == "lr_jitter":
            out[k] = (rng.random((1, t, 2), dtype=np.float32) - 0.5).astype(np.float32)
            continue
        level, name = k.split("/")
        hh, ww = (h, w) if level == "hr" else (h // s, w // s)
        n = t if level == "lr" else 1
        c = {"depth": 1, "motion": 2}.get(name, 3)
        a = rng.random((1, n, c, hh, ww), dtype=np.float32)
        if name == "depth":
            a = 1.0 + 10.0 * a
            a[..., : hh // 4, :] = np.inf  # a band of background
        elif name == "motion":
            a = 4.0 * (a - 0.5)
        elif name == "normal":
            a = a - 0.5
            a /= np.linalg.norm(a, axis=2, keepdims=True) + 1e-6
        out[k] = a.astype(np.float32)
    return out


def export_onnx(model, path, clip: str | None = None, hr_size=None, opset: int = 17) -> dict:
    """Export ``model`` to ``path`` and compare onnxruntime with torch on the example inputs. Returns a report
    with ``max_abs_diff``, ``max_rel_diff`` (relative to the largest output magnitude) and ``match``."""
    import onnx
    import onnxruntime as ort
    model = model.cpu().eval()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    inputs = example_inputs(model, clip, hr_size)
    keys = list(inputs)
    names = [k.replace("/", "_") for k in keys]
    wrapper = PositionalWrapper(model, keys).eval()
    tensors = tuple(torch.from_numpy(inputs[k]) for k in keys)
    dyn = {}
    for k, n in zip(keys, names):
        dyn[n] = {0: "batch"} if k in FRAME_KEYS else {0: "batch", 3: f"{k.split('/')[0]}_height",
                                                        4: f"{k.split('/')[0]}_width"}
    dyn["sr"] = {0: "batch", 2: "hr_height", 3: "hr_width"}
    with torch.no_grad():
        ref = wrapper(*tensors).numpy()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(wrapper, tensors, str(path), input_names=names, output_names=["sr"],
                          dynamic_axes=dyn, opset_version=opset, dynamo=False)
    onnx.checker.check_model(onnx.load(str(path)))
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(["sr"], {n: inputs[k] for k, n in zip(keys, names)})[0]
    diff = float(np.max(np.abs(got - ref)))
    scale_ref = float(np.max(np.abs(ref))) or 1.0
    report = {"onnx": str(path), "model": getattr(model, "spec", type(model).__name__), "scale": model.scale,
              "opset": opset, "inputs": {n: list(inputs[k].shape) for k, n in zip(keys, names)},
              "output_shape": list(ref.shape), "max_abs_diff": diff, "max_rel_diff": diff / scale_ref,
              "match": bool(diff <= 1e-4 * scale_ref + 1e-5)}
    path.with_suffix(path.suffix + ".json").write_text(json.dumps(report, indent=1) + "\n")
    return report
