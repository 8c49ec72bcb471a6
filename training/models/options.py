"""Each model's own options (pure Python, no torch): the ``[model.<name>]`` table of a training configuration.

One dataclass per model, named in its row of ``training.models.MODELS``; the shared ``[model]`` keys (scale,
history, jitter, input transform, remodulation filter, ...) are ``training.config.ModelConfig``'s. A model reads
its options as ``cfg.options`` (``cfg`` the ``ModelConfig`` it is built from). A model without options of its own
uses ``NoOptions`` (the table's default), so it needs no class here.

The classes live here and not beside their ``nn.Module`` because a model's file imports torch, and the configuration
is validated without torch (``blendsr train`` checks its configuration before it imports the trainer).

``validate(where)`` checks ranges and combinations (``where`` is the table's name, e.g. ``model.fusesr``, for the
messages); ``training.config`` checks the types from the annotations before.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from gbuffer_export.config import ConfigError

NORMS = ("none", "batch")
RDG_GBUFFERS = ("normal", "brdf", "depth", "motion")


def _sigma(where: str, v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0 < float(v) <= 100):
        raise ConfigError(f"{where} {v!r}: must lie in (0, 100]")
    return float(v)


def _count(where: str, v, high: int) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or not (1 <= v <= high):
        raise ConfigError(f"{where} {v!r}: must be an integer in 1..{high}")


@dataclass
class NoOptions:
    """A model with no options of its own (only the shared ``[model]`` keys)."""

    def validate(self, where: str) -> None:
        pass


@dataclass
class DemodJBUOptions:
    """``demod-jbu``: the tolerances of the joint bilateral upsampling guided by HR depth and normals."""

    guide_sigma_depth: float = 0.1   # relative depth tolerance (through log depth)
    guide_sigma_normal: float = 0.3  # camera-space normal tolerance (unit vectors)

    def validate(self, where: str) -> None:
        self.guide_sigma_depth = _sigma(f"{where}.guide_sigma_depth", self.guide_sigma_depth)
        self.guide_sigma_normal = _sigma(f"{where}.guide_sigma_normal", self.guide_sigma_normal)


@dataclass
class FuseSRFastOptions:
    """``fusesr-fast``: the switches it shares with ``fusesr`` (all but ``hr_guide``) and its backbone size."""

    hr_gbuffer: bool = True          # HR G-buffer input (Table 3 ablation of the FuseSR paper)
    demodulation: bool = True        # predict L_D and remodulate with HR F_beta (Table 3 ablation)
    width: int = 32                  # backbone channels
    blocks: int = 6                  # backbone blocks
    residual: bool = True            # add the upsampled T(L_D^LR) before the final ReLU (not in the paper)
    guided_upsample: bool = True     # with hr_gbuffer and residual: the residual base is the joint bilateral
    guide_sigma_depth: float = 0.1   #   upsampling guided by HR depth (relative tolerance through log depth)
    guide_sigma_normal: float = 0.3  #   and camera-space normals
    zero_init_refine: bool = False   # the last conv starts at 0: training starts exactly at the residual base
    norm: str = "none"               # encoder/backbone normalisation: "none" or "batch" (the authors' BatchNorm)

    def validate(self, where: str) -> None:
        _count(f"{where}.width", self.width, 1024)
        _count(f"{where}.blocks", self.blocks, 64)
        self.guide_sigma_depth = _sigma(f"{where}.guide_sigma_depth", self.guide_sigma_depth)
        self.guide_sigma_normal = _sigma(f"{where}.guide_sigma_normal", self.guide_sigma_normal)
        if self.norm not in NORMS:
            raise ConfigError(f"{where}.norm {self.norm!r}: choose one of {', '.join(NORMS)}")


@dataclass
class FuseSROptions(FuseSRFastOptions):
    """``fusesr``: ``fusesr-fast``'s switches at FuseSR's sizes, plus the HR guidance of the refinement."""

    width: int = 128
    hr_guide: bool = False           # the HR refinement also reads the HR G-buffers (not in the paper)

    def validate(self, where: str) -> None:
        super().validate(where)
        if self.hr_guide and not self.hr_gbuffer:
            raise ConfigError(f"{where}.hr_guide needs {where}.hr_gbuffer = true (it reads the HR G-buffers)")


@dataclass
class FuseSRLightOptions(FuseSROptions):
    """``fusesr-l``: ``fusesr``'s options at half width."""

    width: int = 64


@dataclass
class NSRDOptions:
    """``nsrd``: deviations from the authors' head (docs/models/nsrd.md, "Base"); both off is the authors' network."""

    residual: bool = False           # add T(demod-bilinear L_D) to the head's output: the network learns a correction
    zero_init_head: bool = False     # with residual: the last conv starts at 0, so a fresh network is demod-bilinear

    def validate(self, where: str) -> None:
        if self.zero_init_head and not self.residual:
            raise ConfigError(f"{where}.zero_init_head needs {where}.residual = true (it starts at the residual base)")


@dataclass
class RDGOptions:
    """``rdg``: width and the inputs of the ablations."""

    width: int = 36                  # C, the channels of the first level (2C and 3C below)
    demod: bool = False              # L_D in, remodulated with HR F_beta and emission (off: radiance, the paper)
    gbuffers: list[str] = field(default_factory=lambda: list(RDG_GBUFFERS))  # G-buffers read; the others are zeros

    def validate(self, where: str) -> None:
        _count(f"{where}.width", self.width, 1024)
        for g in self.gbuffers:
            if g not in RDG_GBUFFERS:
                raise ConfigError(f"{where}.gbuffers item {g!r}: choose one of {', '.join(RDG_GBUFFERS)}")
        if len(set(self.gbuffers)) != len(self.gbuffers):
            raise ConfigError(f"{where}.gbuffers {self.gbuffers}: an item is repeated")


@dataclass
class RDGSmallOptions(RDGOptions):
    """``rdg-s``: ``rdg``'s options at width 16."""

    width: int = 16



@dataclass
class FourierSROptions:
    """``fourier-sr``: the thresholds of the spatial mask (Eq. 3-6; the authors' code's values)."""

    mask_depth: float = 0.01    # |D - Up(d)| above it, on the normalised depth in [0, 1]
    mask_albedo: float = 0.1    # mean over RGB of |A - Up(a)| above it
    mask_normal: float = 0.9    # cosine between N and the normalised Up(n) below it

    def validate(self, where: str) -> None:
        for name, hi in (("mask_depth", 1.0), ("mask_albedo", 1.0), ("mask_normal", 1.0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0 < float(v) <= hi):
                raise ConfigError(f"{where}.{name} {v!r}: must lie in (0, {hi:g}]")
            setattr(self, name, float(v))
