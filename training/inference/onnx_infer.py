"""Upscaling through ONNX Runtime, without torch: the add-on's preview inside Blender's own Python.

    model = OnnxModel(graphs_dir / graph_name("pretrained:fusesr-l", 4))
    out = upscale_frame(model, clip_dir, frame, bilinear=OnnxModel(graphs_dir / graph_name("bilinear", None)))

The graphs are ``training.inference.export.export_onnx``'s (``blendsr export``; ``python -m blender_addon.build`` exports
every shipped network and non-learned model into the add-on zip) with their JSON sidecar, whose ``keys``,
``window``, ``demod_eps``, ``any_scale`` and ``remod_reference`` say how to feed them. Inputs are read as the torch
path reads them (``training.inference.frames.ClipFrames``, ``training.data.frame_window``); a recurrent graph carries its
state as inputs and outputs (``state_i`` -> ``state_out_i``, ``reset`` 1 at a clip's first frame) and runs the
frames before the asked one from the clip's start, as ``training.inference.loading.run_frame`` does.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from gbuffer_export.clip import ClipError
from gbuffer_export.errors import BlendSRError
from training.data import BatchSpec, frame_window
from training.inference.frames import ClipFrames, lead_in

#: How a recurrent state's height or width follows the frame's LR size n and HR size (names recorded per state by
#: ``training.inference.export.state_size_rules`` in the sidecar's ``state_sizes``).
STATE_SIZES = {"lr": lambda n, hr: n, "hr": lambda n, hr: hr, "pad4": lambda n, hr: -(-n // 4) * 4,
               "pad4/2": lambda n, hr: -(-n // 4) * 2, "pad4/4": lambda n, hr: -(-n // 4)}


def graph_name(spec: str, scale: int | None) -> str:
    """The file name of ``spec``'s graph at ``scale`` (None: a graph that takes any scale): 'pretrained:fusesr-l'
    at 4 -> 'pretrained_fusesr-l_x4.onnx', 'bilinear' -> 'bilinear_xany.onnx'."""
    return f"{spec.replace(':', '_')}_x{'any' if scale is None else int(scale)}.onnx"


def find_graph(graphs_dir: str | Path, spec: str, scale: int) -> Path | None:
    """``spec``'s graph for ``scale`` in ``graphs_dir`` (its fixed-scale graph, else its any-scale one), or None."""
    for name in (graph_name(spec, scale), graph_name(spec, None)):
        p = Path(graphs_dir) / name
        if p.is_file() and p.with_suffix(".onnx.json").is_file():
            return p
    return None


def runtime_version() -> str:
    import onnxruntime as ort
    return f"ONNX Runtime {ort.__version__}"


