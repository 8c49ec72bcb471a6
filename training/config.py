"""Typed, validated training configuration (pure Python, no torch).

A configuration is read from a TOML file (sections ``[data]``, ``[model]``, ``[loss]``, ``[optim]``, ``[run]``;
``[model.<name>]`` holds model ``name``'s own options, ``training.models.options``), then CLI overrides are applied
(``--set section.key=value``, ``--set model.NAME.key=value``, ``--max-steps``, ...). Unknown sections or keys are
errors that name the key, and so are values of the wrong type or outside their range: each key's type is its
annotation and its range or choices its ``option(...)`` rule (``gbuffer_export.typed_table``, the helper every
configuration and spec uses); ``validate`` adds the rules that tie keys together. Old flat model keys go
through the legacy rule (``legacy_model_keys``). The resolved configuration is written to the run directory as
``config.toml`` (``to_toml``) and stored in every checkpoint (``to_dict``). docs/configuration.md lists every key.
"""
from __future__ import annotations

import copy
import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from gbuffer_export.config import ConfigError
from gbuffer_export.pixel_filter import FILTERS
from training.models.config import ModelConfig  # noqa: F401 (the [model] section, beside the models)
from gbuffer_export.typed_table import Rule, check_keys, from_table, option, set_checked, typed_value

LOSS_SPACES = ("log1p", "tonemap", "linear")
NONFINITE_POLICIES = ("error", "sanitize")
SCHEDULERS = ("cosine", "constant", "step")
AMP_MODES = ("auto", "none", "bf16", "fp16")
DEVICES = ("auto", "cpu", "cuda")
PIXEL_LOSSES = ("l1", "charbonnier")
TEMPORAL_LOSSES = ("warped", "difference")
FFT_LOSSES = ("ortho", "rfft")


@dataclass
class DataConfig:
    """What the loader feeds. Crop sizes are in LR pixels (the HR crop is ``scale`` times larger)."""

    clips: list[str] = option(factory=list, help=(
        "clip directories (paths); `--data` sets them (a dataset folder gives its train split)"))
    crop: int = option(64, lo=1, unit="LR pixels", help=(
        "LR crop side, pixels. The default shrinks to the smallest LR side of the clips (with a note); another "
        "value that does not fit is an error naming the largest that does"))
    batch_size: int = option(8, lo=1, help="per process")
    augment_flip: bool = option(True, help="random horizontal and vertical flips")
    augment_rotate: bool = option(True, help="random 90-degree rotations (transposes)")
    exposure_range: list[float] = option(factory=lambda: [0.5, 2.0], pair=True, help=(
        "log-uniform scale of radiance, irradiance and emission"))
    reflectance_range: list[float] = option(factory=lambda: [0.5, 2.0], pair=True, help=(
        "log-uniform per-channel scale of the BRDF: radiance, emission, albedo, F_beta"))
    demod_eps: float = option(0.01, lo=1e-6, hi=1, help="floor of F_beta in L_D = (I - E) / max(F_beta, eps)")
    nonfinite: str = option("error", choices=NONFINITE_POLICIES, help=(
        "NaN/Inf in a buffer: an error naming file and frame, or a warning and a repair"))
    cache_dir: str = option("", help=(
        "decoded-clip cache: \"\" is `CLIP/.blendsr_cache`, else `DIR/<clip name>-<path hash>`"))
    prefetch: int = option(2, lo=0, help="batches prepared ahead in a background thread (per worker with `workers`)")
    workers: int = option(0, lo=0, hi=64, help=(
        "loader processes (0: the prefetch thread); the batches are the same either way"))
    pin_memory: bool = option(True, help="with workers on CUDA: page-locked batches, asynchronous copies")
    val_frames: int = option(0, lo=0, help="last N frames of each clip held out of training and evaluated at the end")
    val_clips: list[str] = option(factory=list, help=(
        "whole clips never trained on, evaluated at the end and every `run.eval_every` steps; `--data DATASET` "
        "fills it with the val split"))
    window: int = option(0, lo=0, hi=64, help=(
        "recurrent models (`recurrent = True` on the class: `rdg`, `rdg-s`, `nsrd`, `nsrr-fec`, `fourier-sr`): "
        "frames per training window, a target each (0: 7)"))
    detach_every: int = option(0, lo=0, help="recurrent models: detach the state every N frames of a window (0: never)")

    def validate(self) -> None:
        set_checked(self, "data")


