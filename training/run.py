"""What a training run derives from the user's configuration and the clips (``resolve_run``), and every check made
on ``--resume`` (``resume_run``). The user's ``TrainConfig`` is never rewritten: the derived values live in a frozen
``ResolvedRun``, and ``ResolvedRun.apply(cfg)`` gives the effective configuration as a new object.

A checkpoint holds both (``user_config``, ``resolved``) and the effective configuration (``config``, which
inference reads). On resume the saved user configuration is resolved again against the clips and must give the
same ``ResolvedRun``; a difference is one line naming the field. Checkpoints written before the record existed
(``config`` only, already resolved) resolve to themselves, so they resume unchanged.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from gbuffer_export.clip import scale_value
from gbuffer_export.config import ConfigError
from gbuffer_export.conventions import scale_fraction
from training.config import TrainConfig, config_from_checkpoint

#: Frames per training window of a recurrent model when ``data.window`` is 0.
DEFAULT_WINDOW = 7
#: Run-section keys that may change on --resume (everything else must match the checkpoint).
RESUMABLE_RUN_KEYS = ("max_steps", "minutes", "checkpoint_every", "keep_checkpoints", "log_every", "progress",
                      "threads", "eval_every", "device", "compile")
#: User keys whose effect is recorded in ``ResolvedRun`` (compared through it for checkpoints without the record).
RESOLVED_KEYS = {"data": ("crop",), "model": ("scale", "remod_filter", "remod_filter_px")}


def recurrent_models() -> list[str]:
    """Names of the models trained on frame windows (``recurrent = True`` on their class; imports torch)."""
    from training.models import MODELS, model_class
    return [n for n in MODELS if getattr(model_class(n), "recurrent", False)]


@dataclass(frozen=True)
class ResolvedRun:
    """Everything a run derives from its configuration and clips. ``scales_by_clip``: ((clip, (s, ...)), ...) the LR
    levels trained per clip; ``scale``: the model's scale (the largest when several); ``crop``: the LR crop side in
    pixels after fitting the clips; ``window``: frames per window (0: feed-forward); ``remod_filter``: the pixel
    filter (name, px) the model remodulates with, REFERENCE resolved from the clips.
    ``notes`` (one line each) are not compared."""

    model: str
    scales_by_clip: tuple
    scales: tuple
    scale: float
    crop: int
    window: int
    recurrent: bool
    remod_filter: tuple = ("NONE", 0.0)
    notes: tuple = field(default=(), compare=False)

    def to_dict(self) -> dict:
        """Plain types for the checkpoint (weights-only loading)."""
        d = dataclasses.asdict(self)
        d.pop("notes")
        d["scales_by_clip"] = [[c, list(s)] for c, s in self.scales_by_clip]
        d["scales"] = list(self.scales)
        d["remod_filter"] = list(self.remod_filter)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ResolvedRun":
        return cls(model=d["model"], scales_by_clip=tuple((c, tuple(s)) for c, s in d["scales_by_clip"]),
                   scales=tuple(d["scales"]), scale=d["scale"], crop=int(d["crop"]), window=int(d["window"]),
                   recurrent=bool(d["recurrent"]),
                   remod_filter=tuple(d["remod_filter"]))

    def differs(self, other: "ResolvedRun") -> str | None:
        """The first field (by name) whose value differs from ``other``'s, with both values; None when equal."""
        for f in dataclasses.fields(self):
            if f.compare and getattr(self, f.name) != getattr(other, f.name):
                return f"{f.name} {_show(getattr(other, f.name))} -> {_show(getattr(self, f.name))}"
        return None

    def apply(self, cfg: TrainConfig) -> TrainConfig:
        """A copy of ``cfg`` with the derived values filled in (what the model, the loader and inference read)."""
        out = copy.deepcopy(cfg)
        out.data.crop = self.crop
        if len(self.scales) == 1:
            out.model.scale = self.scale
        out.model.remod_filter, out.model.remod_filter_px = self.remod_filter
        return out


def _show(v) -> str:
    if isinstance(v, tuple) and v and isinstance(v[0], tuple):
        return "; ".join(f"{c}: {', '.join(f'{s:g}' for s in ss)}" for c, ss in v)
    return repr(list(v)) if isinstance(v, tuple) else repr(v)


def _fmt_scales(scales) -> str:
    return ", ".join(f"{s:g}" for s in scales)


