"""ONNX export of a model and a check of onnxruntime against torch (torch, onnx, onnxruntime).

The exported graph takes the model's inputs as separate tensors in the order of ``model.needs()`` (each
(B, T, C, H, W), 'depth_ref' (B, T), 'lr_jitter' (B, T, 2)) with dynamic batch, height and width, and returns SR (B, 3, H_hr, W_hr) linear
radiance. A JSON sidecar ``OUT.onnx.json`` lists the inputs, their shapes and the scale. An arbitrary-scale model
(``SCALES = None``: ``fourier-sr``) has one more input, ``scale`` (B,) float32, last: the graph serves any scale with
HR size = LR size x scale.

A recurrent model (``training.recurrent``) is exported as one step with its state explicit: inputs are the
current frame's tensors (T = 1), then ``state_0`` .. ``state_N`` (the model's ``state_shapes``) and ``reset`` (B,)
(1 at a clip's first frame: the state inputs are then ignored, pass zeros); outputs are ``sr`` and
``state_out_0`` .. ``state_out_N``, fed back as the next frame's state. The check runs 3 consecutive frames through
torch (state carried) and onnxruntime (state fed back) and compares every frame. RDG pads the LR frame to a
multiple of 4 with amounts fixed at export: the graph serves LR sizes with the example's remainders modulo 4
(sidecar ``lr_size_mod4``). Uses the TorchScript-based
exporter (``dynamo=False``): the dynamo exporter needs onnxscript, which is not a dependency; the plan to move to it
is in docs/evaluation.md ("torch versions and the ONNX exporter"). Only the legacy exporter's own deprecation
warnings, its constant-folding notes and the tracer's warnings (Python values frozen into the graph: the check
against onnxruntime below catches what matters) are hidden; anything else is shown.
"""
from __future__ import annotations

import contextlib
import json
import warnings
from pathlib import Path

import numpy as np
import torch

from gbuffer_export.errors import BlendSRError
from gbuffer_export.conventions import BUFFERS
from training.data import FRAME_KEYS, BatchSpec, frame_window
from training.inference.model import InferenceModel, as_inference