@dataclass
class LossConfig:
    """Weights of the loss terms (0 disables a term) and the space the pixel losses compare in."""

    space: str = option("log1p", choices=LOSS_SPACES, help=(
        "where the pixel, FFT and temporal losses compare SR and ground truth: log1p(max(x, 0)), the evaluation"
        " tonemap, or linear radiance"))
    pixel: str = option("l1", choices=PIXEL_LOSSES, help="pixel loss")
    pixel_weight: float = option(1.0, lo=0, help="weight of the pixel loss")
    charbonnier_eps: float = option(1e-3, lo=1e-6, help="sqrt(d^2 + eps^2)")
    ssim_weight: float = option(0.05, lo=0, help="1 - SSIM on the tonemapped images (FuseSR's weight)")
    fft_weight: float = option(0.0, lo=0, help="frequency loss (`fft`)")
    fft: str = option("ortho", choices=FFT_LOSSES, help=(
        "\"ortho\": mean modulus of the orthonormal 2-D FFT difference; \"rfft\": mean of abs(Re) and abs(Im) of "
        "the unnormalised real FFT difference (RDG's code)"))
    temporal_weight: float = option(0.0, lo=0, help="temporal consistency (`temporal`)")
    baseline_weight: float = option(0.0, lo=0, help=(
        "hinge over the guided baseline `demod-jbu` (`baseline`): the mean of max(0, |SR - GT| - |JBU - GT|) in "
        "`space`, paid only where the network is further from the ground truth than the non-learned baseline (not "
        "in the papers)"))
    temporal: str = option("warped", choices=TEMPORAL_LOSSES, help=(
        "\"warped\": L1 of (SR_t - W(SR_t-1)) - (GT_t - W(GT_t-1)), W the HR backward warp; \"difference\": MSE of "
        "(SR_t - SR_t-1) - (GT_t - GT_t-1) (RDG's code)"))
    perceptual_weight: float = option(0.0, lo=0, help="VGG-16 feature distance (FuseSR: 0.5); needs `vgg_weights`")
    vgg_weights: str = option("", help=(
        "torchvision's `vgg16-397923af.pth`, which you download (sha256 checked; "
        "[training.md](training.md#perceptual-loss-the-vgg-16-weights-file)); nothing is downloaded at run time"))

    def validate(self) -> None:
        set_checked(self, "loss")
        if self.pixel_weight + self.ssim_weight + self.fft_weight + self.perceptual_weight <= 0:
            raise ConfigError("loss: every weight is 0; nothing to train")
        if self.perceptual_weight > 0:  # the file must exist; its sha256 is checked when the loss loads it
            from training.perceptual import require_vgg_file
            require_vgg_file(self.vgg_weights, check_hash=False)


@dataclass
class OptimConfig:
    """Adam(W) with a learning-rate schedule."""

    lr: float = option(2e-4, lo=0, lo_open=True, help="learning rate")
    betas: list[float] = option(factory=lambda: [0.9, 0.999], help="Adam betas [b1, b2], each in [0, 1)")
    weight_decay: float = option(0.0, lo=0, help="AdamW's weight decay (0: Adam)")
    scheduler: str = option("cosine", choices=SCHEDULERS, help=(
        "cosine decay to `lr * min_lr_ratio` over `decay_steps`; constant; or times `step_gamma` every "
        "`step_every` steps"))
    decay_steps: int = option(0, lo=0, help="length of the cosine schedule (0: `run.max_steps`)")
    warmup_steps: int = option(0, lo=0, help="linear warm-up")
    min_lr_ratio: float = option(0.01, lo=0, help="end of the cosine schedule, relative to `lr`")
    step_every: int = option(10000, lo=1, help="\"step\" scheduler period, steps")
    step_gamma: float = option(0.5, lo=0, help="\"step\" scheduler factor")
    grad_clip: float = option(0.0, lo=0, help="maximum gradient norm (0: off)")
    gate_lr_scale: float = option(1.0, lo=0, lo_open=True, hi=1000, help=(
        "the learning rate of the model's confidence gate (`model.<M>.confidence_gate`) relative to `lr`, with the "
        "same schedule: a gate that starts nearly open moves by about `lr` per Adam step, too slowly to close "
        "where the network does harm; 1: the network's rate"))
    ema_decay: float = option(0.0, lo=0, hi=1, hi_open=True, help=(
        "exponential moving average of the weights and buffers (0: off; e.g. 0.999, a horizon of about 1000 "
        "steps); when on, evaluation, inference, `run.init_from` and shipped weights use the average"))

    def validate(self) -> None:
        set_checked(self, "optim")
        if len(self.betas) != 2 or not all(0 <= b < 1 for b in self.betas):
            raise ConfigError(f"optim.betas {self.betas}: expected [b1, b2] in [0, 1)", key="optim.betas")