def training_scales(model_name: str, clips: dict, wanted: float) -> dict[str, list[float]]:
    """{clip: the scales (LR levels) to train on}. ``wanted`` (``model.scale``) > 0: that level of every clip.
    0: a model with ``SCALES = None`` trains on every level of every clip; any other on the one scale the clips
    have. ConfigError (one line) when a clip lacks the wanted level, when the clips offer several scales to a
    one-scale model, or when the model cannot take a clip's scale."""
    from training.models import model_class
    cls = model_class(model_name)
    if wanted:
        for c, clip in clips.items():
            if not any(abs(s - wanted) < 1e-9 for s in clip.scales):
                raise ConfigError(f"{c}: model.scale = {wanted:g} but the clip has LR levels at scale(s) "
                                  f"{_fmt_scales(clip.scales)}")
        out = {c: [float(wanted)] for c in clips}
    else:
        out = {c: list(clip.scales) for c, clip in clips.items()}
        have = sorted({s for v in out.values() for s in v})
        if cls.SCALES is not None and len(have) > 1:
            raise ConfigError(f"the training clips have LR levels at scales {_fmt_scales(have)} and model "
                              f"{model_name} trains on one scale ({cls.scales_text()}); set model.scale")
    for c, scales in out.items():
        for s in scales:
            if not cls.supports_scale(s):
                raise ConfigError(f"{c}: scale {s:g}, which model {model_name} cannot take (it supports "
                                  f"{cls.scales_text()}); set model.scale to a level it supports or render one")
    return out


def fit_crop(crop: int, levels: dict) -> tuple[int, str | None]:
    """The one crop rule: (LR crop side in pixels, note or None). ``levels``: {name: (scale, (w, h) LR size)}.
    A crop below 1, or one that is not a multiple of q at a scale p/q (crops start and end on whole HR pixels),
    is a ConfigError; a crop larger than the smallest LR side shrinks to the largest multiple of every q that fits
    it, with a one-line note."""
    grid = math.lcm(*(scale_fraction(float(s)).denominator for s, _ in levels.values()), 1)
    if crop < 1:
        raise ConfigError(f"data.crop = {crop}: must be at least 1 (LR pixels)")
    if crop % grid:
        scales = sorted({float(s) for s, _ in levels.values() if scale_fraction(float(s)).denominator > 1})
        raise ConfigError(f"data.crop = {crop} is not a multiple of {grid}, the LR crop grid of scale(s) "
                          f"{_fmt_scales(scales)}; set data.crop = {max(crop // grid * grid, grid)} or "
                          f"{(crop // grid + 1) * grid}")
    if not levels:
        return crop, None
    name, (_, (w, h)) = min(levels.items(), key=lambda kv: min(kv[1][1]))
    if crop <= min(w, h):
        return crop, None
    fitted = min(w, h) // grid * grid
    if fitted < 1:
        raise ConfigError(f"{name}: LR size {w}x{h} is smaller than the crop grid {grid} of its scale")
    return fitted, (f"note: data.crop {crop} -> {fitted}, the largest that fits {name} (LR {w}x{h}); "
                    f"set data.crop to choose another")


def remod_filter(cfg: TrainConfig, clips: dict) -> tuple:
    """(name, px): the pixel filter the model remodulates with: the ground truths' when ``model.remod_filter`` is
    REFERENCE, else the configured one."""
    if cfg.model.remod_filter != "REFERENCE":
        return (cfg.model.remod_filter, float(cfg.model.remod_filter_px))
    from gbuffer_export.pixel_filter import reference_filter as of_manifest
    refs = {of_manifest(clip.manifest) for clip in clips.values()}
    if len(refs) != 1:
        raise ConfigError(f"the training clips' ground truths use different pixel filters {sorted(refs)}; "
                          "set model.remod_filter and model.remod_filter_px")
    name, px = refs.pop()
    return (name, float(px))


def resolve_run(cfg: TrainConfig, clips: dict) -> ResolvedRun:
    """Derive the run from the user's configuration and ``clips`` ({path: open Clip}); ``cfg`` is not modified.
    ConfigError (one line) for a model/clip combination that cannot train."""
    from training.models import model_class
    scales_of = training_scales(cfg.model.name, clips, cfg.model.scale)
    scales = sorted({s for v in scales_of.values() for s in v})
    scale = scales[0] if len(scales) == 1 else scales[-1]  # several: the model reads batch['scale']
    scale = scale_value(scale)
    levels = {(f"{c} (scale {s:g})" if len(scales) > 1 else c): (s, tuple(clip.at_scale(s).sizes["lr"]))
              for c, clip in clips.items() for s in scales_of[c]}
    crop, note = fit_crop(cfg.data.crop, levels)
    recurrent = bool(getattr(model_class(cfg.model.name), "recurrent", False))
    if not recurrent and (cfg.data.window or cfg.data.detach_every):
        raise ConfigError(f"data.window / data.detach_every apply to recurrent models "
                          f"({', '.join(recurrent_models())}), not {cfg.model.name!r}")
    return ResolvedRun(model=cfg.model.name,
                       scales_by_clip=tuple((str(Path(c).resolve()), tuple(v)) for c, v in scales_of.items()),
                       scales=tuple(scales), scale=scale, crop=crop,
                       window=(cfg.data.window or DEFAULT_WINDOW) if recurrent else 0, recurrent=recurrent,
                       remod_filter=remod_filter(cfg, clips), notes=(note,) if note else ())