class OnnxModel:
    """An exported graph in an ONNX Runtime session (CPU), with what its sidecar says about its inputs.
    ``load_ms``: the session's creation time."""

    def __init__(self, path: str | Path, threads: int = 0):
        import onnxruntime as ort
        self.path = Path(path)
        try:
            self.info = json.loads(self.path.with_suffix(".onnx.json").read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise BlendSRError(f"{self.path}.json: cannot read the graph's sidecar ({exc})") from None
        if "keys" not in self.info:
            raise BlendSRError(f"{self.path}.json: no 'keys' (exported before the runner's fields; export it again)")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(threads)
        opts.log_severity_level = 3
        t0 = time.perf_counter()
        self.session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        self.load_ms = 1000.0 * (time.perf_counter() - t0)
        self.keys = list(self.info["keys"])
        self.window = int(self.info["window"])
        self.recurrent = bool(self.info.get("recurrent"))
        self.scale = None if self.info["any_scale"] else self.info["scale"]
        self.demod_eps = float(self.info["demod_eps"])
        self.graph_inputs = {i.name for i in self.session.get_inputs()}
        self.n_state = len(self.info.get("state", {}))

    def needs(self) -> list[str]:
        """The batch keys the graph reads (``BatchSpec.for_model`` reads them as a module's)."""
        return [k for k in self.keys if k != "scale"]

    def check(self, source: ClipFrames) -> None:
        """One-line ClipError when the graph cannot serve ``source``'s clip as the torch model would."""
        if self.scale is not None and float(source.scale) != float(self.scale):
            raise ClipError(f"{source.clip_path}: clip scale {source.scale} but {self.path.name} upscales by "
                            f"{self.scale}")
        ref = self.info.get("remod_reference")
        if ref is not None:
            from gbuffer_export.pixel_filter import reference_filter
            kind, width = reference_filter(source.clip.manifest)
            if (kind, float(width)) != (ref[0], float(ref[1])):
                raise ClipError(f"{source.clip_path}: the ground truth's pixel filter is {kind} {width:g} px but "
                                f"{self.path.name} remodulates through {ref[0]} {float(ref[1]):g} px; use torch")
        mod4 = self.info.get("lr_mod4")
        if mod4 is not None:
            w, h = source.sizes["lr"]
            if [h % 4, w % 4] != list(mod4):
                raise ClipError(f"{source.clip_path}: {self.path.name} serves LR sizes whose height and width are "
                                f"{mod4[0]} and {mod4[1]} modulo 4, not {h}x{w} (HxW); use torch")

    def feed(self, inputs: dict[str, np.ndarray], scale: float) -> dict[str, np.ndarray]:
        """The graph's inputs from numpy batch inputs (flags as int32, a recurrent graph's current frame only)."""
        out = {}
        for k in self.keys:
            name = k.replace("/", "_")
            if name not in self.graph_inputs:
                continue
            if k == "scale":
                v = np.array([scale], np.float32)
            else:
                v = inputs[k]
                if self.recurrent and v.ndim > 1:
                    v = v[:, -1:]
                v = v.astype(np.int32) if k.endswith("/flags") else v.astype(np.float32, copy=False)
            out[name] = np.ascontiguousarray(v)
        return out

    def run(self, inputs: dict[str, np.ndarray], scale: float, state: list | None = None
            ) -> tuple[np.ndarray, list, float]:
        """(SR H x W x 3 float32, the next state ([] for a feed-forward graph), milliseconds of the call)."""
        feed = self.feed(inputs, scale)
        names = ["sr"]
        if self.recurrent:
            if state is None:
                h, w = next(v for k, v in feed.items() if k.startswith("lr_") and v.ndim == 5).shape[-2:]
                state = self.zero_state(h, w, scale)
                reset = np.ones(1, np.float32)
            else:
                reset = np.zeros(1, np.float32)
            feed.update({f"state_{i}": s for i, s in enumerate(state)}, reset=reset)
            names += [f"state_out_{i}" for i in range(self.n_state)]
        t0 = time.perf_counter()
        outs = self.session.run(names, feed)
        ms = 1000.0 * (time.perf_counter() - t0)
        return np.ascontiguousarray(outs[0][0].transpose(1, 2, 0), dtype=np.float32), list(outs[1:]), ms

    def zero_state(self, lr_h: int, lr_w: int, scale: float) -> list[np.ndarray]:
        """A clip's first state (ignored by the graph under ``reset`` = 1): zeros shaped by the sidecar's
        ``state_sizes`` rules (``STATE_SIZES`` in this module) for this LR size."""
        rules = self.info.get("state_sizes")
        if rules is None:
            raise BlendSRError(f"{self.path}.json: no 'state_sizes' (exported before the runner's fields; export it "
                               "again)")
        out = []
        for shape, axes in zip(self.info["state"].values(), rules):
            if not axes:
                out.append(np.zeros(shape, np.float32))
                continue
            hw = [STATE_SIZES[r](n, round(n * scale)) for r, n in zip(axes, (lr_h, lr_w))]
            out.append(np.zeros((1, shape[1], *hw), np.float32))
        return out


def model_inputs(model: OnnxModel, source: ClipFrames, frame: int, targets=()) -> dict[str, np.ndarray]:
    return frame_window(source, frame, BatchSpec.for_model(model, targets=tuple(targets)))


def run_frame(model: OnnxModel, source: ClipFrames, frame: int, targets=()) -> tuple[np.ndarray, float, dict]:
    """(SR, ms, inputs) of ``frame``; a recurrent graph first runs the frames of ``lead_in`` (untimed)."""
    state = None
    if model.recurrent:
        for g in lead_in(source.frames, frame):
            state = model.run(model_inputs(model, source, g), source.scale, state)[1]
    inputs = model_inputs(model, source, frame, targets)
    sr, _, ms = model.run(inputs, source.scale, state)
    return sr, ms, inputs


def upscale_frame(model: OnnxModel, clip, frame: int, bilinear: OnnxModel) -> dict:
    """``training.inference.loading.upscale_frame`` through ONNX Runtime: ``sr`` and ``bilinear`` (the ``bilinear``
    model's any-scale graph), HR H x W x 3 float32 linear, ``ms`` and ``reference`` (hr/radiance, when present)."""
    source = clip if isinstance(clip, ClipFrames) else ClipFrames(clip, eps=model.demod_eps)
    model.check(source)
    targets = [k for k in ("lr/radiance", "hr/radiance") if source.has(k)]
    sr, ms, inputs = run_frame(model, source, int(frame), targets)
    bil = bilinear.run(model_inputs(bilinear, source, int(frame)), source.scale)[0]
    out = {"sr": sr, "bilinear": bil, "ms": float(ms)}
    if "hr/radiance" in inputs:
        out["reference"] = np.ascontiguousarray(inputs["hr/radiance"][0, -1].transpose(1, 2, 0), dtype=np.float32)
    return out


__all__ = ["OnnxModel", "graph_name", "find_graph", "upscale_frame", "run_frame", "runtime_version"]
