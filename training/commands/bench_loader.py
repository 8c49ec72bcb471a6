"""``blendsr bench loader``: loader throughput against training-step throughput.

Loads ``--batches`` batches with the training sampler (memory-mapped cache, aligned crops, augmentation, float32
conversion): in the main thread without prefetching (``--workers 0``), or through the training loop's worker
processes (``--workers N``, ``training.loader.WorkerLoader``, pinned memory on CUDA), and times a full training step
of ``--model`` (forward, loss, backward, Adam; inputs copied to the device) on ``--device`` with the same batch size
and crop. Reports both as samples per second (``loader_samples_per_s``, ``step_samples_per_s``; the loader keeps the
device busy when it is the larger) and the medians of the per-batch times. Without --data it writes a synthetic clip
(512x288 HR, scale 4, 8 frames) to a temporary directory. torch is imported inside ``run``.
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", nargs="*", default=[], metavar="CLIP",
                        help="clips to load from, of one scale (default: a synthetic clip in a temporary directory)")
    parser.add_argument("--model", default="fusesr", help="model whose inputs are loaded and whose step is timed")
    parser.add_argument("--batch", type=int, default=8, help="batch size")
    parser.add_argument("--crop", type=int, default=64, help="LR crop side, pixels")
    parser.add_argument("--batches", type=int, default=20, help="batches loaded for the timing")
    parser.add_argument("--steps", type=int, default=5, help="training steps timed (after one warm-up step)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: the cores this process may use)")
    parser.add_argument("--amp", default="none", choices=("none", "bf16", "fp16", "auto"), help="autocast of the step")
    parser.add_argument("--workers", type=int, default=0,
                        help="loader processes (0: the main thread, one batch at a time)")
    parser.add_argument("--device", default="cpu", choices=("auto", "cpu", "cuda"), help="where the step runs")
    parser.add_argument("--json", metavar="OUT", help="also write the numbers as JSON")


def _time_loader(sampler, args, device) -> tuple[list[float], float]:
    """(ms per batch, samples per second) of the batch source: ``args.workers`` worker processes (start-up
    excluded), else the sampler in this process."""
    import torch
    load_ms = []
    if args.workers > 0:
        from training.loader import WorkerLoader
        loader = WorkerLoader(sampler, 0, args.batches, args.workers, pin=device.type == "cuda")
        try:
            loader.get(0)  # worker start-up excluded
            t0 = t = time.perf_counter()
            for k in range(1, args.batches):
                loader.get(k)
                load_ms.append(1000 * (time.perf_counter() - t))
                t = time.perf_counter()
            return load_ms, (args.batches - 1) * args.batch / max(time.perf_counter() - t0, 1e-9)
        finally:
            loader.close()
    for k in range(args.batches):
        t = time.perf_counter()
        batch, _ = sampler.batch(k)
        _ = {key: torch.from_numpy(v) for key, v in batch.items()}  # as the training loop converts it
        load_ms.append(1000 * (time.perf_counter() - t))
    return load_ms, args.batch / (statistics.median(load_ms) / 1000)


def run(args) -> int:
    from gbuffer_export.extras import require
    require("blendsr bench loader", "train")
    import torch

    from gbuffer_export.clip import write_json_atomic
    from gbuffer_export.synthetic import SyntheticLook, make_synthetic_clip
    from training.commands.cli import refuse_dataset
    from training.config import DataConfig, ModelConfig
    from training.data import BatchSpec, TrainSampler
    from training.device import amp_dtype, resolve_device, set_threads
    from training.models import build_model

    set_threads(args.threads)
    tmp = None
    clips = list(args.data)
    for c in clips:
        refuse_dataset(c, "--data")
    if not clips:
        tmp = tempfile.TemporaryDirectory(prefix="blendsr-bench-loader-")
        t = time.perf_counter()
        clips = [str(make_synthetic_clip(Path(tmp.name) / "clip", frames=range(1, 9), hr_size=(512, 288),
                                         scale=4, look=SyntheticLook(hr_supersample=1)))]
        print(f"synthetic clip 512x288 x4, 8 frames written in {time.perf_counter() - t:.1f} s")
    try:
        caches = _caches(clips, args.crop)
        scale = caches[0].scale
        model = build_model(ModelConfig(name=args.model), scale)
        data = DataConfig()  # the training defaults' augmentations
        spec = BatchSpec.for_model(model, crop=args.crop, flip=True, rotate=True,
                                   exposure_range=tuple(data.exposure_range),
                                   reflectance_range=tuple(data.reflectance_range))
        t = time.perf_counter()
        for c in caches:
            c.ensure(spec.cache_keys)
        cache_s = time.perf_counter() - t
        sampler = TrainSampler(caches, spec, args.batch, seed=0)
        device = resolve_device(args.device)
        load_ms, loader_sps = _time_loader(sampler, args, device)
        dtype = amp_dtype(args.amp, device)
        step_ms = _time_steps(model, sampler, args, device, dtype)
        res = {"model": args.model, "batch": args.batch, "crop_lr": args.crop, "scale": scale,
               "threads": torch.get_num_threads(), "amp": str(dtype).replace("torch.", "") if dtype else "none",
               "device": str(device), "workers": args.workers,
               "cache_build_s": cache_s, "load_ms_median": statistics.median(load_ms),
               "load_ms_max": max(load_ms), "step_ms_median": statistics.median(step_ms),
               "step_ms_min": min(step_ms), "loader_samples_per_s": loader_sps,
               "step_samples_per_s": args.batch / (statistics.median(step_ms) / 1000)}
        res["ratio"] = res["load_ms_median"] / res["step_ms_median"]
        res["loader_over_step"] = res["loader_samples_per_s"] / res["step_samples_per_s"]
        print(_summary_line(res))
        if args.json:
            write_json_atomic(args.json, res)
        return 0
    finally:
        if tmp is not None:
            tmp.cleanup()


def _summary_line(res: dict) -> str:
    """The result in one line: loader and step throughput, their ratio, and the cache's build time."""
    return (f"{res['model']} batch {res['batch']}, LR crop {res['crop_lr']} (x{res['scale']}), {res['threads']} "
            f"threads, {res['workers']} workers, step on {res['device']}, amp {res['amp']}: loader "
            f"{res['loader_samples_per_s']:.1f} samples/s (batch {res['load_ms_median']:.1f} ms, max "
            f"{res['load_ms_max']:.1f}), step {res['step_samples_per_s']:.1f} samples/s ({res['step_ms_median']:.0f} "
            f"ms) -> loader/step {res['loader_over_step']:.2f} (cache built in {res['cache_build_s']:.1f} s)")


