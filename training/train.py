"""The training loop (torch): ``train(cfg, run_dir, resume=...)``, a short loop over a ``training.trainer.Trainer``
and its hooks (``training.hooks``); what the run derives from the configuration and every resume check are in
``training.run``.

Run directory::

    RUN/.lock                    held by rank 0 for the whole run (one ``blendsr train`` per run folder)
    RUN/config.toml              the user's configuration (what the checkpoint holds as ``user_config``: the run
                                 resumes from it), the values derived from it and the clips as comments
    RUN/log.csv                  one row every run.log_every steps (loss terms, lr, step and data times)
    RUN/checkpoints/last.pt      the latest checkpoint; step_NNNNNNNN.pt every run.checkpoint_every steps
    RUN/summary.json             steps, time per step, fraction of time spent waiting for data, ...
    RUN/val.json                 evaluation of the held-out frames (data.val_frames > 0)

A checkpoint holds the model (and its moving average with optim.ema_decay), optimiser and scheduler states, the
RNG states (torch, numpy, python), the sampler state (seed; batch k is a pure function of seed, rank and k), the
user's configuration, the ResolvedRun (``training.run``), the effective configuration, and the manifest hashes of
the training clips. ``resume`` continues from ``last.pt``: on CPU the
weights after N straight steps and after N/2 + resume + N/2 are bit-identical (tests/train/test_train.py).
Distributed data parallel runs under torchrun (gloo on CPU, NCCL on GPU); only rank 0 writes.
"""
from __future__ import annotations

import logging
import os
import random
import signal
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from gbuffer_export.clip import ClipError, write_json_atomic
from gbuffer_export.config import ConfigError
from gbuffer_export.locks import FolderLock
from training.cache import ClipCache
from training.checkpoint import inference_weights, load_checkpoint
from training.config import TrainConfig
from training.data import BatchSpec, Prefetcher, TrainSampler
from training.device import set_threads
from training.hooks import Checkpoints, Evaluations, RunLog, StepInfo
from training.models import OPTIONAL_KEYS, build_model
from training.run import (ResolvedRun, manifest_record, refuse_existing, resume_run, run_config_toml, start_run,
                          write_text_atomic)
from training.trainer import Dist, Trainer, TrainingError, baseline_models, param_digest, to_device, unwrap

__all__ = ["train", "TrainingError", "param_digest", "open_caches", "make_loader"]
logger = logging.getLogger(__name__)


def make_loader(sampler, step: int, cfg: TrainConfig, device: torch.device):
    """The batch source of the loop: ``loader.WorkerLoader`` with ``data.workers`` > 0 (pinned on CUDA with
    ``data.pin_memory``), else the ``data.Prefetcher`` thread. Both give batch k = sampler.batch(k)."""
    if cfg.data.workers > 0:
        from training.loader import WorkerLoader
        return WorkerLoader(sampler, step, cfg.run.max_steps, cfg.data.workers, max(cfg.data.prefetch, 1),
                            pin=cfg.data.pin_memory and device.type == "cuda")
    return Prefetcher(sampler, step, cfg.data.prefetch)


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


def lock_run(run_dir: Path, create: bool) -> FolderLock | None:
    """``RUN/.lock`` held by rank 0 for the whole run (None on other ranks, or for a missing folder on resume)."""
    if int(os.environ.get("RANK", "0")) != 0 or not (create or run_dir.is_dir()):
        return None
    run_dir.mkdir(parents=True, exist_ok=True)
    return FolderLock(run_dir, "another 'blendsr train' is writing this run folder")


