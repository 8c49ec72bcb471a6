"""``ModelConfig``: which network, the keys every model shares and the chosen model's own options (the ``[model]``
table of a training configuration; ``training.config`` holds the other sections). It lives beside the models, which
read it, so that no model imports the training configuration above them."""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from typing import Any

from gbuffer_export.config import ConfigError
from gbuffer_export.pixel_filter import FILTERS
from gbuffer_export.typed_table import option, set_checked

INPUT_TRANSFORMS = ("log1p", "none")
DEPTH_NORMS = ("ratio", "inverse")


@dataclass
class ModelConfig:
    """Which network: the keys every model shares, and the chosen model's own options (``options``, the
    ``[model.<name>]`` table; its dataclass is ``MODELS[name].options``, ``training.models.options``). ``scale``:
    the LR level to train on; 0 takes the scales from the clips (every level of theirs for a model that takes any
    scale, ``SRModel.SCALES is None``)."""

    name: str = option("fusesr", help="a model name: `blendsr train --list-models` lists them; `--model` sets it")
    scale: float = option(0, help=(
        "upscaling factor (a scale >= 1 such as 2, 2.5 or 4); 0: from the clips (all must agree). Training "
        "writes the clips' scale"))
    history: int = option(-1, lo=-1, hi=4, help=(
        "previous frames the model reads; -1: the model's default (`fusesr` 2, `fusesr-l` 0). Read by `fusesr` "
        "and `fusesr-l`; `fusesr-fast` accepts only -1 and 0; the others read none"))
    input_transform: str = option("log1p", choices=INPUT_TRANSFORMS, help=(
        "HDR transform T of the radiance/irradiance inputs; outputs are inverted (`fusesr*`, `rdg*`)"))
    depth_norm: str = option("ratio", choices=DEPTH_NORMS, help=(
        "depth input: d / (d + median LR depth of the frame), or 1 / (1 + d); background 1 or 0 (`fusesr*`, "
        "`rdg*`)"))
    jitter: bool = option(True, help=(
        "use each LR frame's sub-pixel jitter: upsampling samples at the jittered positions, history warping "
        "adds the jitter difference, learned models read it as 2 channels (all models)"))
    upsample_by_class: bool = option(True, help=(
        "demodulated models: the bilinear upsampling of L_D never mixes demodulated pixels with F_used = 1 ones"
        " (background, untrusted flags)"))
    remod_filter: str = option("REFERENCE", choices=("REFERENCE", "NONE") + FILTERS, help=(
        "pixel filter K of the remodulation SR = K * (L_D F_used + E) of demodulated models. REFERENCE: the "
        "clips' ground-truth filter (manifest `render.hr`); training resolves it into the checkpoint. NONE: no "
        "filter"))
    remod_filter_px: float = option(1.5, lo=0, hi=4, lo_open=True, unit="pixels", help=(
        "filter width in pixels (Cycles' `filter_width`) when `remod_filter` names a filter"))
    options: Any = None  # the options of model ``name`` (None: its defaults)

    def __post_init__(self) -> None:
        from training.models import MODELS  # torch-free table
        if self.options is None and self.name in MODELS:
            self.options = MODELS[self.name].options()

    @classmethod
    def of(cls, name: str = "fusesr", **keys) -> "ModelConfig":
        """A validated configuration of model ``name`` from shared keys and that model's options, by keyword
        (``ModelConfig.of("fusesr", jitter=False, hr_gbuffer=False)``)."""
        cfg = cls(name=name)
        cfg.validate()
        shared = [f.name for f in dataclasses.fields(cls) if f.name not in ("name", "options")]
        own = [f.name for f in dataclasses.fields(cfg.options)]
        for key, value in keys.items():
            if key not in shared + own:
                raise ConfigError(f"model {name}: no key {key!r} (known: {', '.join(shared)}; options: "
                                  f"{', '.join(own) or 'none'})")
            setattr(cfg if key in shared else cfg.options, key, value)
        cfg.validate()
        return cfg

    def validate(self) -> None:
        from training.models import MODELS  # torch-free table
        if self.name not in MODELS:
            raise ConfigError(f"model.name {self.name!r}: choose one of {', '.join(MODELS)}", key="model.name")
        set_checked(self, "model", names=[f.name for f in dataclasses.fields(self) if f.name != "name"])
        if self.scale != 0 and not self.scale >= 1:
            raise ConfigError(f"model.scale {self.scale:g}: must be a scale >= 1 such as 2, 2.5 or 4 "
                              "(0: from the data)", key="model.scale")
        cls = MODELS[self.name].options
        if self.options is None:
            self.options = cls()
        if type(self.options) is not cls:
            raise ConfigError(f"model.{self.name}: options of type {type(self.options).__name__}, expected "
                              f"{cls.__name__}")
        self.options.validate(f"model.{self.name}")

    def to_dict(self) -> dict[str, Any]:
        """The ``[model]`` table: the shared keys, then the chosen model's options as the sub-table ``name``."""
        d = {f.name: copy.deepcopy(getattr(self, f.name)) for f in dataclasses.fields(self) if f.name != "options"}
        d[self.name] = dataclasses.asdict(self.options) if self.options is not None else {}
        return d