def run_config_toml(user: TrainConfig, run: ResolvedRun) -> str:
    """``RUN/config.toml``: the user's configuration, the one the checkpoint holds as ``user_config`` (so that
    ``--resume --config RUN/config.toml`` is the same run and a new run from it resolves the same way), preceded by
    comments giving what the run derived from it and the clips (ResolvedRun)."""
    scales = ", ".join(f"{s:g}" for s in run.scales)
    lines = ["# The configuration of this run as given; the run resumes from it:",
             "#   blendsr train -o RUN --resume --config RUN/config.toml",
             "# Derived from it and the clips (training.run.ResolvedRun; the checkpoints hold both):",
             f"#   data.crop = {run.crop}   model.scale = {run.scale:g} (LR levels {scales})   "
             f"model.remod_filter = {run.remod_filter[0]!r} ({float(run.remod_filter[1]):g} px)"
             + (f"   window = {run.window}" if run.window else ""), ""]
    return "\n".join(lines) + user.to_toml()


def write_text_atomic(path: Path, text: str, newline: str | None = None) -> None:
    """Write ``text`` to ``path`` through a temporary file and a rename (no half-written file after a crash);
    ``newline`` as ``open``'s ('' for csv text, whose line ends are its own)."""
    from gbuffer_export.clip import open_nofollow
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.unlink(missing_ok=True)  # a leftover (or a planted link) is never written through
    try:
        with os.fdopen(open_nofollow(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL), "w", encoding="utf-8",
                       newline=newline) as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


# ------------------------------------------------------------------------------------------------- starting a run
def open_clips(paths) -> dict:
    """{path: open Clip} (manifests read once), each only if its last validation passed and nothing changed since,
    or it passes now (``open_valid_clip``); radiance that is not finite or negative is the cache's to refuse, or to
    sanitise under ``data.nonfinite``, in validate's words (``training.cache.CACHE_CHECKED``)."""
    from gbuffer_export.validate.gate import open_valid_clip
    from training.cache import CACHE_CHECKED
    return {c: open_valid_clip(c, tolerate=CACHE_CHECKED) for c in paths}


def manifest_record(clips: dict) -> list[dict]:
    """[{clip (resolved path), manifest_sha256}] of ``clips``, as the checkpoint holds it."""
    from training.cache import manifest_sha256
    out = {str(Path(c).resolve()): None for c in clips}
    return [{"clip": c, "manifest_sha256": manifest_sha256(Path(c))} for c in out]


def start_run(cfg: TrainConfig | None, run_dir: Path, run_overrides: dict | None) -> tuple:
    """A new run: (configuration, clips, ResolvedRun). ``cfg`` is copied before ``run_overrides`` apply."""
    from training.models import MODELS
    if cfg is None:
        raise ConfigError("no configuration given")
    cfg = copy.deepcopy(cfg)
    for key, value in (run_overrides or {}).items():
        setattr(cfg.run, key, value)
    cfg.validate()
    refuse_existing(run_dir)
    _check_trainable(cfg, MODELS)
    clips = open_clips(cfg.data.clips)
    return cfg, clips, resolve_run(cfg, clips)


def refuse_existing(run_dir: Path) -> None:
    """FileExistsError when ``run_dir`` already holds a run (a new run never overwrites one)."""
    if (run_dir / "checkpoints" / "last.pt").exists():
        raise FileExistsError(f"{run_dir}: already holds a run (checkpoints/last.pt); pass --resume to continue or "
                              "choose another output directory")


def _check_trainable(cfg: TrainConfig, models: dict) -> None:
    if not cfg.data.clips:
        raise ConfigError("no training clips: pass --data CLIP [CLIP ...] or set data.clips")
    if not models[cfg.model.name].learned:
        raise ConfigError(f"model {cfg.model.name!r} has no weights to train; evaluate it with "
                          f"'blendsr evaluate --model {cfg.model.name}'")


def _comparable(cfg: TrainConfig, skip: dict) -> dict:
    """``cfg.to_dict()`` with resolved clip paths and the model's options as dotted keys, without ``skip``."""
    d = cfg.to_dict()
    d["data"]["clips"] = [str(Path(c).resolve()) for c in d["data"]["clips"]]
    options = d["model"].pop(cfg.model.name)
    d["model"].update({f"{cfg.model.name}.{k}": v for k, v in options.items()})
    for section, keys in skip.items():
        for k in keys:
            d[section].pop(k, None)
    return d