@dataclass
class RunConfig:
    """How long and where to run, and what to record."""

    seed: int = option(0, help="seeds Python, numpy and torch")
    max_steps: int = option(20000, lo=1, help="optimiser steps; `--max-steps` sets it (and clears `minutes`)")
    minutes: float = option(0.0, lo=0, help=(
        "wall-clock budget of this invocation (0: none); stops cleanly with a checkpoint"))
    checkpoint_every: int = option(500, lo=1, help="steps between checkpoints")
    keep_checkpoints: int = option(3, lo=0, help="numbered checkpoints kept besides `last.pt`")
    log_every: int = option(10, lo=1, help="steps between rows of `log.csv`")
    device: str = option("auto", choices=DEVICES, help="auto: cuda when available")
    amp: str = option("auto", choices=AMP_MODES, help=(
        "auto: bf16 where the hardware has it, fp16 on older GPUs, else full precision"))
    compile: bool = option(False, help="`torch.compile` the model")
    threads: int = option(0, lo=0, help="torch intra-op threads (0: OMP_NUM_THREADS where set, else the cores "
                                        "this process may use: its CPU affinity, capped by the cgroup CPU quota)")
    progress: bool = option(True, help="progress bar")
    eval_every: int = option(0, lo=0, help="steps between validation runs (0: only at the end)")
    init_from: str = option("", help=(
        "checkpoint (a path, or `pretrained:NAME`) whose model weights start a fresh run (fine-tuning)"))

    def validate(self) -> None:
        set_checked(self, "run")


@dataclass
class TrainConfig:
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    run: RunConfig = field(default_factory=RunConfig)

    #: One line each about parts of the input that were read but not used (``config_from_dict``): the tables of
    #: other models than the chosen one, old flat keys the chosen model has no use for. Not saved.
    notes: ClassVar[tuple[str, ...]] = ()

    def validate(self) -> "TrainConfig":
        for f in dataclasses.fields(self):
            getattr(self, f.name).validate()
        return self

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Nested plain types: {section: {key: value}}, the model's options as ``model.<name>`` (a dict)."""
        d = dataclasses.asdict(self)
        d["model"] = self.model.to_dict()
        return d

    def to_toml(self) -> str:
        return dict_to_toml(self.to_dict())


SECTIONS = {f.name: f.type for f in dataclasses.fields(TrainConfig)}


def _section_class(name: str):
    return {"data": DataConfig, "model": ModelConfig, "loss": LossConfig, "optim": OptimConfig, "run": RunConfig}[name]


def _table(cls, values: dict, source: str, prefix: str, no_keys: str = "known: none") -> Any:
    """An instance of the dataclass ``cls`` from ``values``, each key checked (``typed_table.from_table``);
    ``prefix`` names the table in messages (``data``, ``model.fusesr``), ``no_keys`` ends the unknown-key message of
    a class without fields."""
    if not isinstance(values, dict):
        raise ConfigError(f"{source}: [{prefix}] must be a table", key=prefix)
    return from_table(cls, values, prefix, prefix=f"{source}: ", empty=no_keys)


def _model_from_dict(values: dict, source: str) -> tuple[ModelConfig, list[str]]:
    """The ``[model]`` table: shared keys, the chosen model's ``[model.<name>]`` table (old flat keys moved there by
    ``legacy_model_keys``) and tables of other models (type-checked, then left out with a note)."""
    from training.models import MODELS  # torch-free table
    name = typed_value("model.name", values.get("name", ModelConfig.name), str, Rule(), prefix=f"{source}: ")
    if name not in MODELS:
        raise ConfigError(f"{source}: model.name {name!r}: choose one of {', '.join(MODELS)}")
    values, notes = legacy_model_keys(values, source)
    shared = [f.name for f in dataclasses.fields(ModelConfig) if f.name != "options"]
    check_keys(values, [*shared, *MODELS], "model", prefix=f"{source}: ",
               also=f"; model.NAME is a table [model.NAME] of options for NAME one of {', '.join(MODELS)}")
    cfg = from_table(ModelConfig, {k: v for k, v in values.items() if k in shared}, "model", prefix=f"{source}: ",
                     base=ModelConfig(name=name))
    for key, value in values.items():
        if key not in MODELS:
            continue
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: model.{key} must be a table ([model.{key}]) of model {key}'s options",
                              key=f"model.{key}")
        options = _table(MODELS[key].options, value, source, f"model.{key}",
                         f"model {key} has no options of its own")
        if key == name:
            cfg.options = options
        else:
            options.validate(f"{source}: model.{key}")
            notes.append(f"{source}: [model.{key}] is not used (model.name is {name!r})")
    return cfg, notes


