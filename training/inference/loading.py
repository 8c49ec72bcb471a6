"""Inference API (torch) used by ``blendsr evaluate/upscale``, the benchmark and the Blender add-on.

    model = load_model("demod-bilinear", scale=4)          # a model name (non-learned) or a checkpoint path
    out = upscale_frame(model, clip, frame)                # clip: a Clip, a clip directory or a ClipFrames
    out["sr"], out["bilinear"], out["reference"]           # HR H x W x 3 float32 linear radiance, Linear Rec.709
    out["ms"]                                              # model time of this call, milliseconds

Inputs are read straight from the clip's EXRs (``ClipFrames``), colour buffers converted into the training space
(``gbuffer_export.colour_spaces.TRAINING_SPACE``) like the training cache does: the demodulated irradiance is
computed with the torch mirror of the demodulation (``training.demod``), with the eps the checkpoint was trained
with.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from gbuffer_export.errors import BlendSRError
from gbuffer_export.clip import ClipError, scale_value
from training.config import ModelConfig
from training.inference import frames
from training.data import BATCH_KEYS, FRAME_KEYS, BatchSpec, frame_window
from training.demod import demodulate
from training.inference.model import InferenceModel, module_of
from training.models import MODELS, OPTIONAL_KEYS, build_model
from training.models.base import upsample
from training.inference.frames import lead_in


class ClipFrames(frames.ClipFrames):
    """``training.inference.frames.ClipFrames`` with the derived buffers computed by the torch mirror of the demodulation
    (``training.demod``)."""

    def _demodulate(self, frame: int, level: str) -> tuple[np.ndarray, np.ndarray]:
        def t(a):
            return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))
        rad = t(self._get(frame, f"{level}/radiance"))
        em = t(self._get(frame, f"{level}/emission")) if "emission" in self.clip.buffers else None
        fb = t(self._get(frame, f"{level}/fbeta"))
        fl = t(self._get(frame, f"{level}/flags").astype(np.int64)) if "flags" in self.clip.buffers else None
        irr, fbu = demodulate(rad, em, fb, fl, self.eps)
        return irr.numpy().transpose(1, 2, 0), fbu.numpy().transpose(1, 2, 0)


def load_model(spec: str, scale: int, overrides: list[str] | tuple[str, ...] = (), fast: bool = True
               ) -> InferenceModel:
    """A model in eval mode on the CPU, as an ``InferenceModel``: ``spec`` is a non-learned model name from ``MODELS`` or a checkpoint path.
    ``scale`` must match the checkpoint's, unless the model takes any scale (``SCALES is None``).
    ``overrides`` ('model.KEY=VALUE', TOML values) set the configuration of
    a non-learned model; a checkpoint's is fixed but for its inference options (``_load_checkpoint_model``).
    ``spec`` may end in '?KEY=VALUE&...', the model's own options (``split_spec``), e.g.
    ``pretrained:fusesr?residual_clamp=lr-range``; the model keeps the whole text as its label. The model holds
    ``module``, ``spec``, ``demod_eps``, ``config`` and ``n_params``. With ``fast`` (default) it is prepared for the inference fast path
    (``training.inference.fastpath.prepare_inference``: fast ops, BatchNorm folded, channels-last, fp32; call it again after
    moving the model to set the precision or compile)."""
    scale = scale_value(scale)
    label = str(spec)
    spec, query = split_spec(spec)
    if spec not in MODELS:
        return _load_checkpoint_model(spec, label, scale, [*overrides, *query], fast)
    overrides = [*overrides, *(f"model.{spec}.{q}" for q in query)]
    if MODELS[spec].learned:
        raise BlendSRError(f"model {spec!r} is learned: pass the path of a checkpoint trained with "
                           "'blendsr train', not its name")
    bad = [o for o in overrides if not o.strip().startswith("model.")]
    if bad:
        raise BlendSRError(f"--set {bad[0]!r}: only model.KEY=VALUE applies to a non-learned model")
    if overrides:
        from training.config import load_config
        cfg = load_config(None, [*overrides, f'model.name="{spec}"']).model
        cfg.scale = scale
    else:
        cfg = ModelConfig(name=spec, scale=scale)
    model = InferenceModel(build_model(cfg, scale), label)
    model.eval()
    return _prepared(model, fast)


def _prepared(model: InferenceModel, fast: bool) -> InferenceModel:
    if fast:
        from training.inference.fastpath import prepare_inference
        prepare_inference(model)
    return model


def split_spec(spec) -> tuple[str, list[str]]:
    """'pretrained:fusesr?residual_clamp=lr-range&residual_clamp_margin=0.5' -> ('pretrained:fusesr',
    ['residual_clamp=lr-range', 'residual_clamp_margin=0.5']): the model's own options (its ``[model.NAME]`` table)
    after a '?', '&'-separated; a spec without '?' is returned with no options."""
    spec = str(spec)
    base, sep, query = spec.partition("?")
    items = [q.strip() for q in query.split("&")] if sep else []
    bad = [q for q in items if not q.partition("=")[1] or not q.partition("=")[0].strip()]
    if bad or (sep and not items):
        raise BlendSRError(f"{spec}: expected MODEL?KEY=VALUE[&KEY=VALUE...] after '?', got {query!r}")
    return base, items


def _load_checkpoint_model(spec: str, label: str, scale, overrides: list[str], fast: bool) -> InferenceModel:
    """``load_model`` for a checkpoint (a path or ``pretrained:NAME``). ``overrides`` ('model.NAME.KEY=VALUE' or
    'KEY=VALUE') may set only the options that leave the weights' meaning alone
    (``training.models.options.INFERENCE_OPTIONS``, e.g. ``residual_clamp``); the rest of its configuration is
    fixed."""
    from training.checkpoint import check_weights_fit, inference_weights, load_checkpoint
    from training.config import config_from_checkpoint
    from training.pretrained import resolve
    path = Path(resolve(spec))
    if not path.exists():
        raise FileNotFoundError(f"{spec}: neither a model name ({', '.join(MODELS)}) nor a checkpoint file")
    ck = load_checkpoint(path)
    from training.models import model_class
    data = with_inference_options(ck["config"], overrides, label)
    cfg = config_from_checkpoint(data, source=f"{path} with {', '.join(overrides)}" if overrides else str(path))
    if model_class(cfg.model.name).SCALES is not None and float(ck["scale"]) != float(scale):
        raise BlendSRError(f"{spec}: checkpoint was trained for scale {ck['scale']}, not {scale}")
    module = build_model(cfg.model, scale)
    weights = inference_weights(ck)
    check_weights_fit(path, module, weights, cfg.model.name)  # strict: one line naming the file
    module.load_state_dict(weights)
    model = InferenceModel(module, label, demod_eps=cfg.data.demod_eps, config=cfg)
    model.eval()
    return _prepared(model, fast)


def checked_inference_options(config: dict, overrides: list[str], label: str) -> dict:
    """``with_inference_options`` and the configuration built from the result, so a value or a combination the model
    refuses (``residual_clamp = "lr-guidd"``, a bound without ``residual``) fails now, in one line (ConfigError or
    BlendSRError), not when the weights are loaded hours later; returns the configuration's dict."""
    from training.config import config_from_checkpoint
    data = with_inference_options(config, overrides, label)
    config_from_checkpoint(data, source=f"{label} with {', '.join(overrides)}")
    return data


