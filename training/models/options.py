"""Each model's own options (pure Python, no torch): the ``[model.<name>]`` table of a training configuration.

One dataclass per model, named in its row of ``training.models.MODELS``; the shared ``[model]`` keys (scale,
history, jitter, input transform, remodulation filter, ...) are ``training.config.ModelConfig``'s. A model reads
its options as ``self.options`` (its constructor takes them by keyword and validates them through
``ModelConfig.of``: these dataclasses and ``ModelConfig`` hold every default, once). A model without options of
its own uses ``NoOptions`` (the table's default), so it needs no class here.

The classes live here and not beside their ``nn.Module`` because a model's file imports torch, and the configuration
is validated without torch (``blendsr train`` checks its configuration before it imports the trainer).

Each key's type and range are its annotation and ``option(...)`` rule (``gbuffer_export.typed_table``);
``validate(where)`` checks them and the combinations (``where`` is the table's name, e.g. ``model.fusesr``, for the
messages).
"""
from __future__ import annotations

from dataclasses import dataclass

from gbuffer_export.typed_table import ConfigError, option, set_checked

NORMS = ("none", "batch")
RDG_GBUFFERS = ("normal", "brdf", "depth", "motion")
#: ``residual_clamp`` of the FuseSR family: none (the paper's network), lr-range or lr-guided
#: (``FuseSRFastOptions``; training/models/fusesr.py, "Bounded correction").
RESIDUAL_CLAMPS = ("none", "lr-range", "lr-guided")
#: Options that change what a trained network's output goes through, not its weights: ``load_model`` lets them be
#: set on a checkpoint (``--set model.NAME.KEY=VALUE``, or ``CHECKPOINT?KEY=VALUE``).
INFERENCE_OPTIONS = ("residual_clamp", "residual_clamp_margin", "transmission_fallback")


def _sigma(default: float):
    """A joint bilateral tolerance: a number in (0, 100]."""
    return option(default, lo=0, lo_open=True, hi=100)


def _width(default: int):
    return option(default, lo=1, hi=1024, unit="channels")


@dataclass
class NoOptions:
    """A model with no options of its own (only the shared ``[model]`` keys)."""

    def validate(self, where: str) -> None:
        set_checked(self, where)


@dataclass
class DemodJBUOptions:
    """``demod-jbu``: the tolerances of the joint bilateral upsampling guided by HR depth and normals."""

    guide_sigma_depth: float = _sigma(0.1)   # relative depth tolerance (through log depth)
    guide_sigma_normal: float = _sigma(0.3)  # camera-space normal tolerance (unit vectors)

    def validate(self, where: str) -> None:
        set_checked(self, where)


@dataclass
class FuseSRFastOptions:
    """``fusesr-fast``: the switches it shares with ``fusesr`` (all but ``hr_guide``) and its backbone size."""

    hr_gbuffer: bool = True          # HR G-buffer input (Table 3 ablation of the FuseSR paper)
    demodulation: bool = True        # predict L_D and remodulate with HR F_beta (Table 3 ablation)
    width: int = _width(32)          # backbone channels
    blocks: int = option(6, lo=1, hi=64)  # backbone blocks
    residual: bool = True            # add the upsampled T(L_D^LR) before the final ReLU (not in the paper)
    guided_upsample: bool = True     # with hr_gbuffer and residual: the residual base is the joint bilateral
    guide_sigma_depth: float = _sigma(0.1)   # upsampling guided by HR depth (relative tolerance through log depth)
    guide_sigma_normal: float = _sigma(0.3)  # and camera-space normals
    zero_init_refine: bool = False   # the last conv starts at 0: training starts exactly at the residual base
    norm: str = option("none", choices=NORMS)  # encoder/backbone normalisation (batch: the authors' BatchNorm)
    residual_clamp: str = option("none", choices=RESIDUAL_CLAMPS)  # lr-range: the output L_D clamped per channel
    residual_clamp_margin: float = option(0.0, lo=0, hi=100)  # to the LR range of its base's taps, widened by this
    # fraction of the range's width; lr-guided: over the taps of the pixel's surface only, unclamped where none is
    # (not in the paper; training/models/fusesr.py, "Bounded correction")
    confidence_gate: bool = False    # with residual: the correction times a learned per-HR-pixel confidence in
    # [0, 1]; 0 is the residual base (not in the paper; training/models/fusesr.py, "Confidence gate")
    hr_geometry: bool = False        # fusesr-fast only: the fusion also reads the pixel-unshuffled HR depth, normals
    # and albedo through a 1x1 conv (not in the authors' fast network; training/models/fusesr_fast.py)
    gate_transmission: bool = False  # with confidence_gate: the gate's logit also gains a learned weight (from 0)
    # times the HR TRANSMISSION mask, so training decides how far to trust the network on glass (not in the paper;
    # training/models/fusesr.py, "Transmission fallback")
    transmission_fallback: bool = False  # with residual: no correction on HR pixels flagged TRANSMISSION (their
    # G-buffers describe the glass, not what is seen through it): the residual base there (not in the paper;
    # training/models/fusesr.py, "Transmission fallback")

    def validate(self, where: str) -> None:
        set_checked(self, where)
        if self.residual_clamp != "none" and not self.residual:
            raise ConfigError(f"{where}.residual_clamp needs {where}.residual = true (it bounds the correction of "
                              "the residual base)")
        if self.confidence_gate and not self.residual:
            raise ConfigError(f"{where}.confidence_gate needs {where}.residual = true (it gates the correction of "
                              "the residual base)")
        if self.gate_transmission and not self.confidence_gate:
            raise ConfigError(f"{where}.gate_transmission needs {where}.confidence_gate = true (it adds to the "
                              "gate's logit)")
        if self.transmission_fallback and not self.residual:
            raise ConfigError(f"{where}.transmission_fallback needs {where}.residual = true (it falls back to the "
                              "residual base)")
        if self.hr_geometry and not self.hr_gbuffer:
            raise ConfigError(f"{where}.hr_geometry needs {where}.hr_gbuffer = true (the HR G-buffer input)")
        if self.residual_clamp == "lr-guided" and not (self.guided_upsample and self.hr_gbuffer):
            raise ConfigError(f"{where}.residual_clamp = \"lr-guided\" needs {where}.guided_upsample = true and "
                              f"{where}.hr_gbuffer = true (it weighs the taps by the HR guides)")