@contextlib.contextmanager
def _legacy_exporter_warnings():
    """Hide the TorchScript exporter's deprecation notices ('legacy TorchScript-based ONNX export', 'The feature
    will be removed'), torch.jit.TracerWarning and its constant-folding notes; other warnings pass."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r".*(legacy TorchScript-based ONNX export|The feature will be "
                                                  r"removed)", category=DeprecationWarning)
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        warnings.filterwarnings("ignore", message=r"Constant folding - ", category=UserWarning)  # an optimiser note
        yield


def scale_keys(module) -> list[str]:
    """``["scale"]`` for an arbitrary-scale model (its graph takes the scale as an input), else []."""
    return ["scale"] if module.SCALES is None else []


def dynamic_axes_of(key: str) -> dict:
    """The dynamic axes of an exported input: batch for per-frame values and the scale, batch and size for images."""
    if key in FRAME_KEYS or key == "scale":
        return {0: "batch"}
    level = key.split("/")[0]
    return {0: "batch", 3: f"{level}_height", 4: f"{level}_width"}


class PositionalWrapper(torch.nn.Module):
    """Calls ``model(dict(zip(keys, tensors)))``."""

    def __init__(self, model, keys):
        super().__init__()
        self.model = model
        self.keys = list(keys)

    def forward(self, *tensors):
        return self.model(dict(zip(self.keys, tensors)))


def example_inputs(model, clip: str | None, hr_size: tuple[int, int] | None,
                   seed: int = 0) -> dict[str, np.ndarray]:
    """Inputs of ``model`` (an ``InferenceModel`` or a module) for one frame of ``clip`` (its last frame) or random
    plausible values."""
    model = as_inference(model)
    module = model.module
    keys = list(module.needs())
    if clip:
        from training.inference.loading import ClipFrames
        src = ClipFrames(clip, eps=model.demod_eps)
        spec = BatchSpec.for_model(module, targets=())
        inputs = frame_window(src, src.frames[-1], spec)
        for k in keys:  # optional keys absent from the clip
            if k not in inputs:
                ref = inputs[next(x for x in inputs if x.startswith(k.split("/")[0] + "/"))]
                inputs[k] = np.zeros(ref.shape[:2] + (3,) + ref.shape[3:], np.float32)
        out = {k: inputs[k] for k in keys}
        for k in scale_keys(module):
            out[k] = np.array([src.scale], np.float32)
        return out
    w, h = hr_size or (128, 72)
    s = module.scale
    if (w / s) % 1 or (h / s) % 1:
        raise BlendSRError(f"--hr-size {w}x{h} is not divisible by the scale {s}")
    rng = np.random.default_rng(seed)
    t = module.window
    out = {}
    for k in keys:
        if k == "depth_ref":
            out[k] = np.full((1, t), 5.0, np.float32)
            continue
        if k == "lr_jitter":
            out[k] = (rng.random((1, t, 2), dtype=np.float32) - 0.5).astype(np.float32)
            continue
        level, name = k.split("/")
        hh, ww = (h, w) if level == "hr" else (round(h / s), round(w / s))
        n = t if level == "lr" else 1
        if name == "flags":  # bits as the loaders give them (float32): none, BACKGROUND, TRANSMISSION, with ALPHA
            out[k] = rng.choice(np.array([0, 1, 2048, 2064], np.float32), size=(1, n, 1, hh, ww))
            continue
        c = len(BUFFERS[name].channels) if name in BUFFERS else 3  # derived keys (irradiance, ...): RGB
        a = rng.random((1, n, c, hh, ww), dtype=np.float32)
        if name == "depth":
            a = 1.0 + 10.0 * a
            a[..., : hh // 4, :] = np.inf  # a band of background
        elif name in ("motion", "motion_next"):
            a = 4.0 * (a - 0.5)
        elif name == "normal":
            a = a - 0.5
            a /= np.linalg.norm(a, axis=2, keepdims=True) + 1e-6
        out[k] = a.astype(np.float32)
    for k in scale_keys(module):  # last: the graph's inputs are the model's keys, then the scale
        out[k] = np.array([s], np.float32)
    return out


class StepExport(torch.nn.Module):
    """One step of a recurrent model: ``forward(*inputs, *state, reset) -> (sr, *state)``."""

    def __init__(self, model, keys, n_state: int):
        super().__init__()
        self.model = model
        self.keys = list(keys)
        self.n_state = n_state

    def forward(self, *tensors):
        k, n = len(self.keys), self.n_state
        batch = dict(zip(self.keys, tensors[:k]))
        sr, state = self.model.step(batch, list(tensors[k:k + n]), tensors[k + n])
        return (sr, *state)


def recurrent_example_frames(model: InferenceModel, clip: str | None, hr_size,
                             frames: int = 3) -> list[dict[str, np.ndarray]]:
    """``frames`` consecutive frames of inputs: the last ones of ``clip``, or random ones (moving content)."""
    module = model.module
    if clip:
        from training.inference.loading import ClipFrames
        src = ClipFrames(clip, eps=model.demod_eps)
        if len(src.frames) < frames:
            raise BlendSRError(f"{clip}: the check needs {frames} consecutive frames, the clip has {len(src.frames)}")
        spec = BatchSpec.for_model(module, targets=())
        out = []
        for f in src.frames[-frames:]:
            inputs = frame_window(src, f, spec)
            for k in module.needs():
                if k not in inputs:
                    ref = inputs[next(x for x in inputs if x.startswith(k.split("/")[0] + "/"))]
                    inputs[k] = np.zeros(ref.shape[:2] + (3,) + ref.shape[3:], np.float32)
            out.append({**{k: inputs[k] for k in module.needs()},
                        **{k: np.array([src.scale], np.float32) for k in scale_keys(module)}})
        return out
    return [example_inputs(model, None, hr_size, seed=i) for i in range(frames)]


def graph_dtypes(inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``inputs`` as the ONNX graph takes them: the flags (bits, all below 2^16; float32 from the loaders, uint32 in
    a clip's cache) as int32, whatever their source, since the exporter takes no uint32 and bits are integers."""
    return {k: v.astype(np.int32) if k.endswith("/flags") else v for k, v in inputs.items()}


