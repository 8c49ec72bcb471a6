"""The training loop (torch): ``train(cfg, run_dir, resume=...)``.

Run directory::

    RUN/config.toml              the resolved configuration
    RUN/log.csv                  one row every run.log_every steps (loss terms, lr, step and data times)
    RUN/checkpoints/last.pt      the latest checkpoint; step_NNNNNNNN.pt every run.checkpoint_every steps
    RUN/summary.json             steps, time per step, fraction of time spent waiting for data, ...
    RUN/val.json                 evaluation of the held-out frames (data.val_frames > 0)

A checkpoint holds the model (and its moving average with optim.ema_decay), optimiser and scheduler states, the
RNG states (torch, numpy, python), the sampler state (seed; batch k is a pure function of seed, rank and k), the
configuration, and the manifest hashes of the training clips. ``resume`` continues from ``last.pt``: on CPU the
weights after N straight steps and after N/2 + resume + N/2 are bit-identical (tests/test_training_train.py).
Distributed data parallel runs under torchrun (gloo on CPU, NCCL on GPU); only rank 0 writes.
"""
from __future__ import annotations

import csv
import hashlib
import math
import os
import random
import signal
import statistics
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from gbuffer_export.clip import ClipError, write_json_atomic
from gbuffer_export.config import ConfigError
from training.cache import ClipCache
from training.checkpoint import (CHECKPOINT_FORMAT, CHECKPOINT_VERSION, inference_weights,  # noqa: F401
                                 load_checkpoint, numpy_rng_state, restore_numpy_rng, save_checkpoint)
from training.config import TrainConfig, config_from_checkpoint
from training.data import BatchSpec, Prefetcher, TrainSampler
from training.device import amp_dtype, autocast, cpu_bf16_supported, resolve_device  # noqa: F401  (re-exported)
from training.losses import Criterion
from training.models import MODELS, OPTIONAL_KEYS, build_model
from training.recurrent import StepWrapper, is_recurrent, window_losses

LOG_COLUMNS = ("step", "loss", "pixel", "ssim", "fft", "temporal", "perceptual", "lr", "step_ms", "data_ms",
               "samples_per_s", "elapsed_s", "mem_mb")
#: Frames per training window of a recurrent model when ``data.window`` is 0.
DEFAULT_WINDOW = 7
#: Run-section keys that may change on --resume (everything else must match the checkpoint).
RESUMABLE_RUN_KEYS = ("max_steps", "minutes", "checkpoint_every", "keep_checkpoints", "log_every", "progress",
                      "threads", "eval_every", "device", "compile")


class TrainingError(RuntimeError):
    """Training stopped (non-finite loss, broken data); the message says where."""


# ------------------------------------------------------------------------------------------------- devices
# ------------------------------------------------------------------------------------------------- helpers
def progress_kwargs(cfg, step: int) -> dict:
    """tqdm's total/initial/unit: a ``run.minutes`` budget counts seconds of that budget (its steps are unknown:
    counting to ``run.max_steps`` would show an ETA of days), otherwise steps up to ``run.max_steps``."""
    if cfg.run.minutes:
        return {"total": max(int(round(60 * cfg.run.minutes)), 1), "initial": 0, "unit": "s"}
    return {"total": cfg.run.max_steps, "initial": step, "unit": "step"}


def to_device(batch: dict, device: torch.device) -> dict[str, torch.Tensor]:
    """numpy arrays or (pinned) CPU tensors -> tensors on ``device`` (asynchronous copies where pinned)."""
    return {k: (v if isinstance(v, torch.Tensor) else torch.from_numpy(v)).to(device, non_blocking=True)
            for k, v in batch.items()}


def make_loader(sampler, step: int, cfg: TrainConfig, device: torch.device):
    """The batch source of the loop: ``loader.WorkerLoader`` with ``data.workers`` > 0 (pinned on CUDA with
    ``data.pin_memory``), else the ``data.Prefetcher`` thread. Both give batch k = sampler.batch(k)."""
    if cfg.data.workers > 0:
        from training.loader import WorkerLoader
        return WorkerLoader(sampler, step, cfg.run.max_steps, cfg.data.workers, max(cfg.data.prefetch, 1),
                            pin=cfg.data.pin_memory and device.type == "cuda")
    return Prefetcher(sampler, step, cfg.data.prefetch)