# ------------------------------------------------------------------------------------------------- set-up
def init_from(model, cfg: TrainConfig, scale) -> None:
    """Fine-tuning: load ``run.init_from``'s weights into ``model`` (ConfigError when they do not fit)."""
    init = load_checkpoint(cfg.run.init_from)
    if model.SCALES is not None and float(init["scale"]) != float(scale):
        raise ConfigError(f"run.init_from {cfg.run.init_from}: trained for scale {init['scale']}, not {scale}")
    weights = {k: v.float() if v.is_floating_point() else v for k, v in inference_weights(init).items()}
    own = model.state_dict()
    fresh = [k for k in getattr(model, "FRESH_PARAMETERS", ()) if k in own and k not in weights]
    grown = [k for k in getattr(model, "GROWN_INPUTS", ()) if k in own and k in weights and
             grows_inputs(weights[k], own[k])]
    for k in grown:  # input channels an option appends: zero weights on them, so the network starts as the weights'
        weights[k] = torch.cat([weights[k], own[k].new_zeros((own[k].shape[0], own[k].shape[1] - weights[k].shape[1],
                                                              *own[k].shape[2:]))], dim=1)
    try:
        model.load_state_dict(weights | {k: own[k] for k in fresh})
    except RuntimeError as exc:
        raise ConfigError(f"run.init_from {cfg.run.init_from}: its weights do not fit model {cfg.model.name} "
                          f"with this configuration ({str(exc).splitlines()[0]})") from None
    started = f"; {', '.join(fresh)} start fresh (an option its run did not have)" if fresh else ""
    started += f"; {', '.join(grown)} gain zero-weighted input channels (an option its run did not have)" \
        if grown else ""
    logger.info(f"initialised {cfg.model.name} from {cfg.run.init_from} (step {init.get('step')}){started}")


def grows_inputs(theirs, ours) -> bool:
    """True when conv weight ``ours`` is ``theirs`` with more input channels (dim 1) and the same other sizes."""
    return (theirs.dim() == ours.dim() == 4 and theirs.shape[0] == ours.shape[0] and theirs.shape[2:] == ours.shape[2:]
            and theirs.shape[1] < ours.shape[1])


def init_record(cfg: TrainConfig, ck: dict | None) -> dict | None:
    """What ``run.init_from`` read when the run started: its spec, the sha256 of that file and, for weights with a
    JSON beside them, their ``param_digest``; kept in every checkpoint (a resumed run keeps its first one), so that a
    release can tell whether the shipped weights it started from are still the ones shipped; None without
    ``run.init_from``."""
    if ck is not None:
        return ck.get("init")
    if not cfg.run.init_from:
        return None
    import json

    from training.checkpoint import file_sha256
    from training.pretrained import resolve
    path = Path(resolve(cfg.run.init_from))
    out = {"from": cfg.run.init_from, "sha256": file_sha256(path)}
    if path.suffix == ".safetensors" and path.with_suffix(".json").is_file():  # the same tensors under a new header
        out["param_digest"] = json.loads(path.with_suffix(".json").read_text()).get("param_digest")
    return out


def open_model_caches(cfg: TrainConfig, run: ResolvedRun, clips: dict, spec, dist: Dist, baseline) -> dict:
    """The clips' caches of ``spec``'s buffers; a clip without one the model (or the baseline of
    ``loss.baseline_weight``) reads is a ClipError that says how to render it."""
    scales_of = {c: list(dict(run.scales_by_clip)[str(Path(c).resolve())]) for c in clips}
    try:
        return open_caches(cfg.data.clips, cfg.data, spec.cache_keys, dist, scales_of)
    except ClipError as exc:
        if "has no buffer" not in str(exc):
            raise
        names = cfg.model.name + (",demod-jbu" if baseline is not None else "")
        reads = " (and demod-jbu's, for loss.baseline_weight)" if baseline is not None else ""
        raise ClipError(f"{exc}; model {cfg.model.name!r} reads more buffers{reads} than these clips have: render "
                        f"them with 'blendsr render --for-models {names}' (or 'blendsr dataset ... "
                        f"--for-models {names}')") from None


def build_trainer(cfg: TrainConfig, run: ResolvedRun, clips: dict, dist: Dist, ck: dict | None):
    """Seeds, model, caches, sampler and Trainer (restored from ``ck`` when resuming); returns (trainer, caches).
    ``cfg`` is the effective configuration."""
    set_threads(cfg.run.threads)
    random.seed(cfg.run.seed)
    np.random.seed(cfg.run.seed % 2**32)
    torch.manual_seed(cfg.run.seed)
    model = build_model(cfg.model, run.scale)
    if cfg.run.init_from and ck is None:
        init_from(model, cfg, run.scale)
    model.fast_ops = True  # the non-learned parts with fewer kernels (training.models.fast_ops); same values
    for c, clip in clips.items():
        mismatch = model.remod_filter_mismatch(clip.manifest, c)
        if mismatch:
            raise ConfigError(mismatch + "; set them to the clip's filter, or model.remod_filter = \"NONE\"")
    temporal = cfg.loss.temporal_weight > 0
    baselines = baseline_models(cfg, run.scales)
    baseline = next(iter(baselines.values()), None)  # its inputs are those of every scale
    spec = BatchSpec.for_model(model, temporal=temporal and (not run.recurrent or cfg.loss.temporal == "warped"),
                               also=baseline, window=run.window, crop=run.crop, flip=cfg.data.augment_flip,
                               rotate=cfg.data.augment_rotate, exposure_range=tuple(cfg.data.exposure_range),
                               reflectance_range=tuple(cfg.data.reflectance_range))
    caches = open_model_caches(cfg, run, clips, spec, dist, baseline)
    sampler = TrainSampler(caches, spec, cfg.data.batch_size, cfg.run.seed, dist.rank, cfg.data.val_frames)
    trainer = Trainer(cfg, run, model, sampler, dist, baselines=baselines)
    if ck is not None:
        trainer.load_state_dict(ck)
    trainer.wrap()
    return trainer, caches


