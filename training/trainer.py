"""The trainer (torch): ``Trainer`` owns what one optimisation step needs (model, wrapped net, optimiser, scheduler,
EMA, grad scaler, sampler) and its checkpoint state; ``Dist`` is the torchrun environment. Logging, checkpoints and
evaluation are hooks (``training.hooks``) that ``training.train.train`` calls after every step.
"""
from __future__ import annotations

import dataclasses
import gc
import hashlib
import math
import os
import random
import warnings

import torch

from training.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, numpy_rng_state, restore_numpy_rng
from training.config import TrainConfig
from training.device import amp_dtype, autocast, resolve_device
from training.losses import Criterion
from training.recurrent import StepWrapper, window_losses


class TrainingError(RuntimeError):
    """Training stopped (non-finite loss, broken data); the message says where."""


def to_device(batch: dict, device: torch.device) -> dict[str, torch.Tensor]:
    """numpy arrays or (pinned) CPU tensors -> tensors on ``device`` (asynchronous copies where pinned)."""
    return {k: (v if isinstance(v, torch.Tensor) else torch.from_numpy(v)).to(device, non_blocking=True)
            for k, v in batch.items()}


def drop_last(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The batch of the window that ends one frame earlier (every key loses its last frame; per-sample values such
    as 'scale' (B,) stay)."""
    return {k: v[:, :-1] if v.dim() > 1 else v for k, v in batch.items()}


def lr_lambda(cfg: TrainConfig):
    """step -> learning-rate factor: linear warm-up, then constant, step decay or cosine to ``min_lr_ratio``."""
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


def baseline_models(cfg: TrainConfig, scales) -> dict:
    """{scale: the guided baseline ``demod-jbu``} of the ``baseline`` loss term, one per scale the run trains at
    ({} when ``loss.baseline_weight`` is 0): the model's shared keys (jitter, remodulation filter, ...) with
    demod-jbu's default options, the baseline every margin in docs/results.md is measured against. ConfigError
    for a scale demod-jbu does not take."""
    if cfg.loss.baseline_weight <= 0:
        return {}
    from gbuffer_export.config import ConfigError
    from training.models import build_model, model_class
    jbu = model_class("demod-jbu")
    bad = [f"{s:g}" for s in scales if not jbu.supports_scale(s)]
    if bad:
        raise ConfigError(f"loss.baseline_weight: the run trains at scale {', '.join(bad)} and its baseline "
                          f"demod-jbu takes {jbu.scales_text()}; set loss.baseline_weight = 0 or train at those")
    out = {}
    for s in scales:
        base = build_model(dataclasses.replace(cfg.model, name="demod-jbu", options=None), s)
        base.fast_ops = True
        out[float(s)] = base.eval().requires_grad_(False)
    return out


def param_groups(model: torch.nn.Module, cfg: TrainConfig) -> list[dict]:
    """The optimiser's parameter groups: the model's parameters, and its confidence gate's (``GATE_PARAMETERS``)
    at ``optim.lr * optim.gate_lr_scale`` in a group of their own when the scale is not 1 (the schedule multiplies
    both). ConfigError for a scale without a gate."""
    named = list(model.named_parameters())
    scale = cfg.optim.gate_lr_scale
    if scale == 1.0:
        return [{"params": [p for _, p in named]}]
    gate = set(getattr(model, "GATE_PARAMETERS", ())) & {n for n, _ in named}
    if not gate:
        from gbuffer_export.config import ConfigError
        raise ConfigError(f"optim.gate_lr_scale = {scale:g} but model {cfg.model.name} has no confidence gate (set "
                          f"model.{cfg.model.name}.confidence_gate = true, or optim.gate_lr_scale = 1)")
    return [{"params": [p for n, p in named if n not in gate]},
            {"params": [p for n, p in named if n in gate], "lr": cfg.optim.lr * scale}]


def param_digest(model: torch.nn.Module, params_only: bool = False) -> str:
    """Short hash of the state dict (or of the parameters only: BatchNorm running statistics are per rank under
    DDP until the next forward pass broadcasts rank 0's)."""
    h = hashlib.sha256()
    items = model.named_parameters() if params_only else model.state_dict().items()
    for k, v in items:
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def make_ema(model: torch.nn.Module, decay: float):
    """The exponential moving average of ``model``'s weights and buffers (torch.optim.swa_utils.AveragedModel);
    None when ``decay`` is 0. After update k the average is w_1 for k = 1, else decay * avg + (1 - decay) * w_k."""
    if not decay:
        return None
    from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
    return AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(decay), use_buffers=True)


def unwrap(model):
    """The model inside DDP, torch.compile and StepWrapper wrappers."""
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


class Trainer:
    """One model's optimisation: ``step(batch, samples)`` runs one step (forward, losses, backward, optimiser,
    scheduler, EMA) and advances ``step_no``; ``state_dict()`` / ``load_state_dict(ck)`` hold everything a resumed
    run needs to continue bit-identically. ``cfg`` is the effective configuration (``ResolvedRun.apply``), ``run``
    the ResolvedRun, ``model`` the unwrapped module (on the CPU; moved to ``dist.device`` here)."""

    def __init__(self, cfg: TrainConfig, run, model: torch.nn.Module, sampler, dist: Dist, baselines=None):
        self.cfg, self.run, self.model, self.sampler, self.dist = cfg, run, model, sampler, dist
        # the guided baselines of the ``baseline`` loss term (``baseline_models``; no parameters), by scale
        self.baselines = {s: b.to(dist.device) for s, b in (baselines or {}).items()}
        self.device = device = dist.device
        self.step_no = 0
        self.elapsed_before = 0.0  # seconds trained before this process (resumed runs)
        self.temporal = cfg.loss.temporal_weight > 0
        self.checkpoint_path = None  # the last checkpoint written, named by a non-finite loss
        model.to(device)
        self.criterion = Criterion(cfg.loss).to(device)
        opt_cls = torch.optim.AdamW if cfg.optim.weight_decay > 0 else torch.optim.Adam
        self.optimizer = opt_cls(param_groups(model, cfg), lr=cfg.optim.lr, betas=tuple(cfg.optim.betas),
                                 weight_decay=cfg.optim.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, lr_lambda(cfg))
        self.ema = make_ema(model, cfg.optim.ema_decay)
        self.dtype = amp_dtype(cfg.run.amp, device)
        fp16 = self.dtype == torch.float16 and device.type == "cuda"
        self.scaler = torch.amp.GradScaler("cuda") if fp16 else None
        self.net = None  # set by wrap(), after load_state_dict

    # ------------------------------------------------------------------------------------------- state
    def state_dict(self) -> dict:
        """The training state of step ``step_no`` (weights, averages, optimiser, scheduler, scaler, RNGs, sampler)."""
        ema = self.ema
        cuda = self.device.type == "cuda"
        return {"step": self.step_no, "model": unwrap(self.net or self.model).state_dict(),
                "ema_model": ema.module.state_dict() if ema is not None else None,
                "ema_updates": int(ema.n_averaged) if ema is not None else 0,
                "optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(),
                "scaler": self.scaler.state_dict() if self.scaler is not None else None,
                "rng": {"torch": torch.get_rng_state(), "numpy": numpy_rng_state(), "python": random.getstate(),
                        "cuda": torch.cuda.get_rng_state_all() if cuda else None},
                "sampler": {**self.sampler.state_dict(), "next_step": self.step_no},
                "world_size": self.dist.world, "device": str(self.device), "amp": self.amp_name,
                "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION}

    def load_state_dict(self, ck: dict) -> None:
        """Restore a checkpoint's training state (before ``wrap``)."""
        self.model.load_state_dict(ck["model"])
        self.optimizer.load_state_dict(ck["optimizer"])
        self.scheduler.load_state_dict(ck["scheduler"])
        rng = ck["rng"]
        torch.set_rng_state(rng["torch"])
        restore_numpy_rng(rng["numpy"])
        random.setstate(rng["python"])
        if self.device.type == "cuda" and rng.get("cuda") is not None:
            torch.cuda.set_rng_state_all(rng["cuda"])
        self.step_no = int(ck["step"])
        self.elapsed_before = float(ck.get("elapsed_s", 0.0))
        if self.ema is not None and ck.get("ema_model") is not None:
            self.ema.module.load_state_dict(ck["ema_model"])
            self.ema.n_averaged.fill_(int(ck["ema_updates"]))
        if self.scaler is not None and ck.get("scaler"):
            self.scaler.load_state_dict(ck["scaler"])

    @property
    def amp_name(self) -> str:
        return str(self.dtype).replace("torch.", "") if self.dtype else "none"

    def evaluated(self) -> torch.nn.Module:
        """The weights evaluations and releases use: the moving average when there is one."""
        return self.ema.module if self.ema is not None else unwrap(self.net)

    # ------------------------------------------------------------------------------------------- wrapping
    def wrap(self) -> None:
        """SyncBatchNorm (DDP on CUDA), DDP (feed-forward) or StepWrapper (recurrent), then torch.compile."""
        dist, model, device = self.dist, self.model, self.device
        net = model
        if dist.enabled and any(isinstance(m, torch.nn.modules.batchnorm._BatchNorm) for m in model.modules()):
            if device.type == "cuda":  # same Parameter objects: the optimiser and the checkpoint keys are unchanged
                model = self.model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(model)
                net = model
            elif dist.main:
                warnings.warn(f"model.{self.cfg.model.name}.norm = 'batch' under DDP on CPU: BatchNorm statistics "
                              "are per rank (torch's SyncBatchNorm needs a GPU)", RuntimeWarning)
        if dist.enabled and not self.run.recurrent:
            net = torch.nn.parallel.DistributedDataParallel(
                model, device_ids=[device.index] if device.type == "cuda" else None)
        if self.run.recurrent:  # several forward/backward passes per step: no DDP wrapper, gradients averaged by hand
            net = StepWrapper(model)
            if dist.enabled:
                for p in model.parameters():
                    torch.distributed.broadcast(p.data, 0)
        self.net = torch.compile(net) if self.cfg.run.compile else net

    def release(self) -> None:
        """Drop the DDP wrapper (it holds the process group and sits in reference cycles) and collect it now, so that
        gloo's threads are not torn down during interpreter exit (a rare SIGABRT at the end of torchrun)."""
        self.net = None
        gc.collect()

    # ------------------------------------------------------------------------------------------- one step
    def _backward(self, chunk: torch.Tensor) -> None:
        (self.scaler.scale(chunk) if self.scaler is not None else chunk).backward()

    def _losses(self, batch: dict) -> tuple:
        """(loss, {term: value}, SR of the current frame); recurrent models have back-propagated already."""
        cfg, net, temporal = self.cfg, self.net, self.temporal
        if self.run.recurrent:  # back-propagates chunk by chunk (training.recurrent)
            self.optimizer.zero_grad(set_to_none=True)
            return window_losses(net, self.criterion, batch, cfg.data.detach_every or self.run.window,
                                 self._backward, temporal, lambda: autocast(self.device, self.dtype),
                                 self.baseline_sr)
        with autocast(self.device, self.dtype):
            sr = net(batch).float()
            sr_prev = net(drop_last(batch)).float() if temporal else None
        hr = batch["hr/radiance"]
        loss, terms = self.criterion(sr, hr[:, -1], sr_prev, hr[:, -2] if temporal else None,
                                     batch["hr/motion"][:, -1] if temporal else None, self.baseline_sr(batch))
        return loss, terms, sr

    def baseline_sr(self, batch: dict):
        """The baseline's SR of the batch's current frame at the batch's scale (float32, no gradient); None
        without the term."""
        if not self.baselines:
            return None
        scale = next(iter(self.baselines.values())).batch_scale(batch)
        with torch.no_grad():
            return self.baselines[float(scale)](batch).float()

    def _check_finite(self, loss, sr, samples) -> None:
        if not self.dist.any(not bool(torch.isfinite(loss))):
            return
        where = "; ".join(f"{s.clip} frames {s.frames[0]}-{s.frames[-1]}" for s in samples)
        bad_sr = not bool(torch.isfinite(sr).all())
        last = self.checkpoint_path
        raise TrainingError(f"loss became {loss.item()} at step {self.step_no + 1} (rank {self.dist.rank}; "
                            f"{'the model output' if bad_sr else 'a loss term'} is not finite; batch: {where}); "
                            "training stopped, " + (f"last checkpoint: {last}" if last is not None and last.is_file()
                                                    else "no checkpoint was written before it"))

    def _average_grads(self) -> None:
        """Recurrent models under DDP: the mean gradient over ranks, by hand."""
        for p in self.model.parameters():
            if p.requires_grad:
                if p.grad is None:
                    p.grad = torch.zeros_like(p)
                torch.distributed.all_reduce(p.grad)
                p.grad /= self.dist.world

    def step(self, batch: dict, samples) -> tuple:
        """One optimisation step on ``batch`` (tensors on the device); returns (loss, {term: value})."""
        loss, terms, sr = self._losses(batch)
        self._check_finite(loss, sr, samples)
        if not self.run.recurrent:
            self.optimizer.zero_grad(set_to_none=True)
            self._backward(loss)
        elif self.dist.enabled:
            self._average_grads()
        if self.scaler is not None:
            self.scaler.unscale_(self.optimizer)
        if self.cfg.optim.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.optim.grad_clip)
        if self.scaler is not None:
            self.scaler.step(self.optimizer)
            self.scaler.update()
        else:
            self.optimizer.step()
        self.scheduler.step()
        if self.ema is not None:
            self.ema.update_parameters(self.model)
        self.step_no += 1
        return loss, terms