def config_from_dict(data: dict, source: str = "config") -> TrainConfig:
    """Build and validate a TrainConfig from nested dicts; unknown sections/keys raise ConfigError. Notes on what
    was read but not used are in the result's ``notes``."""
    cfg = TrainConfig()
    notes: list[str] = []
    for section, values in data.items():
        if section not in SECTIONS:
            raise ConfigError(f"{source}: unknown section [{section}] (known: {', '.join(SECTIONS)})", key=section)
        if not isinstance(values, dict):
            raise ConfigError(f"{source}: [{section}] must be a table", key=section)
        if section == "model":
            cfg.model, notes = _model_from_dict(values, source)
        else:
            setattr(cfg, section, _table(_section_class(section), values, source, section))
    cfg.notes = tuple(notes)
    return cfg.validate()


#: The legacy rule's table: every ``[model]`` key of the configurations (and checkpoints) written before each model
#: had its own table, with its name in that table and its old default. Old 0 widths/blocks meant the default.
LEGACY_FLAT_KEYS: dict[str, tuple[str, Any]] = {
    "hr_gbuffer": ("hr_gbuffer", True), "demodulation": ("demodulation", True), "width": ("width", 0),
    "blocks": ("blocks", 0), "residual": ("residual", True), "hr_guide": ("hr_guide", False),
    "guided_upsample": ("guided_upsample", True), "guide_sigma_depth": ("guide_sigma_depth", 0.1),
    "guide_sigma_normal": ("guide_sigma_normal", 0.3), "zero_init_refine": ("zero_init_refine", False),
    "norm": ("norm", "none"), "rdg_demod": ("demod", False),
    "rdg_gbuffers": ("gbuffers", ["normal", "brdf", "depth", "motion"]),
}


def legacy_model_keys(model: dict, source: str = "config") -> tuple[dict, list[str]]:
    """The legacy rule: a ``[model]`` table in which old flat option keys (``LEGACY_FLAT_KEYS``: ``model.hr_gbuffer``,
    ``model.rdg_demod``, ...) are moved into the table ``[model.<name>]`` of the model in use, renamed where the
    table names them otherwise (``rdg_demod`` -> ``demod``, ``rdg_gbuffers`` -> ``gbuffers``). A width or block
    count of 0 (the old "model's default") is dropped. A key the model has no option for is dropped (the model never
    read it) with a note when its value is not the old default. A key given both ways is an error. Returns the new
    table and the notes; ``model`` is not modified."""
    from training.models import MODELS  # torch-free table
    name = model.get("name", ModelConfig.name)
    if not any(k in LEGACY_FLAT_KEYS for k in model) or not isinstance(name, str) or name not in MODELS:
        return model, []
    out = {k: v for k, v in model.items() if k not in LEGACY_FLAT_KEYS}
    table = out.get(name, {})
    if not isinstance(table, dict):
        raise ConfigError(f"{source}: model.{name} must be a table ([model.{name}]) of model {name}'s options")
    table = dict(table)
    known = {f.name for f in dataclasses.fields(MODELS[name].options)}
    notes = []
    for old, value in model.items():
        if old not in LEGACY_FLAT_KEYS:
            continue
        new, default = LEGACY_FLAT_KEYS[old]
        if old in ("width", "blocks") and type(value) is int and value == 0:
            continue
        if new not in known:
            if value != default:
                notes.append(f"{source}: model.{old} is not an option of model {name} (not used)")
            continue
        if new in table:
            raise ConfigError(f"{source}: model.{old} and model.{name}.{new} both given; keep model.{name}.{new}")
        table[new] = value
    if table or name in out:
        out[name] = table
    return out, notes


#: Keys added after checkpoints were first written, with the behaviour such checkpoints were trained with: shared
#: model keys, then options (applied to the model's table when its options have the key).
LEGACY_MODEL_KEYS = {"jitter": False, "remod_filter": "NONE", "upsample_by_class": False}
LEGACY_OPTION_KEYS = {"norm": "batch", "guided_upsample": False, "zero_init_refine": False}
LEGACY_DATA_KEYS = {"reflectance_range": [1.0, 1.0]}


