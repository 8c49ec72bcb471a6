"""The model table. Every entry is a plain ``nn.Module`` in its own file under ``training/models/``; this module
imports no torch, so the CLI and the config validation can list models cheaply.

Contract (see ``base.SRModel``): ``model(batch) -> SR`` where ``batch`` maps keys such as ``'lr/irradiance'`` to
tensors (B, T, C, H, W) (the last frame is the current one; LR keys hold ``model.history + 1`` frames or more,
HR keys at least the current frame) plus ``'depth_ref'`` (B, T). SR is (B, 3, H_hr, W_hr) linear radiance.

Options: a row's ``options`` is the dataclass of the model's own ``[model.<name>]`` table
(``training.models.options``; ``NoOptions``, the default, for a model without any), built as ``cfg.options``.
A model class takes the shared keys and its options by keyword (``FuseSR(4, width=64)``; ``base.SRModel``);
``build_model`` unpacks a ``ModelConfig`` into them (``model_keys``).
"""
from __future__ import annotations

import copy
import dataclasses
import importlib
from dataclasses import dataclass

from gbuffer_export.errors import BlendSRError
from training.models.options import (DemodJBUOptions, FourierSROptions, FuseSRFastOptions, FuseSRLightOptions,
                                     FuseSROptions, NoOptions, NSRDOptions, NSRROptions, RDGOptions,
                                     RDGSmallOptions)


@dataclass(frozen=True)
class ModelInfo:
    module: str
    cls: str
    learned: bool
    description: str
    options: type = NoOptions  # the dataclass of its [model.<name>] table (training.models.options)


#: Keys a batch may lack; models then use zeros (e.g. a clip rendered without emission).
OPTIONAL_KEYS = ("lr/emission", "hr/emission")

#: name -> where the class lives, whether it trains, what it is.
MODELS: dict[str, ModelInfo] = {
    "bilinear": ModelInfo("training.models.bilinear", "Bilinear", False,
                          "bilinear upsampling of LR radiance (no training)"),
    "bicubic": ModelInfo("training.models.bicubic", "Bicubic", False,
                         "bicubic upsampling of LR radiance, clamped at 0 (no training)"),
    "demod-bilinear": ModelInfo("training.models.demod_bilinear", "DemodBilinear", False,
                                "bilinear upsampling of LR demodulated irradiance, remodulated with HR F_beta "
                                "and HR emission (no training)"),
    "demod-jbu": ModelInfo("training.models.demod_jbu", "DemodJBU", False,
                           "joint bilateral upsampling of LR demodulated irradiance guided by HR depth and normals, "
                           "remodulated with HR F_beta and HR emission (no training)", DemodJBUOptions),
    "fusesr": ModelInfo("training.models.fusesr", "FuseSR", True,
                        "FuseSR H-Net (Zhong et al. 2023): LR encoder + 2 warped history frames, pixel-unshuffled "
                        "HR G-buffers, LR fusion backbone, pixel shuffle, HR F_beta remodulation", FuseSROptions),
    "fusesr-l": ModelInfo("training.models.fusesr_l", "FuseSRLight", True,
                          "FuseSR-l: no history, half-width fusion network of depthwise-separable convolutions",
                          FuseSRLightOptions),
    "rdg": ModelInfo("training.models.rdg", "RDG", True,
                     "RDG (Zhou et al. 2025): recurrent asymmetric U-Net, width 36, LR image with decoupled LR "
                     "G-buffer guidance (normal, BRDF, depth, motion); state = the 3 decoder levels", RDGOptions),
    "rdg-s": ModelInfo("training.models.rdg", "RDGSmall", True, "RDG-s: RDG at width 16", RDGSmallOptions),
    "nsrd": ModelInfo("training.models.nsrd", "NSRD", True,
                      "NSRD (Li et al. 2024): LR demodulated irradiance, 2 warped previous frames with dual-motion-"
                      "vector disocclusion masks, warped previous HR output, ConvLSTM (64) and an RCAB U-Net; HR F_beta "
                      "remodulation", NSRDOptions),
    "fusesr-fast": ModelInfo("training.models.fusesr_fast", "FuseSRFast", True,
                             "FuseSR-fast (the authors' FuseSR_Fast): no history, 32-16-12-12-16 separable encoder, "
                             "unshuffled HR F_beta, 32-wide backbone of 6 inverted residual blocks (68 K params)",
                             FuseSRFastOptions),
    "nsrr": ModelInfo("training.models.nsrr_fec", "NSRR", True,
                      "NSRR (Xiao et al. 2020): LR RGB-D features zero-upsampled at the jittered sample positions, "
                      "4 history frames warped at HR and reweighted, HR U-Net (535 K params)", NSRROptions),
    "nsrr-fec": ModelInfo("training.models.nsrr_fec", "NSRRFEC", True,
                          "NSRR with feature enhancement and caching (Zhong et al. 2023): Y'CbCr features cached "
                          "as the recurrent state (4 HR maps, each warped once per frame), HR G-buffer features",
                          NSRROptions),
    "fourier-sr": ModelInfo("training.models.fourier_sr", "FourierSR", True,
                            "Fourier arbitrary-scale SR (Zhang et al. 2024): one network for any scale; HR G-buffer "
                            "frequencies x LR amplitudes (HFFM), recurrent temporal branch with soft masks (532 K)",
                            FourierSROptions),
}


def model_class(name: str):
    """The class of model ``name`` (imports torch)."""
    try:
        info = MODELS[name]
    except KeyError:
        raise BlendSRError(f"unknown model {name!r}; choose one of {', '.join(MODELS)}") from None
    return getattr(importlib.import_module(info.module), info.cls)


def model_keys(cfg) -> dict:
    """The keyword arguments of model ``cfg.name``'s constructor from a ``ModelConfig``: its shared ``[model]`` keys
    (all but ``name``, ``scale`` and ``options``), then its own options' fields."""
    shared = {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)
              if f.name not in ("name", "scale", "options")}
    own = {f.name: getattr(cfg.options, f.name) for f in dataclasses.fields(cfg.options)}
    return copy.deepcopy({**shared, **own})


def build_model(cfg, scale: float):
    """The model of a ``ModelConfig`` for upscaling factor ``scale``: its class called with the configuration's keys
    (``model_keys``), e.g. ``FuseSR(4, width=128, jitter=True, ...)``."""
    return model_class(cfg.name)(scale, **model_keys(cfg))


__all__ = ["MODELS", "ModelInfo", "OPTIONAL_KEYS", "model_class", "model_keys", "build_model"]