def state_size_rules(module) -> list[list[str]] | None:
    """Per state, the ``STATE_SIZES`` names of its height and width ([] for a per-frame vector), found by asking
    ``module.state_shapes`` at an LR size where every rule differs (13 x 22); None when one fits no rule."""
    import inspect

    from training.inference.onnx_infer import STATE_SIZES
    s = module.scale
    lr = (13, 22)
    hr = (13 * s, 22 * s)
    takes_hr = next(iter(inspect.signature(module.state_shapes).parameters)).startswith("hr")
    rules = []
    for shape in module.state_shapes(*(hr if takes_hr else lr)):
        if len(shape) == 2:
            rules.append([])
            continue
        axes = [next((k for k, f in STATE_SIZES.items() if f(n, h) == got), None)
                for n, h, got in zip(lr, hr, shape[2:])]
        if None in axes:
            return None
        rules.append(axes)
    return rules


def runtime_fields(model: InferenceModel, keys, lr_mod4=None) -> dict:
    """What a runner without torch needs beside the graph (``training.inference.onnx_infer``): the batch keys in the graph's
    input order, the LR window, the demodulation eps, whether the graph takes any scale and the ground-truth pixel
    filter a ``remod_filter = "REFERENCE"`` model was exported with (None for any other) and, for RDG (its padding is
    fixed at export), the LR size's remainders modulo 4 (H, W) the graph serves (None: any LR size)."""
    from training.models.rdg import RDG
    module = model.module
    ref = None
    if getattr(module.config, "remod_filter", "NONE") == "REFERENCE":
        from gbuffer_export.pixel_filter import HR_REFERENCE_FILTER
        ref = list(HR_REFERENCE_FILTER)
    return {"keys": list(keys), "window": int(module.window), "demod_eps": float(model.demod_eps),
            "any_scale": module.SCALES is None, "remod_reference": ref,
            "lr_mod4": lr_mod4 if isinstance(module, RDG) else None,
            "state_sizes": state_size_rules(module) if getattr(module, "recurrent", False) else None}


def export_recurrent(model: InferenceModel, path: Path, clip: str | None, hr_size, opset: int) -> dict:
    import onnx
    import onnxruntime as ort
    frames = [graph_dtypes(f) for f in recurrent_example_frames(model, clip, hr_size)]
    keys = list(frames[0])
    names = [k.replace("/", "_") for k in keys]
    refs, states = [], []
    with torch.no_grad():
        state = None
        for inp in frames:
            sr, state = model.module.step({k: torch.from_numpy(v) for k, v in inp.items()}, state)
            refs.append(sr.numpy())
            states.append(state)
    n = len(states[0])
    s_names = [f"state_{i}" for i in range(n)]
    o_names = [f"state_out_{i}" for i in range(n)]
    wrapper = StepExport(model.module, keys, n).eval()
    example = tuple(torch.from_numpy(frames[1][k]) for k in keys) + tuple(states[0]) + (torch.zeros(1),)
    dyn = {nm: dynamic_axes_of(k) for k, nm in zip(keys, names)}
    for i, st in enumerate(states[0]):
        axes = {0: "batch"} if st.dim() == 2 else {0: "batch", 2: f"state_{i}_height", 3: f"state_{i}_width"}
        dyn[s_names[i]] = axes
        dyn[o_names[i]] = axes
    dyn["reset"] = {0: "batch"}
    dyn["sr"] = {0: "batch", 2: "hr_height", 3: "hr_width"}
    with _legacy_exporter_warnings():
        torch.onnx.export(wrapper, example, str(path), input_names=names + s_names + ["reset"],
                          output_names=["sr"] + o_names, dynamic_axes=dyn, opset_version=opset, dynamo=False)
    onnx.checker.check_model(onnx.load(str(path)))
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    feed_state = [np.zeros(tuple(s.shape), np.float32) for s in states[0]]
    reset = np.ones(1, np.float32)
    diffs = []
    for inp, ref in zip(frames, refs):
        outs = sess.run(["sr"] + o_names, {**{nm: inp[k] for k, nm in zip(keys, names)},
                                          **dict(zip(s_names, feed_state)), "reset": reset})
        diffs.append(float(np.max(np.abs(outs[0] - ref))))
        feed_state, reset = outs[1:], np.zeros(1, np.float32)
    diff = max(diffs)
    scale_ref = max(float(np.max(np.abs(r))) for r in refs) or 1.0
    h, w = frames[0][keys[0]].shape[-2:]
    return {"onnx": str(path), "model": model.spec, "scale": model.module.scale,
            "opset": opset, "recurrent": True, "inputs": {nm: list(frames[0][k].shape) for k, nm in zip(keys, names)},
            "state": {nm: list(s.shape) for nm, s in zip(s_names, states[0])}, "lr_size_mod4": [h % 4, w % 4],
            "output_shape": list(refs[0].shape), "frames_checked": len(frames), "max_abs_diff_per_frame": diffs,
            "max_abs_diff": diff, "max_rel_diff": diff / scale_ref, "match": bool(diff <= 1e-4 * scale_ref + 1e-5),
            **runtime_fields(model, keys, [h % 4, w % 4])}