# ------------------------------------------------------------------------------------------------- train
def train(cfg: TrainConfig | None, run_dir: str | os.PathLike, *, resume: bool = False,
          run_overrides: dict | None = None, stop_at: int | None = None, data: list | None = None) -> dict:
    """Train ``cfg.model.name`` on ``cfg.data.clips`` into ``run_dir``; returns the summary dict. ``cfg`` is not
    modified. With ``resume`` the checkpoint's configuration is used (``cfg`` may be None; ``data``: clips repeated
    alone; see ``training.run.resume_run``). ``stop_at`` stops after that step as if interrupted (checkpoint
    written), for tests. Notes go to ``logging`` (rank 0 only)."""
    run_dir = Path(run_dir)
    last = run_dir / "checkpoints" / "last.pt"
    lock = lock_run(run_dir, create=False) if resume else None
    try:
        if resume:
            ck = load_checkpoint(last)
            cfg, clips, run = resume_run(ck, str(last), cfg, run_overrides, data)
        else:
            ck = None
            cfg, clips, run = start_run(cfg, run_dir, run_overrides)
            lock = lock_run(run_dir, create=True)
            refuse_existing(run_dir)  # again under the lock: nobody wrote a run here meanwhile
        return _train(cfg, run, clips, run_dir, ck, stop_at)
    finally:
        if lock is not None:
            lock.close()


def _train(user: TrainConfig, run: ResolvedRun, clips: dict, run_dir: Path, ck, stop_at) -> dict:
    dist = Dist(user.run.device)
    cfg = run.apply(user)
    if dist.main:
        for note in run.notes:
            logger.info(note)
        if cfg.run.minutes and cfg.optim.scheduler == "cosine":
            logger.info(f"note: the cosine schedule decays over {cfg.optim.decay_steps or cfg.run.max_steps} steps "
                f"(optim.decay_steps or run.max_steps) whatever the {cfg.run.minutes:g}-minute budget")
    trainer, caches = build_trainer(cfg, run, clips, dist, ck)
    record = {"model_name": cfg.model.name, "scale": run.scale, "scales": list(run.scales), "config": cfg.to_dict(),
              "user_config": user.to_dict(), "resolved": run.to_dict(), "data": manifest_record(clips),
              "init": init_record(cfg, ck)}
    if dist.main:
        write_text_atomic(run_dir / "config.toml", run_config_toml(user, run))
    checkpoints, evaluations = Checkpoints(trainer, run_dir, record), Evaluations(trainer, run_dir, caches)
    runlog = RunLog(trainer, run_dir)
    reason, elapsed, times = _loop(trainer, [runlog, checkpoints, evaluations], checkpoints, stop_at)
    summary = summarize(trainer, reason, elapsed, times, runlog.mem_peak)
    if dist.main:
        if reason in ("max_steps", "minutes"):
            summary.update(evaluations.evaluate(trainer))
        write_json_atomic(run_dir / "summary.json", summary)
        logger.info(f"trained {cfg.model.name} to step {trainer.step_no} ({reason}) in {elapsed:.1f} s; "
            f"checkpoint {checkpoints.last}")
    dist.barrier()
    trainer.release()
    dist.close()
    return summary