@dataclass
class FuseSROptions(FuseSRFastOptions):
    """``fusesr``: ``fusesr-fast``'s switches at FuseSR's sizes, plus the HR guidance of the refinement."""

    width: int = _width(128)
    hr_guide: bool = False           # the HR refinement also reads the HR G-buffers (not in the paper)
    hr_material: bool = False        # the HR branch also reads HR roughness and metallic (2 more HR channels; not in
    # the paper; training/models/fusesr.py, "Material inputs")

    def validate(self, where: str) -> None:
        super().validate(where)
        if self.hr_geometry:
            raise ConfigError(f"{where}.hr_geometry is fusesr-fast's: this network reads the HR depth, normals and "
                              "albedo in its HR branch already")
        if self.hr_guide and not self.hr_gbuffer:
            raise ConfigError(f"{where}.hr_guide needs {where}.hr_gbuffer = true (it reads the HR G-buffers)")
        if self.hr_material and not self.hr_gbuffer:
            raise ConfigError(f"{where}.hr_material needs {where}.hr_gbuffer = true (it widens the HR branch)")


@dataclass
class FuseSRLightOptions(FuseSROptions):
    """``fusesr-l``: ``fusesr``'s options at half width."""

    width: int = _width(64)


@dataclass
class ResidualOptions:
    """The residual base (not in the papers; docs/models/nsrd.md, "Base"): both off is the authors' network. With
    ``residual`` the network's output T(L_D^HR) is added to T(demod-bilinear's upsampling of L_D) and remodulated
    (``SRModel.demod_base``), so the network learns a correction of ``demod-bilinear``."""

    residual: bool = False           # add T(demod-bilinear L_D) to the head's output: the network learns a correction
    zero_init_head: bool = False     # with residual: the last conv starts at 0, so a fresh network is demod-bilinear

    def validate(self, where: str) -> None:
        set_checked(self, where)
        check_residual(self, where)


def check_residual(opts, where: str) -> None:
    """ConfigError for ``zero_init_head`` without ``residual`` (the fields of ``ResidualOptions``)."""
    if opts.zero_init_head and not opts.residual:
        raise ConfigError(f"{where}.zero_init_head needs {where}.residual = true (it starts at the residual base)")


@dataclass
class NSRDOptions(ResidualOptions):
    """``nsrd``: deviations from the authors' head (docs/models/nsrd.md, "Base"); both off is the authors' network."""


@dataclass
class NSRROptions(ResidualOptions):
    """``nsrr``, ``nsrr-fec``: the residual base (docs/models/nsrr_fec.md, "Base"); off is the paper's network. With
    ``residual`` the output is T(L_D^HR), remodulated with HR F_beta and emission, instead of T(radiance)."""


@dataclass
class RDGOptions:
    """``rdg``: width, the inputs of the ablations and the residual base (docs/models/rdg.md, "Base"; needs
    ``demod``)."""

    width: int = _width(36)          # C, the channels of the first level (2C and 3C below)
    demod: bool = False              # L_D in, remodulated with HR F_beta and emission (off: radiance, the paper)
    gbuffers: list[str] = option(factory=lambda: list(RDG_GBUFFERS), items=RDG_GBUFFERS, unique=True)
    # the G-buffers read; the others are zeros
    residual: bool = False           # ResidualOptions' two keys (with demod): a correction of demod-bilinear
    zero_init_head: bool = False

    def validate(self, where: str) -> None:
        set_checked(self, where)
        check_residual(self, where)
        if self.residual and not self.demod:
            raise ConfigError(f"{where}.residual needs {where}.demod = true (the base is the demodulated L_D)")


@dataclass
class RDGSmallOptions(RDGOptions):
    """``rdg-s``: ``rdg``'s options at width 16."""

    width: int = _width(16)


@dataclass
class FourierSROptions:
    """``fourier-sr``: the thresholds of the spatial mask (Eq. 3-6; the authors' code's values) and the residual
    base at any scale (docs/models/fourier_sr.md, "Base")."""

    mask_depth: float = option(0.01, lo=0, lo_open=True, hi=1)   # |D - Up(d)| above it, normalised depth in [0, 1]
    mask_albedo: float = option(0.1, lo=0, lo_open=True, hi=1)   # mean over RGB of |A - Up(a)| above it
    mask_normal: float = option(0.9, lo=0, lo_open=True, hi=1)   # cosine between N and the normalised Up(n) below it
    residual: bool = False           # ResidualOptions' two keys: a correction of demod-bilinear at the clip's scale
    zero_init_head: bool = False

    def validate(self, where: str) -> None:
        set_checked(self, where)
        check_residual(self, where)