def export_onnx(model: InferenceModel, path, clip: str | None = None, hr_size=None, opset: int = 17) -> dict:
    """Export ``model`` (moved to the CPU) to ``path`` and compare onnxruntime with torch on the example inputs.
    Returns a report with ``max_abs_diff``, ``max_rel_diff`` (relative to the largest output magnitude) and
    ``match``."""
    import onnx
    import onnxruntime as ort
    model = model.to("cpu").eval()
    if model.recurrent:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        report = export_recurrent(model, path, clip, hr_size, opset)
        path.with_suffix(path.suffix + ".json").write_text(json.dumps(report, indent=1) + "\n")
        return report
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    inputs = graph_dtypes(example_inputs(model, clip, hr_size))
    keys = list(inputs)
    names = [k.replace("/", "_") for k in keys]
    wrapper = PositionalWrapper(model.module, keys).eval()
    tensors = tuple(torch.from_numpy(inputs[k]) for k in keys)
    dyn = {n: dynamic_axes_of(k) for k, n in zip(keys, names)}
    dyn["sr"] = {0: "batch", 2: "hr_height", 3: "hr_width"}
    with torch.no_grad():
        ref = wrapper(*tensors).numpy()
    with _legacy_exporter_warnings():
        torch.onnx.export(wrapper, tensors, str(path), input_names=names, output_names=["sr"],
                          dynamic_axes=dyn, opset_version=opset, dynamo=False)
    onnx.checker.check_model(onnx.load(str(path)))
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    graph_inputs = {i.name for i in sess.get_inputs()}  # the exporter drops inputs the graph never reads
    keys, names = zip(*[(k, n) for k, n in zip(keys, names) if n in graph_inputs])
    got = sess.run(["sr"], {n: inputs[k] for k, n in zip(keys, names)})[0]
    diff = float(np.max(np.abs(got - ref)))
    scale_ref = float(np.max(np.abs(ref))) or 1.0
    report = {"onnx": str(path), "model": model.spec, "scale": model.module.scale,
              "opset": opset, "inputs": {n: list(inputs[k].shape) for k, n in zip(keys, names)},
              "output_shape": list(ref.shape), "max_abs_diff": diff, "max_rel_diff": diff / scale_ref,
              "match": bool(diff <= 1e-4 * scale_ref + 1e-5), **runtime_fields(model, keys)}
    path.with_suffix(path.suffix + ".json").write_text(json.dumps(report, indent=1) + "\n")
    return report