def _loop(trainer: Trainer, hooks: list, checkpoints: Checkpoints, stop_at: int | None) -> tuple:
    """Steps until run.max_steps, run.minutes, SIGTERM or ``stop_at``; returns (reason, elapsed s, step times)."""
    cfg, device, dist = trainer.cfg, trainer.device, trainer.dist
    term = {"flag": False}
    try:
        old_handler = signal.signal(signal.SIGTERM, lambda signum, frame: term.update(flag=True))
    except ValueError:  # not in the main thread
        old_handler = None
    loader = make_loader(trainer.sampler, trainer.step_no, cfg, device)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True  # fixed crop size: cuDNN picks its fastest algorithms once
        torch.cuda.reset_peak_memory_stats(device)
    t_start, times, reason, interrupted = time.perf_counter(), [], "max_steps", False
    trainer.net.train()
    try:
        while trainer.step_no < cfg.run.max_steps:
            t0 = time.perf_counter()
            batch_np, samples = loader.get(trainer.step_no)
            batch = to_device(batch_np, device)
            t1 = time.perf_counter()
            loss, terms = trainer.step(batch, samples)
            t2 = time.perf_counter()
            times.append((t2 - t0, t1 - t0))
            info = StepInfo(trainer.step_no, loss, terms, t1 - t0, t2 - t0, trainer.elapsed_before + t2 - t_start,
                            t2 - t_start)
            for hook in hooks:
                hook.on_step(trainer, info)
            stop_time = bool(cfg.run.minutes) and info.budget_s >= 60 * cfg.run.minutes
            if dist.any(stop_time or term["flag"] or (stop_at is not None and trainer.step_no >= stop_at)):
                reason = "minutes" if stop_time else ("signal" if term["flag"] else "stop_at")
                break
    except KeyboardInterrupt:
        interrupted, reason = True, "interrupted"
        raise
    finally:
        loader.close()
        elapsed = trainer.elapsed_before + (time.perf_counter() - t_start)
        exc = sys.exc_info()[1]
        for hook in hooks:
            hook.close(trainer, exc, elapsed, interrupted) if hook is checkpoints else hook.close(trainer, exc)
        if old_handler is not None:
            signal.signal(signal.SIGTERM, old_handler)
    return reason, elapsed, times


def summarize(trainer: Trainer, reason: str, elapsed: float, times: list, mem_peak: float) -> dict:
    """summary.json: steps, device, sizes, time per step, fraction of time waiting for data, memory, digests."""
    cfg, run, dist, device = trainer.cfg, trainer.run, trainer.dist, trainer.device
    summary = {"model": cfg.model.name, "step": trainer.step_no, "max_steps": cfg.run.max_steps,
               "stopped_by": reason, "device": str(device), "amp": trainer.amp_name, "world_size": dist.world,
               "threads": torch.get_num_threads(), "batch_size": cfg.data.batch_size, "crop_lr": run.crop,
               "scale": run.scale, "scales": list(run.scales),
               "params": sum(p.numel() for p in trainer.model.parameters()),
               "elapsed_s": elapsed, "window": run.window or None, "peak_mem_mb": mem_peak or None}
    if len(times) > 2:
        st, dt = [t[0] for t in times[2:]], [t[1] for t in times[2:]]
        summary.update(median_step_ms=1000 * statistics.median(st), median_data_ms=1000 * statistics.median(dt),
                       data_fraction=sum(dt) / sum(st), steps_per_s=len(st) / sum(st),
                       samples_per_s=len(st) * cfg.data.batch_size * dist.world / sum(st))
    summary["workers"] = cfg.data.workers
    summary["gpu_max_memory_mb"] = (torch.cuda.max_memory_allocated(device) / 2 ** 20
                                    if device.type == "cuda" else None)
    from gbuffer_export.resources import peak_rss_bytes
    peak = peak_rss_bytes()
    summary["max_rss_mb"] = peak / 2**20 if peak is not None else None
    if dist.enabled:
        digest = param_digest(unwrap(trainer.net), params_only=True)
        digests = [None] * dist.world
        torch.distributed.all_gather_object(digests, digest)
        summary["ranks_agree"] = len(set(digests)) == 1
        if not summary["ranks_agree"]:
            warnings.warn(f"DDP ranks hold different weights: {digests}", RuntimeWarning)
    summary["param_digest"] = param_digest(unwrap(trainer.net))
    summary["weights"] = "ema" if trainer.ema is not None else "trained"  # what inference, evaluation, release use
    return summary