def _caches(clips: list[str], crop: int) -> list:
    """The clips' caches; BlendSRError naming the clip when clips differ in scale or an LR frame is smaller than
    ``crop`` (this command's flag, not the training configuration's key)."""
    from gbuffer_export.errors import BlendSRError
    from training.cache import ClipCache
    caches = [ClipCache(c) for c in clips]
    for c in caches:
        if c.scale != caches[0].scale:
            raise BlendSRError(f"{c.clip_path}: scale {c.scale:g} differs from {caches[0].clip_path}'s "
                               f"{caches[0].scale:g}; benchmark clips of one scale")
        w, h = c.sizes["lr"]
        if crop > min(w, h):
            raise BlendSRError(f"{c.clip_path}: LR size {w}x{h} is smaller than --crop {crop}; pass "
                               f"--crop {min(w, h)} or less")
    return caches


def _time_steps(model, sampler, args, device, dtype) -> list[float]:
    """Milliseconds of each of ``args.steps`` training steps (forward, loss, backward, Adam) after one untimed."""
    import torch

    from training.config import LossConfig
    from training.device import autocast
    from training.losses import Criterion
    from training.trainer import to_device
    model.fast_ops = True  # as in training
    model.to(device)
    crit = Criterion(LossConfig()).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    step_ms = []
    for k in range(args.steps + 1):
        batch, _ = sampler.batch(1000 + k)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t = time.perf_counter()
        tb = to_device(batch, device)
        with autocast(device, dtype):
            sr = model(tb).float()
        loss, _ = crit(sr, tb["hr/radiance"][:, -1])
        opt.zero_grad()
        loss.backward()
        opt.step()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        if k:
            step_ms.append(1000 * (time.perf_counter() - t))
    return step_ms