def config_from_checkpoint(data: dict, source: str = "checkpoint") -> TrainConfig:
    """``config_from_dict`` for a checkpoint's saved configuration. Old flat model keys go through the legacy rule
    (``legacy_model_keys``); keys it predates take their old behaviour (``LEGACY_MODEL_KEYS``,
    ``LEGACY_OPTION_KEYS``, ``LEGACY_DATA_KEYS``), so older checkpoints load and run as they were trained."""
    from training.models import MODELS  # torch-free table
    model, _ = legacy_model_keys(data.get("model", {}), source)
    model = {**LEGACY_MODEL_KEYS, **model}
    name = model.get("name", ModelConfig.name)
    if isinstance(name, str) and name in MODELS and isinstance(model.get(name, {}), dict):
        known = {f.name for f in dataclasses.fields(MODELS[name].options)}
        missing = {k: v for k, v in LEGACY_OPTION_KEYS.items() if k in known}
        if missing:
            model[name] = {**missing, **model.get(name, {})}
    loader = {**LEGACY_DATA_KEYS, **data.get("data", {})}
    return config_from_dict({**data, "model": model, "data": loader}, source=source)


def load_config(path: str | Path | None, overrides: list[str] | None = None) -> TrainConfig:
    """Read a TOML config (None: defaults) and apply ``section.key=value`` overrides (``model.NAME.key=value`` for a
    model's own option; values in TOML syntax; bare words are taken as strings)."""
    data: dict = {}
    source = "--set" if overrides else "defaults"  # what an error names: the file, else the --set values
    if path:
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"{p}: config file not found")
        try:
            data = tomllib.loads(p.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{p}: not valid TOML ({exc})") from None
        source = str(p)
    for item in overrides or []:
        key, sep, text = item.partition("=")
        parts = [k.strip() for k in key.split(".")]
        if not sep or len(parts) < 2 or not all(parts):
            raise ConfigError(f"--set {item!r}: expected section.key=value, e.g. data.crop=48")
        table = data
        for i, part in enumerate(parts[:-1]):
            table = table.setdefault(part, {})
            if not isinstance(table, dict):
                raise ConfigError(f"--set {item!r}: [{'.'.join(parts[:i + 1])}] is not a table")
        table[parts[-1]] = parse_value(text.strip())
    return config_from_dict(data, source)


def parse_value(text: str) -> Any:
    """A TOML literal (1, 2.5, true, "x", [1, 2]); anything else is a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


#: TOML basic-string escapes; other control characters are written as \uXXXX.
_TOML_ESCAPES = {"\\": "\\\\", '"': '\\"', "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def _toml_string(v: str) -> str:
    return '"' + "".join(_TOML_ESCAPES.get(c) or (f"\\u{ord(c):04x}" if ord(c) < 0x20 or ord(c) == 0x7F else c)
                         for c in v) + '"'


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")


def _toml_key(k: str) -> str:
    return k if k and all(c.isascii() and (c.isalnum() or c in "-_") for c in k) else _toml_value(k)


def dict_to_toml(d: dict[str, dict[str, Any]]) -> str:
    """Nested {section: {key: value}} as TOML text (round-trips through tomllib); a dict value is a sub-table
    ``[section.key]``. Written by tomli-w (the ``[train]`` extra); in an environment made before it was a
    dependency, by ``_dict_to_toml`` (the same escapes: every control character, newlines included)."""
    try:
        import tomli_w
    except ModuleNotFoundError:
        return _dict_to_toml(d)
    return tomli_w.dumps(d)


def _dict_to_toml(d: dict[str, dict[str, Any]]) -> str:
    lines = []

    def table(name: str, values: dict) -> None:
        lines.append(f"[{name}]")
        for k, v in values.items():
            if not isinstance(v, dict):
                lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
        lines.append("")
        for k, v in values.items():
            if isinstance(v, dict):
                table(f"{name}.{_toml_key(k)}", v)

    for section, values in d.items():
        table(_toml_key(section), values)
    return "\n".join(lines)


__all__ = ["TrainConfig", "DataConfig", "ModelConfig", "LossConfig", "OptimConfig", "RunConfig", "ConfigError",
           "load_config", "config_from_dict", "config_from_checkpoint", "legacy_model_keys"]
