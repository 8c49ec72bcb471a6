"""``InferenceModel``: a model ready for inference and what inference keeps beside it (torch), instead of
attributes bolted onto the ``nn.Module``. ``training.inference.loading.load_model`` returns one,
``training.inference.fastpath.prepare_inference`` fills in its fast-path settings, and ``evaluate``, ``upscale``, ``export``,
the benches and the add-on preview take one.

It is a plain object: the module's own attributes are read on ``model.module`` (``model.module.scale``,
``model.module.needs()``). It owns a recurrent model's state along a clip (``step``), so callers never hold it.
"""
from __future__ import annotations

import time

import numpy as np
import torch


class ClipState:
    """The state of a recurrent model along a clip: ``get(clip, frame)`` is the state to use for ``frame`` (None
    at a clip's first frame, after a gap in the frame numbers, or on another clip); ``put`` stores the state after
    it."""

    def __init__(self):
        self.key = None
        self.state = None

    def follows(self, clip, frame: int) -> bool:
        """Whether the stored state is the one after frame ``frame - 1`` of ``clip``."""
        return self.key is not None and self.key == (str(clip), int(frame) - 1)

    def get(self, clip, frame: int):
        return self.state if self.follows(clip, frame) else None

    def put(self, clip, frame: int, state) -> None:
        self.key = (str(clip), int(frame))
        self.state = state

    def reset(self) -> None:
        self.key = None
        self.state = None


class InferenceModel:
    """``module``: the model (an ``SRModel``), in eval mode; ``spec``: the name or checkpoint it came from;
    ``demod_eps``: the floor of F_beta its demodulated inputs use (the checkpoint's ``data.demod_eps``; default
    ``DataConfig``'s);
    ``config``: the checkpoint's ``TrainConfig`` (None for a non-learned model); ``n_params``: its parameter count;
    ``settings``: the fast-path settings of ``prepare_inference`` (dtype, channels_last, compiled module, precision,
    ...; empty until prepared); ``device``: where it runs. ``step`` runs one frame and, for a recurrent model, carries
    the state from the previous frame of the same clip."""

    def __init__(self, module: torch.nn.Module, spec: str | None = None, demod_eps: float | None = None,
                 config=None):
        from training.config import DataConfig  # torch-free; its table holds the default eps
        self.module = module
        self.spec = str(spec) if spec is not None else type(module).__name__
        self.demod_eps = float(DataConfig.demod_eps if demod_eps is None else demod_eps)
        self.config = config
        self.n_params = sum(p.numel() for p in module.parameters())
        self.settings: dict = {}
        self.state = ClipState()
        self._device = torch.device("cpu")

    @property
    def recurrent(self) -> bool:
        return bool(getattr(self.module, "recurrent", False))

    @property
    def device(self) -> torch.device:
        """The device of the module's tensors; for a module without any, the one it was last moved to."""
        for t in list(self.module.parameters()) + list(self.module.buffers()):
            return t.device
        return self._device

    def to(self, device) -> "InferenceModel":
        self._device = torch.device(device)
        self.module.to(self._device)
        return self

    def eval(self) -> "InferenceModel":
        self.module.eval()
        return self

    def forward(self, batch: dict, amp: torch.dtype | None = None) -> torch.Tensor:
        """SR of ``batch`` (tensors on the device) with the fast-path settings of ``prepare_inference``
        (``training.inference.fastpath``): channels-last inputs, the compiled module or one CUDA graph per frame, autocast to
        the prepared dtype; ``amp`` overrides the prepared dtype when given. Under ``path="auto"`` the first call
        chooses the path (``fastpath.AutoPath``)."""
        auto = self.settings.get("auto")
        if hasattr(auto, "check"):
            return auto.check(lambda: self._forward(batch, amp))
        return self._forward(batch, amp)

    def _forward(self, batch: dict, amp: torch.dtype | None) -> torch.Tensor:
        from training.device import autocast
        dtype = amp if amp is not None else self.settings.get("dtype")
        if self.settings.get("channels_last"):
            batch = channels_last_batch(batch, self.settings.get("channels_last_levels", ("lr", "hr")))
        fn = self.settings.get("compiled")
        fn = self.module if fn is None else fn

        def call(b):
            with autocast(_device(b), dtype):
                return fn(b)
        if self.settings.get("frame_graph"):
            return self._graph("forward", call)(host_scale(batch))
        return call(batch)

    def _on_device(self, arrays: dict[str, np.ndarray]) -> dict:
        """Tensors of ``arrays`` on the device; ``scale`` stays on the host (models read it there: ``host_scale``)."""
        return {k: torch.from_numpy(v) if k == "scale" else torch.from_numpy(v).to(self.device)
                for k, v in arrays.items()}

    def _graph(self, name: str, fn):
        """The ``FrameGraph`` (one CUDA graph per frame and input layout) of ``fn`` kept under ``name``."""
        from training.inference.frame_graph import FrameGraph
        graphs = self.settings.setdefault("graphs", {})
        if name not in graphs:  # a clip's pixel filter (follow_reference_filter) is baked into a capture: in the key
            graphs[name] = FrameGraph(fn, baked=lambda: getattr(self.module, "remod_taps", None))
        return graphs[name]

    def run(self, inputs: dict[str, np.ndarray], amp: torch.dtype | None = None) -> tuple[np.ndarray, float]:
        """(SR H x W x 3 float32, ms) of the whole input window (numpy (1, T, C, H, W)), no state: the forward pass
        timed with the inputs on the device (GPU synchronised). ``amp`` overrides the prepared precision."""
        from training.data import BATCH_KEYS
        needs = set(self.module.needs()) | set(BATCH_KEYS)
        batch = self._on_device({k: v for k, v in inputs.items() if k in needs})
        sr, ms = self._timed(lambda: self.forward(batch, amp))
        return _image(sr), ms

    def step(self, inputs: dict[str, np.ndarray], at: tuple | None = None,
             amp: torch.dtype | None = None) -> tuple[np.ndarray, float]:
        """(SR H x W x 3 float32, ms) of the current frame of ``inputs``. A recurrent model runs one step
        (``module.step``) from the state this object holds when ``at`` = (clip, frame) follows the last stored
        step, else from none, and stores the new state under ``at`` (``at`` None: nothing kept, e.g. warm-up
        runs). A feed-forward model is ``run``."""
        if not self.recurrent:
            return self.run(inputs, amp)
        needs = set(self.module.needs())
        batch = self._on_device({k: v[:, -1:] if v.ndim > 1 else v for k, v in inputs.items()
                                 if k in needs or k == "scale"})  # 'scale' (B,): per batch element, no time axis
        state = self.state.get(*at) if at is not None else None
        from training.device import autocast

        def call(b, st):
            with autocast(self.device, amp if amp is not None else self.settings.get("dtype")):
                return self.module.step(b, st)

        def one():
            if self.settings.get("frame_graph"):
                return self._graph("step", call)(host_scale(batch), state)
            return call(batch, state)
        auto = self.settings.get("auto")
        if hasattr(auto, "check"):
            (sr, new), ms = self._timed(lambda: auto.check(one, pick=lambda r: r[0]))
        else:
            (sr, new), ms = self._timed(one)
        if at is not None:
            self.state.put(*at, new)
        return _image(sr), ms

    def follows(self, clip, frame: int) -> bool:
        """Whether a recurrent model's stored state is the one after frame ``frame - 1`` of ``clip``."""
        return self.state.follows(clip, frame)

    def reset(self) -> None:
        """Forget the recurrent state."""
        self.state.reset()

    def _timed(self, fn):
        dev = self.device
        with torch.inference_mode():
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
            t0 = time.perf_counter()
            out = fn()
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
            return out, 1000 * (time.perf_counter() - t0)

    def __repr__(self) -> str:
        return f"InferenceModel({self.spec!r}, {type(self.module).__name__}, {self.n_params} parameters)"