def drop_last(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The batch of the window that ends one frame earlier (every key loses its last frame; per-sample values such
    as 'scale' (B,) stay)."""
    return {k: v[:, :-1] if v.dim() > 1 else v for k, v in batch.items()}


def peak_memory_mb(device: torch.device) -> float:
    """Peak memory since the last call: CUDA memory allocated by torch on a GPU (the peak is reset), else the
    process's peak resident set size (never reset: the maximum so far)."""
    if device.type == "cuda":
        mb = torch.cuda.max_memory_allocated(device) / 2**20
        torch.cuda.reset_peak_memory_stats(device)
        return mb
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def lr_lambda(cfg: TrainConfig):
    o = cfg.optim
    total = o.decay_steps or cfg.run.max_steps

    def f(step: int) -> float:
        if o.warmup_steps and step < o.warmup_steps:
            return (step + 1) / o.warmup_steps
        if o.scheduler == "constant":
            return 1.0
        if o.scheduler == "step":
            return o.step_gamma ** (step // o.step_every)
        t = min(max(step - o.warmup_steps, 0) / max(total - o.warmup_steps, 1), 1.0)
        return o.min_lr_ratio + (1 - o.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * t))
    return f


def param_digest(model: torch.nn.Module, params_only: bool = False) -> str:
    """Short hash of the state dict (or of the parameters only: BatchNorm running statistics are per rank under
    DDP until the next forward pass broadcasts rank 0's)."""
    h = hashlib.sha256()
    items = model.named_parameters() if params_only else model.state_dict().items()
    for k, v in items:
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def make_ema(model: torch.nn.Module, decay: float, ck: dict | None):
    """The exponential moving average of ``model``'s weights and buffers (torch.optim.swa_utils.AveragedModel),
    restored from the checkpoint ``ck`` when resuming; None when ``decay`` is 0. After update k the average is
    w_1 for k = 1, else decay * avg + (1 - decay) * w_k."""
    if not decay:
        return None
    from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
    ema = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(decay), use_buffers=True)
    if ck is not None and ck.get("ema_model") is not None:
        ema.module.load_state_dict(ck["ema_model"])
        ema.n_averaged.fill_(int(ck["ema_updates"]))
    return ema


def fit_crop(cfg: TrainConfig, clips: dict, log=None) -> None:
    """Shrink the default ``data.crop`` to the smallest LR side of ``clips`` (with a note); a crop set to
    another value that does not fit is a ConfigError that names the largest one that does."""
    from training.config import DataConfig
    sides = {c: min(clip.sizes["lr"]) for c, clip in clips.items()}
    if not sides or cfg.data.crop <= min(sides.values()):
        return
    c, side = min(sides.items(), key=lambda kv: kv[1])
    w, h = clips[c].sizes["lr"]
    if cfg.data.crop != DataConfig().crop:
        raise ConfigError(f"{c}: LR size {w}x{h} is smaller than data.crop = {cfg.data.crop}; "
                          f"--set data.crop={side} (or less) fits every clip")
    if log is not None:
        log(f"note: data.crop {cfg.data.crop} -> {side}, the largest that fits {c} (LR {w}x{h}); "
            f"set data.crop to choose another")
    cfg.data.crop = side


def unwrap(model):
    model = getattr(model, "module", model)
    model = getattr(model, "_orig_mod", model)
    return model.model if isinstance(model, StepWrapper) else model