def _compare_configs(cfg: TrainConfig, saved: TrainConfig, source: str, skip: dict, effective: dict | None) -> None:
    """ConfigError naming the first key of ``cfg`` that differs from the checkpoint's user configuration ``saved``
    (a different model first, by name). A key whose effect is recorded in ResolvedRun (RESOLVED_KEYS) may also
    equal the checkpoint's effective value (``effective``, ``ck["config"]``): a configuration that states the
    derived value (a config.toml written before it held the user's configuration) is the same run."""
    if cfg.model.name != saved.model.name:
        raise ConfigError(f"{source}: this run is {saved.model.name}, not {cfg.model.name} (model.name differs from "
                          f"the checkpoint's); resume with model {saved.model.name} or start a new run in another "
                          "folder")
    a, b = _comparable(cfg, skip), _comparable(saved, skip)
    if not cfg.data.clips:
        a["data"]["clips"] = b["data"]["clips"]
    for k in RESUMABLE_RUN_KEYS:
        a["run"].pop(k), b["run"].pop(k)
    for section in ("data", "model", "loss", "optim", "run"):
        for k in sorted(set(a[section]) | set(b[section])):
            if a[section].get(k) == b[section].get(k):
                continue
            if k in RESOLVED_KEYS.get(section, ()) and effective and \
                    a[section].get(k) == effective.get(section, {}).get(k):
                continue
            raise ConfigError(f"{source}: {section}.{k} = {a[section].get(k)!r} differs from the checkpoint's "
                              f"{b[section].get(k)!r}; resume with the same configuration (only run.* "
                              "budget, logging and device settings may change)")


def resume_run(ck: dict, source: str, cfg: TrainConfig | None, run_overrides: dict | None,
               data: list | None = None) -> tuple:
    """Every check of ``--resume``, in one place: (configuration, clips, ResolvedRun) of the checkpoint ``ck`` read
    from ``source``. ``cfg`` (the command's configuration, or None) must match the saved user configuration except
    run.* settings in RESUMABLE_RUN_KEYS; ``data`` (clips repeated alone) must be the checkpoint's; the clips must
    resolve to the recorded ResolvedRun and have unchanged manifests. ConfigError naming the one thing that differs."""
    from training.models import MODELS
    old = ck.get("resolved") is None  # written before the record: its 'config' is already resolved
    saved = config_from_checkpoint(ck.get("user_config") or ck["config"], source=source)
    if data:
        have = sorted(str(Path(c).resolve()) for c in saved.data.clips)
        if sorted(str(Path(c).resolve()) for c in data) != have:
            raise ConfigError(f"--resume: --data differs from the checkpoint's clips ({', '.join(have)})")
    if cfg is not None:
        _compare_configs(cfg, saved, source, RESOLVED_KEYS if old else {}, None if old else ck.get("config"))
        for key in RESUMABLE_RUN_KEYS:
            setattr(saved.run, key, getattr(cfg.run, key))
    for key, value in (run_overrides or {}).items():
        if key not in RESUMABLE_RUN_KEYS:
            raise ConfigError(f"run.{key} cannot change on --resume")
        setattr(saved.run, key, value)
    saved.validate()
    _check_trainable(saved, MODELS)
    clips = open_clips(saved.data.clips)
    resolved = resolve_run(saved, clips)
    if not old:
        _same_run(resolved, ResolvedRun.from_dict(ck["resolved"]), source, "since the checkpoint (clips changed?)")
    elif cfg is not None:
        probe = copy.deepcopy(cfg)
        probe.data.clips = saved.data.clips
        _same_run(resolve_run(probe, clips), resolved, source, "from the checkpoint's")
    _same_data(ck, clips)
    if ck["sampler"]["seed"] != saved.run.seed:
        raise ConfigError(f"{source}: sampler seed differs from the checkpoint's")
    return saved, clips, resolved


def _same_run(now: ResolvedRun, then: ResolvedRun, source: str, how: str) -> None:
    diff = now.differs(then)
    if diff:
        raise ConfigError(f"{source}: the resolved {diff} differs {how}; resume with the same configuration and "
                          "clips, or start a new run")


def _same_data(ck: dict, clips: dict) -> None:
    old = {m["clip"]: m["manifest_sha256"] for m in ck["data"]}
    for m in manifest_record(clips):
        if m["clip"] in old and old[m["clip"]] != m["manifest_sha256"]:
            raise ConfigError(f"{m['clip']}: the clip changed since the checkpoint was written "
                              "(manifest hash differs); start a new run")