def channels_last_batch(batch: dict, levels: tuple[str, ...] = ("lr", "hr")) -> dict:
    """Image tensors (B, T, C, H, W) of the ``levels`` ('lr/...', 'hr/...' keys) re-laid out so that every frame
    (B, C, H, W) is channels-last; others as is."""
    out = {}
    for k, v in batch.items():
        if v.dim() == 5 and v.shape[2] > 1 and v.stride(2) != 1 and k.split("/")[0] in levels:
            v = v.permute(0, 1, 3, 4, 2).contiguous().permute(0, 1, 4, 2, 3)
        out[k] = v
    return out


def _device(batch: dict) -> torch.device:
    """The device of ``batch``: its first CUDA tensor's, else its first tensor's, else the CPU (``scale`` is a host
    value)."""
    devices = [v.device for v in batch.values() if torch.is_tensor(v)]
    return next((d for d in devices if d.type == "cuda"), devices[0] if devices else torch.device("cpu"))


def host_scale(batch: dict) -> dict:
    """``batch`` with ``scale`` on the CPU, for one CUDA graph per frame (``FrameGraph``): models read the factor on the
    host (``ModelBase.batch_scale``), which a graph capture does not allow on a CUDA tensor; on the CPU it is a host
    value, keyed by value. ``run`` and ``step`` keep it there from the start; a batch given on the device (``bench
    models``) pays one copy, which waits for the queued work."""
    s = batch.get("scale")
    return {**batch, "scale": s.cpu()} if torch.is_tensor(s) and s.is_cuda else batch


def _image(sr: torch.Tensor) -> np.ndarray:
    """The first image of an SR batch as H x W x 3 float32 numpy."""
    return sr[0].float().permute(1, 2, 0).cpu().numpy()


def as_inference(model) -> InferenceModel:
    """``model`` itself when it is an InferenceModel, else a new one around the module."""
    return model if isinstance(model, InferenceModel) else InferenceModel(model)


def module_of(model) -> torch.nn.Module:
    """The ``nn.Module`` of an InferenceModel, or ``model`` itself."""
    return model.module if isinstance(model, InferenceModel) else model
