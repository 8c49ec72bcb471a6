"""``InferenceModel``: a model ready for inference and what inference keeps beside it (torch), instead of
attributes bolted onto the ``nn.Module``. ``training.inference.load_model`` returns one and
``training.fastpath.prepare_inference`` fills in its fast-path settings.
"""
from __future__ import annotations

import torch


class InferenceModel:
    """``module``: the model (an ``SRModel``); ``spec``: the name or checkpoint it came from; ``demod_eps``: the floor
    of F_beta its demodulated inputs use; ``config``: the checkpoint's ``TrainConfig`` (None for a non-learned model);
    ``n_params``: its parameter count; ``inference``: the fast-path settings of ``prepare_inference`` (dtype,
    channels_last, compiled module, precision, ...; empty until prepared); ``clip_state``: a recurrent model's state
    between ``upscale_frame`` calls (``training.recurrent.ClipState``). Every other attribute is the module's, read
    and written through, so the object is used like the module (``to`` and ``eval`` return the wrapper)."""

    OWN = ("module", "spec", "demod_eps", "config", "n_params", "inference", "clip_state")

    def __init__(self, module: torch.nn.Module, spec: str | None = None, demod_eps: float = 0.01, config=None):
        from training.recurrent import ClipState
        object.__setattr__(self, "module", module)
        self.spec = str(spec) if spec is not None else type(module).__name__
        self.demod_eps = float(demod_eps)
        self.config = config
        self.n_params = sum(p.numel() for p in module.parameters())
        self.inference = {}
        self.clip_state = ClipState()

    def __getattr__(self, name):  # only for names that are not the wrapper's own
        if name.startswith("__") or "module" not in self.__dict__:
            raise AttributeError(name)
        return getattr(self.__dict__["module"], name)

    def __setattr__(self, name, value) -> None:
        if name in self.OWN:
            object.__setattr__(self, name, value)
        else:
            setattr(self.module, name, value)

    def __call__(self, *args, **kwargs):
        return self.module(*args, **kwargs)

    def to(self, *args, **kwargs) -> "InferenceModel":
        self.module.to(*args, **kwargs)
        return self

    def cpu(self) -> "InferenceModel":
        return self.to("cpu")

    def eval(self) -> "InferenceModel":
        self.module.eval()
        return self

    def train(self, mode: bool = True) -> "InferenceModel":
        self.module.train(mode)
        return self

    def __repr__(self) -> str:
        return f"InferenceModel({self.spec!r}, {type(self.module).__name__}, {self.n_params} parameters)"


def as_inference(model) -> InferenceModel:
    """``model`` itself when it is an InferenceModel, else a new one around the module."""
    return model if isinstance(model, InferenceModel) else InferenceModel(model)


def module_of(model) -> torch.nn.Module:
    """The ``nn.Module`` of an InferenceModel, or ``model`` itself."""
    return model.module if isinstance(model, InferenceModel) else model