class Dist:
    """torchrun environment (WORLD_SIZE, RANK, LOCAL_RANK); a no-op for a single process."""

    def __init__(self, device_name: str):
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = int(os.environ.get("RANK", "0"))
        self.local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        self.enabled = self.world > 1
        device = resolve_device(device_name, "run.device")
        if device.type == "cuda" and self.enabled:
            device = torch.device("cuda", self.local_rank)
            torch.cuda.set_device(device)
        self.device = device
        if self.enabled and not torch.distributed.is_initialized():
            backend = "nccl" if device.type == "cuda" else "gloo"
            torch.distributed.init_process_group(backend=backend)

    @property
    def main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        if self.enabled:
            torch.distributed.barrier()

    def any(self, flag: bool) -> bool:
        """True on every rank when ``flag`` is true on any rank."""
        if not self.enabled:
            return flag
        t = torch.tensor([1.0 if flag else 0.0], device=self.device)
        torch.distributed.all_reduce(t)
        return bool(t.item() > 0)

    def close(self) -> None:
        if self.enabled and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()


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


def open_caches(clips, data_cfg, keys, dist: Dist | None = None, scales: dict | None = None) -> list[ClipCache]:
    """Open (and build where needed) the caches of ``clips``, one per clip and scale of ``scales`` ({clip: [s]};
    None: each clip's level 'lr'); rank 0 builds first."""
    caches = []
    for c in clips:
        for s in (scales or {}).get(c, [None]):
            caches.append(ClipCache(c, eps=data_cfg.demod_eps, nonfinite=data_cfg.nonfinite,
                                    cache_dir=data_cfg.cache_dir or None, scale=s))
    if dist is not None and dist.enabled and not dist.main:
        dist.barrier()
    for cache in caches:
        cache.ensure([k for k in keys if cache.has(k) or k not in OPTIONAL_KEYS])
    if dist is not None and dist.enabled and dist.main:
        dist.barrier()
    return caches


# ------------------------------------------------------------------------------------------------- train
def _comparable(cfg: TrainConfig) -> dict:
    """``cfg.to_dict()`` with resolved clip paths, without model.scale, the model's options as dotted keys."""
    d = cfg.to_dict()
    d["data"]["clips"] = [str(Path(c).resolve()) for c in d["data"]["clips"]]
    d["model"].pop("scale")
    options = d["model"].pop(cfg.model.name)
    d["model"].update({f"{cfg.model.name}.{k}": v for k, v in options.items()})
    return d


def resumed_config(ck: dict, cfg: TrainConfig | None, run_overrides: dict | None, source: str) -> TrainConfig:
    """The checkpoint's configuration with run.* settings from ``cfg`` / ``run_overrides``. ``cfg`` (when given)
    must otherwise match the checkpoint's (clips compared as resolved paths)."""
    saved = config_from_checkpoint(ck["config"], source=source)
    if cfg is not None:
        a, b = _comparable(cfg), _comparable(saved)
        if not cfg.data.clips:
            a["data"]["clips"] = b["data"]["clips"]
        if a["model"].get("remod_filter") == "REFERENCE":  # the checkpoint holds what REFERENCE resolved to
            for k in ("remod_filter", "remod_filter_px"):
                a["model"][k] = b["model"].get(k)
        for section in ("data", "model", "loss", "optim"):
            if a[section] != b[section]:
                diff = [k for k in a[section] if a[section][k] != b[section].get(k)]
                raise ConfigError(f"{source}: {section}.{diff[0]} differs from the checkpoint's; resume with the "
                                  "same configuration (only run.* settings may change)")
        for key in RESUMABLE_RUN_KEYS:
            setattr(saved.run, key, getattr(cfg.run, key))
    for key, value in (run_overrides or {}).items():
        if key not in RESUMABLE_RUN_KEYS:
            raise ConfigError(f"run.{key} cannot change on --resume")
        setattr(saved.run, key, value)
    return saved.validate()