def with_inference_options(config: dict, overrides: list[str], label: str) -> dict:
    """A copy of a checkpoint's saved configuration with ``overrides`` (``_load_checkpoint_model``) set in its
    ``[model.NAME]`` table; BlendSRError (one line) for any other key."""
    import copy
    from training.config import parse_value
    from training.models.options import INFERENCE_OPTIONS
    if not overrides:
        return config
    data = copy.deepcopy(config)
    model = data.setdefault("model", {})
    name = model.get("name", "")
    for item in overrides:
        key, _, text = item.partition("=")
        parts = [k.strip() for k in key.split(".")]
        if parts[0] == "model" and len(parts) == 3 and parts[1] == name:
            parts = parts[2:]
        if len(parts) != 1 or parts[0] not in INFERENCE_OPTIONS:
            raise BlendSRError(f"{label}: {item.strip()!r}: a checkpoint's configuration is fixed except its "
                               f"inference options model.{name}.{{{', '.join(INFERENCE_OPTIONS)}}}")
        table = model.setdefault(name, {})
        if not isinstance(table, dict):
            raise BlendSRError(f"{label}: the checkpoint's [model.{name}] is not a table")
        table[parts[0]] = parse_value(text.strip())
    return data


def missing_keys(model: InferenceModel, source) -> list[str]:
    """The inputs of ``model`` that ``source`` (a ``ClipFrames``) cannot provide (optional keys aside): a model
    such a clip cannot run."""
    skip = set(FRAME_KEYS) | set(BATCH_KEYS) | set(OPTIONAL_KEYS)
    return [k for k in model.module.needs() if k not in skip and not source.has(k)]


def model_inputs(model, source, frame: int, with_reference: bool = True) -> dict[str, np.ndarray]:
    """Full-frame numpy inputs (1, T, C, H, W) of ``model`` (an ``InferenceModel`` or a module) for ``frame`` plus
    'lr/radiance' and, when present, 'hr/radiance' (the reference) and 'hr/motion'/'hr/flags' for metrics."""
    targets = ["lr/radiance"]
    if with_reference:
        targets += [k for k in ("hr/radiance", "hr/motion", "hr/flags") if source.has(k)]
    return frame_window(source, frame, BatchSpec.for_model(module_of(model), targets=tuple(targets)))


def run_model(model: InferenceModel, inputs: dict[str, np.ndarray], amp: torch.dtype | None = None
              ) -> tuple[np.ndarray, float]:
    """(SR H x W x 3 float32, milliseconds of the forward pass, synchronised on GPU): ``model.run``. ``amp``
    overrides the precision set by ``fastpath.prepare_inference``."""
    return model.run(inputs, amp)


def run_frame(model: InferenceModel, source: "ClipFrames", frame: int, key: str | None = None,
              amp: torch.dtype | None = None) -> tuple[np.ndarray, float, dict]:
    """(SR, ms, inputs) of ``frame`` of ``source``. A recurrent model continues its state when the previous call
    under the same ``key`` (default: the clip's path) was the previous frame, else first runs the frames of
    ``recurrent.lead_in`` from the clip's start (untimed, unscored)."""
    key = str(source.clip_path) if key is None else key
    inputs = model_inputs(model, source, int(frame))
    if model.recurrent and not model.follows(key, frame):
        model.reset()
        for g in lead_in(source.frames, frame):
            model.step(model_inputs(model, source, g, False), (key, g), amp)
    sr, ms = model.step(inputs, (key, int(frame)), amp)
    return sr, ms, inputs


def upscale_frame(model: InferenceModel, clip, frame: int) -> dict:
    """Upscale one frame of ``clip`` (a Clip, a clip path or a ClipFrames) with ``model``. A recurrent model keeps
    its state between calls (``run_frame``): frames asked in order carry it; another frame is reached by running
    the clip from its start. Returns ``sr`` and ``bilinear`` (HR H x W x 3 float32 linear, jitter-compensated like
    the ``bilinear`` model), ``ms`` (model milliseconds) and ``reference`` (hr/radiance, when the clip has it)."""
    source = clip if isinstance(clip, ClipFrames) else ClipFrames(clip, eps=model.demod_eps)
    module = model.module
    if module.SCALES is not None and source.scale != module.scale:
        raise ClipError(f"{source.clip_path}: clip scale {source.scale} but the model upscales by {module.scale}")
    module.follow_reference_filter(source.clip.manifest)
    sr, ms, inputs = run_frame(model, source, int(frame))
    lr = torch.from_numpy(inputs["lr/radiance"][:, -1])
    bil = upsample(lr, source.scale, "bilinear", torch.from_numpy(source.jitter(int(frame)))[None])
    out = {"sr": np.ascontiguousarray(sr, dtype=np.float32),
           "bilinear": np.ascontiguousarray(bil[0].permute(1, 2, 0).numpy(), dtype=np.float32), "ms": float(ms)}
    if "hr/radiance" in inputs:
        out["reference"] = np.ascontiguousarray(inputs["hr/radiance"][0, -1].transpose(1, 2, 0), dtype=np.float32)
    return out


__all__ = ["load_model", "upscale_frame", "run_frame", "missing_keys", "ClipFrames", "model_inputs", "run_model",
           "InferenceModel"]