def train(cfg: TrainConfig | None, run_dir: str | os.PathLike, *, resume: bool = False,
          run_overrides: dict | None = None, stop_at: int | None = None, log=print) -> dict:
    """Train ``cfg.model.name`` on ``cfg.data.clips`` into ``run_dir``; returns the summary dict.
    With ``resume`` the checkpoint's configuration is used (``cfg`` may be None; see ``resumed_config``).
    ``stop_at`` stops after that step as if interrupted (checkpoint written), for tests."""
    run_dir = Path(run_dir)
    last = run_dir / "checkpoints" / "last.pt"
    ck = None
    if resume:
        ck = load_checkpoint(last)
        cfg = resumed_config(ck, cfg, run_overrides, str(last))
    elif cfg is None:
        raise ConfigError("no configuration given")
    else:
        for key, value in (run_overrides or {}).items():
            setattr(cfg.run, key, value)
        cfg.validate()
    if not resume and last.exists():
        raise FileExistsError(f"{run_dir}: already holds a run (checkpoints/last.pt); pass --resume to continue or "
                              "choose another output directory")
    if not cfg.data.clips:
        raise ConfigError("no training clips: pass --data CLIP [CLIP ...] or set data.clips")
    if not MODELS[cfg.model.name].learned:
        raise ConfigError(f"model {cfg.model.name!r} has no weights to train; evaluate it with "
                          f"'blendsr evaluate --model {cfg.model.name}'")

    dist = Dist(cfg.run.device)
    device = dist.device
    if dist.main and cfg.run.minutes and cfg.optim.scheduler == "cosine":
        log(f"note: the cosine schedule decays over {cfg.optim.decay_steps or cfg.run.max_steps} steps "
            f"(optim.decay_steps or run.max_steps) whatever the {cfg.run.minutes:g}-minute budget")
    if cfg.run.threads:
        torch.set_num_threads(cfg.run.threads)
    random.seed(cfg.run.seed)
    np.random.seed(cfg.run.seed % 2**32)
    torch.manual_seed(cfg.run.seed)

    # Data: scales from the clips and what the model takes, then the model, then what it reads.
    from gbuffer_export.clip import open_clip
    clips = {c: open_clip(c) for c in cfg.data.clips}  # manifests read once
    scales_of = training_scales(cfg.model.name, clips, cfg.model.scale)
    all_scales = sorted({s for v in scales_of.values() for s in v})
    scale = all_scales[0] if len(all_scales) == 1 else all_scales[-1]  # several: the model reads batch['scale']
    scale = int(scale) if float(scale).is_integer() else scale
    if len(all_scales) == 1:
        cfg.model.scale = scale
    fit_crop(cfg, {f"{c} (scale {s:g})" if len(all_scales) > 1 else c: clip.at_scale(s)
                   for c, clip in clips.items() for s in scales_of[c]}, log if dist.main else None)
    if cfg.model.remod_filter == "REFERENCE":  # resolved once into the saved configuration
        from gbuffer_export.pixel_filter import reference_filter
        refs = {reference_filter(clip.manifest) for clip in clips.values()}
        if len(refs) != 1:
            raise ConfigError(f"the training clips' ground truths use different pixel filters {sorted(refs)}; "
                              "set model.remod_filter and model.remod_filter_px")
        cfg.model.remod_filter, cfg.model.remod_filter_px = refs.pop()
    model = build_model(cfg.model, scale)
    if cfg.run.init_from and not resume:  # fine-tuning: the weights of another run (its configuration must match)
        init = load_checkpoint(cfg.run.init_from)
        if model.SCALES is not None and float(init["scale"]) != float(scale):
            raise ConfigError(f"run.init_from {cfg.run.init_from}: trained for scale {init['scale']}, not {scale}")
        try:
            model.load_state_dict({k: v.float() if v.is_floating_point() else v
                                   for k, v in inference_weights(init).items()})
        except RuntimeError as exc:
            raise ConfigError(f"run.init_from {cfg.run.init_from}: its weights do not fit model {cfg.model.name} "
                              f"with this configuration ({str(exc).splitlines()[0]})") from None
        log(f"initialised {cfg.model.name} from {cfg.run.init_from} (step {init.get('step')})")
    model.fast_ops = True  # the non-learned parts with fewer kernels (training.models.fast_ops); same values
    for c, clip in clips.items():
        mismatch = model.remod_filter_mismatch(clip.manifest, c)
        if mismatch:
            raise ConfigError(mismatch + "; set them to the clip's filter, or model.remod_filter = \"NONE\"")
    temporal = cfg.loss.temporal_weight > 0
    recurrent = is_recurrent(model)
    window = (cfg.data.window or DEFAULT_WINDOW) if recurrent else 0
    if not recurrent and (cfg.data.window or cfg.data.detach_every):
        raise ConfigError(f"data.window / data.detach_every apply to recurrent models (rdg, rdg-s, nsrr-fec), not "
                          f"{cfg.model.name!r}")
    spec = BatchSpec.for_model(model, temporal=temporal and (not recurrent or cfg.loss.temporal == "warped"),
                               window=window, crop=cfg.data.crop, flip=cfg.data.augment_flip,
                               rotate=cfg.data.augment_rotate, exposure_range=tuple(cfg.data.exposure_range),
                               reflectance_range=tuple(cfg.data.reflectance_range))
    try:
        caches = open_caches(cfg.data.clips, cfg.data, spec.cache_keys, dist, scales_of)
    except ClipError as exc:
        if "has no buffer" not in str(exc):
            raise
        raise ClipError(f"{exc}; model {cfg.model.name!r} reads more buffers than these clips have: render them "
                        f"with 'blendsr render --for-models {cfg.model.name}' (or 'blendsr dataset ... "
                        f"--for-models {cfg.model.name}')") from None
    manifests = list({str(Path(c.clip_path).resolve()): {"clip": str(Path(c.clip_path).resolve()),
                                                          "manifest_sha256": c.manifest_sha256}
                      for c in caches}.values())
    if ck is not None:
        old = {m["clip"]: m["manifest_sha256"] for m in ck["data"]}
        for m in manifests:
            if m["clip"] in old and old[m["clip"]] != m["manifest_sha256"]:
                raise ConfigError(f"{m['clip']}: the clip changed since the checkpoint was written "
                                  "(manifest hash differs); start a new run")
    sampler = TrainSampler(caches, spec, cfg.data.batch_size, cfg.run.seed, dist.rank, cfg.data.val_frames)

    model.to(device)
    criterion = Criterion(cfg.loss).to(device)
    opt_cls = torch.optim.AdamW if cfg.optim.weight_decay > 0 else torch.optim.Adam
    optimizer = opt_cls(model.parameters(), lr=cfg.optim.lr, betas=tuple(cfg.optim.betas),
                        weight_decay=cfg.optim.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lr_lambda(cfg))
    step = 0
    elapsed_before = 0.0
    if ck is not None:
        model.load_state_dict(ck["model"])
        optimizer.load_state_dict(ck["optimizer"])
        scheduler.load_state_dict(ck["scheduler"])
        rng = ck["rng"]
        torch.set_rng_state(rng["torch"])
        restore_numpy_rng(rng["numpy"])
        random.setstate(rng["python"])
        if device.type == "cuda" and rng.get("cuda") is not None:
            torch.cuda.set_rng_state_all(rng["cuda"])
        step = int(ck["step"])
        elapsed_before = float(ck.get("elapsed_s", 0.0))
        if ck["sampler"]["seed"] != sampler.seed:
            raise ConfigError(f"{last}: sampler seed differs from the checkpoint's")
    ema = make_ema(model, cfg.optim.ema_decay, ck)
    dtype = amp_dtype(cfg.run.amp, device)
    scaler = torch.amp.GradScaler("cuda") if (dtype == torch.float16 and device.type == "cuda") else None
    if ck is not None and scaler is not None and ck.get("scaler"):
        scaler.load_state_dict(ck["scaler"])
    net = model
    if dist.enabled and any(isinstance(m, torch.nn.modules.batchnorm._BatchNorm) for m in model.modules()):
        if device.type == "cuda":  # same Parameter objects: the optimiser and the checkpoint keys are unchanged
            model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
            net = model
        elif dist.main:
            warnings.warn(f"model.{cfg.model.name}.norm = 'batch' under DDP on CPU: BatchNorm statistics are per "
                          "rank (torch's SyncBatchNorm needs a GPU)", RuntimeWarning)
    if dist.enabled and not recurrent:
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None)
    if recurrent:  # several forward/backward passes per step: no DDP wrapper, gradients averaged by hand
        net = StepWrapper(model)
        if dist.enabled:
            for p in model.parameters():
                torch.distributed.broadcast(p.data, 0)
    if cfg.run.compile:
        net = torch.compile(net)

    if dist.main:
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "config.toml").write_text(cfg.to_toml())
    logf = None
    writer = None
    if dist.main:
        new = not (run_dir / "log.csv").exists()
        logf = open(run_dir / "log.csv", "a", newline="")
        writer = csv.writer(logf)
        if new:
            writer.writerow(LOG_COLUMNS)
    tb = None
    if dist.main:
        try:
            from torch.utils.tensorboard import SummaryWriter
            tb = SummaryWriter(str(run_dir / "tensorboard"))
        except ImportError:
            tb = None

    def state(cur_step: int, elapsed: float) -> dict:
        return {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "model_name": cfg.model.name, "scale": scale,
                "scales": all_scales,
                "step": cur_step, "config": cfg.to_dict(), "model": unwrap(net).state_dict(),
                "ema_model": ema.module.state_dict() if ema is not None else None,
                "ema_updates": int(ema.n_averaged) if ema is not None else 0,
                "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
                "scaler": scaler.state_dict() if scaler is not None else None,
                "rng": {"torch": torch.get_rng_state(), "numpy": numpy_rng_state(), "python": random.getstate(),
                        "cuda": torch.cuda.get_rng_state_all() if device.type == "cuda" else None},
                "sampler": {**sampler.state_dict(), "next_step": cur_step}, "data": manifests,
                "world_size": dist.world, "elapsed_s": elapsed, "device": str(device),
                "amp": str(dtype).replace("torch.", "") if dtype else "none"}

    def evaluated() -> torch.nn.Module:
        """The weights the run's evaluations use: the moving average when there is one."""
        return ema.module if ema is not None else unwrap(net)

    def checkpoint(cur_step: int, elapsed: float, numbered: bool) -> None:
        if not dist.main:
            return
        st = state(cur_step, elapsed)
        save_checkpoint(last, st)
        if numbered:
            save_checkpoint(run_dir / "checkpoints" / f"step_{cur_step:08d}.pt", st)
            olds = sorted((run_dir / "checkpoints").glob("step_*.pt"))
            for p in olds[:max(len(olds) - cfg.run.keep_checkpoints, 0)]:
                p.unlink()

    stop_requested = {"flag": False}

    def on_term(signum, frame):
        stop_requested["flag"] = True
    old_handler = None
    try:
        old_handler = signal.signal(signal.SIGTERM, on_term)
    except ValueError:  # not in the main thread
        pass

    def backward(chunk: torch.Tensor) -> None:
        (scaler.scale(chunk) if scaler is not None else chunk).backward()

    bar = None
    if cfg.run.progress and dist.main:
        from tqdm import tqdm
        bar = tqdm(**progress_kwargs(cfg, step), desc=f"train {cfg.model.name}", dynamic_ncols=True)
    prefetch = make_loader(sampler, step, cfg, device)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True  # fixed crop size: cuDNN picks its fastest algorithms once
        torch.cuda.reset_peak_memory_stats(device)
    t_start = time.perf_counter()
    step_times: list[float] = []
    mem_peak = 0.0
    data_times: list[float] = []
    net.train()
    reason = "max_steps"
    interrupted = False
    try:
        while step < cfg.run.max_steps:
            t0 = time.perf_counter()
            batch_np, samples = prefetch.get(step)
            batch = to_device(batch_np, device)
            t1 = time.perf_counter()
            if recurrent:  # back-propagates chunk by chunk (training.recurrent)
                optimizer.zero_grad(set_to_none=True)
                loss, terms, sr = window_losses(net, criterion, batch, cfg.data.detach_every or window,
                                                backward, temporal, lambda: autocast(device, dtype))
            else:
                with autocast(device, dtype):
                    sr = net(batch).float()
                    sr_prev = net(drop_last(batch)).float() if temporal else None
                gt = batch["hr/radiance"][:, -1]
                loss, terms = criterion(sr, gt, sr_prev,
                                        batch["hr/radiance"][:, -2] if temporal else None,
                                        batch["hr/motion"][:, -1] if temporal else None)
            bad = not bool(torch.isfinite(loss))
            if dist.any(bad):
                where = "; ".join(f"{s.clip} frames {s.frames[0]}-{s.frames[-1]}" for s in samples)
                bad_sr = not bool(torch.isfinite(sr).all())
                raise TrainingError(f"loss became {loss.item()} at step {step + 1} (rank {dist.rank}; "
                                    f"{'the model output' if bad_sr else 'a loss term'} is not finite; batch: "
                                    f"{where}); training stopped, "
                                    + (f"last checkpoint: {last}" if last.is_file() else "no checkpoint was written "
                                       "before it"))
            if not recurrent:
                optimizer.zero_grad(set_to_none=True)
                backward(loss)
            elif dist.enabled:
                for p in model.parameters():
                    if p.requires_grad:
                        if p.grad is None:
                            p.grad = torch.zeros_like(p)
                        torch.distributed.all_reduce(p.grad)
                        p.grad /= dist.world
            if scaler is not None:
                scaler.unscale_(optimizer)
            if cfg.optim.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.optim.grad_clip)
            if scaler is not None:
                scaler.step(optimizer)
                scaler.update()
            else:
                optimizer.step()
            scheduler.step()
            if ema is not None:
                ema.update_parameters(model)
            step += 1
            t2 = time.perf_counter()
            step_times.append(t2 - t0)
            data_times.append(t1 - t0)
            elapsed = elapsed_before + (t2 - t_start)
            if bar is not None:
                if cfg.run.minutes:  # a time budget: the bar counts its seconds, the postfix the steps
                    bar.update(max(min(int(elapsed - elapsed_before), bar.total) - bar.n, 0))
                else:
                    bar.update(1)
                post = {"step": step} if cfg.run.minutes else {}
                post |= {"loss": f"{loss.item():.4f}",
                        "samples_s": f"{cfg.data.batch_size * dist.world / (t2 - t0):.1f}"}
                if cfg.run.minutes:  # the time budget often ends the run long before max_steps (bar's ETA)
                    post["min_left"] = f"{max(cfg.run.minutes - (elapsed - elapsed_before) / 60, 0):.1f}"
                bar.set_postfix(post)
            if step % cfg.run.log_every == 0 or step == cfg.run.max_steps:
                row = {"step": step, "loss": loss.item(), **{k: v.item() for k, v in terms.items()},
                       "lr": scheduler.get_last_lr()[0], "step_ms": 1000 * (t2 - t0), "data_ms": 1000 * (t1 - t0),
                       "samples_per_s": cfg.data.batch_size * dist.world / (t2 - t0), "elapsed_s": elapsed,
                       "mem_mb": peak_memory_mb(device)}
                mem_peak = max(mem_peak, row["mem_mb"])
                if writer is not None:
                    writer.writerow(["" if row.get(c) is None else row.get(c, "") for c in LOG_COLUMNS])
                    logf.flush()
                if tb is not None:
                    for k, v in row.items():
                        if k != "step":
                            tb.add_scalar(k, v, step)
            if step % cfg.run.checkpoint_every == 0 and step < cfg.run.max_steps:
                checkpoint(step, elapsed, numbered=True)
            if cfg.run.eval_every and step % cfg.run.eval_every == 0 and dist.main:
                if cfg.data.val_frames:
                    _validate(evaluated(), caches, cfg, run_dir / f"val_step_{step:08d}.json", device, dtype)
                if cfg.data.val_clips:
                    _validate_clips(evaluated(), cfg, run_dir / f"val_clips_step_{step:08d}.json", device, dtype)
                net.train()
            stop_time = bool(cfg.run.minutes) and elapsed - elapsed_before >= 60 * cfg.run.minutes
            stop_now = dist.any(stop_time or stop_requested["flag"] or (stop_at is not None and step >= stop_at))
            if stop_now:
                reason = "minutes" if stop_time else ("signal" if stop_requested["flag"] else "stop_at")
                break
    except KeyboardInterrupt:
        interrupted = True
        reason = "interrupted"
        raise
    finally:
        prefetch.close()
        if bar is not None:
            bar.close()
        elapsed = elapsed_before + (time.perf_counter() - t_start)
        # On an exception other than an interrupt the last checkpoint stays the last good one.
        import sys
        exc = sys.exc_info()[1]
        if exc is None or interrupted:
            checkpoint(step, elapsed, numbered=(exc is None and step == cfg.run.max_steps))
        if old_handler is not None:
            signal.signal(signal.SIGTERM, old_handler)
        if logf is not None:
            logf.close()
        if tb is not None:
            tb.close()

    summary = {"model": cfg.model.name, "step": step, "max_steps": cfg.run.max_steps, "stopped_by": reason,
               "device": str(device), "amp": str(dtype).replace("torch.", "") if dtype else "none",
               "world_size": dist.world, "threads": torch.get_num_threads(), "batch_size": cfg.data.batch_size,
               "crop_lr": cfg.data.crop, "scale": scale, "scales": all_scales,
               "params": sum(p.numel() for p in model.parameters()),
               "elapsed_s": elapsed, "window": window or None, "peak_mem_mb": mem_peak or None}
    if len(step_times) > 2:
        st, dt = step_times[2:], data_times[2:]
        summary.update(median_step_ms=1000 * statistics.median(st), median_data_ms=1000 * statistics.median(dt),
                       data_fraction=sum(dt) / sum(st), steps_per_s=len(st) / sum(st),
                       samples_per_s=len(st) * cfg.data.batch_size * dist.world / sum(st))
    summary["workers"] = cfg.data.workers
    summary["gpu_max_memory_mb"] = (torch.cuda.max_memory_allocated(device) / 2 ** 20
                                    if device.type == "cuda" else None)
    try:
        import resource
        summary["max_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    except (ImportError, OSError):
        summary["max_rss_mb"] = None
    if dist.enabled:
        digest = param_digest(unwrap(net), params_only=True)
        digests = [None] * dist.world
        torch.distributed.all_gather_object(digests, digest)
        summary["ranks_agree"] = len(set(digests)) == 1
        if not summary["ranks_agree"]:
            warnings.warn(f"DDP ranks hold different weights: {digests}", RuntimeWarning)
    summary["param_digest"] = param_digest(unwrap(net))
    summary["weights"] = "ema" if ema is not None else "trained"  # what inference, evaluation and release use
    if dist.main:
        if cfg.data.val_frames and reason in ("max_steps", "minutes"):
            summary["val"] = _validate(evaluated(), caches, cfg, run_dir / "val.json", device, dtype)["mean"]
        if cfg.data.val_clips and reason in ("max_steps", "minutes"):
            summary["val_clips"] = _validate_clips(evaluated(), cfg, run_dir / "val_clips.json", device, dtype)["mean"]
        write_json_atomic(run_dir / "summary.json", summary)
        log(f"trained {cfg.model.name} to step {step} ({reason}) in {elapsed:.1f} s; checkpoint {last}")
    dist.barrier()
    dist.close()
    return summary


def _validate_clips(model, cfg: TrainConfig, out: Path, device, dtype) -> dict:
    """Evaluate the whole ``data.val_clips`` (clips never trained on); writes ``out``."""
    from training.evaluate import evaluate_model
    result = evaluate_model(model, list(cfg.data.val_clips), device=device, amp=dtype, flip=False, data_cfg=cfg.data)
    write_json_atomic(out, result)
    model.train()
    return result


def _validate(model, caches, cfg: TrainConfig, out: Path, device, dtype) -> dict:
    """Evaluate the held-out last ``data.val_frames`` frames of every training clip; writes ``out``."""
    from training.evaluate import evaluate_model
    frames = {str(c.clip_path): c.frames[-cfg.data.val_frames:] for c in caches}
    scales: dict[str, list[float]] = {}
    for c in caches:  # one cache per clip and scale
        scales.setdefault(str(c.clip_path), []).append(float(c.scale))
    result = evaluate_model(model, list(dict.fromkeys(c.clip_path for c in caches)), frames=frames, device=device,
                            amp=dtype, flip=False, data_cfg=cfg.data, scales=scales)
    write_json_atomic(out, result)
    model.train()
    return result
