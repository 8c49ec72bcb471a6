"""Evaluation of a model on clips (torch): ``evaluate_model`` -> the JSON-ready dict of ``blendsr evaluate``.

Every model is fed the same inputs (``inference.model_inputs``) and scored against ``hr/radiance`` with the metrics of
``training.metrics`` on one declared tonemap. Nothing of the ground truth ever enters an output pixel. Pixels with an
UNTRUSTED flag (demodulation not trustworthy there) are scored separately (``psnr_flagged``, ``psnr_unflagged``,
``flagged_fraction``); the main metrics cover all pixels. Timing: the model runs ``warmup`` times on the first frame,
then each frame's forward pass is timed (inputs already on the device, GPU synchronised); ``mean.ms_per_frame`` is
the median over frames. Recurrent models (``training.recurrent``) run the frames in order with their state carried
from frame to frame, reset at the clip's first frame and after a gap in the frame numbers; when the scored frames
start later in the clip, the frames before them are run first (unscored) from the clip's start.

Scales: a clip is evaluated at each of its LR levels that the model takes (``eval_scales``: every level for a model
with ``SCALES = None``, else the level at ``model.scale``); each row carries its ``scale`` and ``per_scale`` holds
the means per scale.
"""
from __future__ import annotations

import logging

import os
import platform
import statistics
import sys
from pathlib import Path

import numpy as np
import torch

from gbuffer_export.clip import ClipError, buffer_path, open_clip
from gbuffer_export.conventions import UNTRUSTED, Flag
from gbuffer_export.exr import write_exr
from gbuffer_export.regions import REGIONS, error_breakdown, pixel_regions
from training import metrics
from training.flip_worker import FlipRunner
from training.inference import ClipFrames, model_device, model_inputs, run_model
from training.recurrent import ClipState, is_recurrent, lead_in, run_step


log = logging.getLogger(__name__)

METRIC_KEYS = ("psnr", "ssim", "psnr_hdr", "flip", "tpsnr", "warp_error", "ms_per_frame")
EXTRA_KEYS = ("warp_error_gt", "psnr_flagged", "psnr_unflagged", "flagged_fraction", "sr_nonfinite", "delta_e_itp")


def describe_device(device: torch.device) -> str:
    if device.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(device)})"
    name = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"cpu ({name}, {torch.get_num_threads()} threads)"


def _mean(values):
    vals = [v for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def eval_scales(model, clip, wanted=None) -> list[float]:
    """The scales at which ``model`` is evaluated on ``clip`` (a Clip): ``wanted`` when given, else every LR level
    for a model that takes any scale, else ``model.scale``. ClipError (one line) when the clip lacks a level or the
    model cannot take it."""
    scales = [float(s) for s in wanted] if wanted else (
        list(clip.scales) if getattr(model, "SCALES", ()) is None else [float(model.scale)])
    for s in scales:
        if getattr(model, "SCALES", ()) is not None and s != float(model.scale):
            raise ClipError(f"{clip.path}: clip scale {s:g} but the model upscales by {model.scale}")
        if not any(abs(s - v) < 1e-9 for v in clip.scales):
            if len(clip.scales) == 1:
                raise ClipError(f"{clip.path}: clip scale {clip.scale} but the model upscales by {model.scale}")
            clip.level_at(s)  # raises, naming the clip's scales
    return scales


def _frame_scores(sr: np.ndarray, gt: np.ndarray, inputs: dict, runner, delta_e_itp: bool) -> dict:
    """Scores of one frame (HR (H, W, 3) linear SR and ground truth): PSNR/SSIM (tonemapped), PSNR HDR, FLIP,
    Delta E ITP, and PSNR inside/outside the flagged (untrusted, non-background) pixels when the clip has flags."""
    row = {"psnr": metrics.psnr_tm(sr, gt), "ssim": metrics.ssim_tm(sr, gt), "psnr_hdr": metrics.psnr_hdr(sr, gt),
           "flip": runner(gt, sr) if runner is not None else None,
           "delta_e_itp": metrics.delta_e_itp(sr, gt) if delta_e_itp else None}
    if "hr/flags" not in inputs:
        return {**row, "flagged_fraction": None, "psnr_flagged": None, "psnr_unflagged": None}
    fl = inputs["hr/flags"][0, -1, 0].astype(np.uint32)
    flagged = ((fl & np.uint32(UNTRUSTED)) != 0) & ((fl & np.uint32(Flag.BACKGROUND)) == 0)
    return {**row, "flagged_fraction": float(flagged.mean()), "psnr_flagged": metrics.psnr_tm(sr, gt, flagged),
            "psnr_unflagged": metrics.psnr_tm(sr, gt, ~flagged)}


def _temporal_scores(sr, gt, inputs: dict, f: int, prev) -> dict:
    """tPSNR and warping errors against the previous frame ``prev`` = (frame, SR, GT) when it is frame f - 1."""
    row = {"tpsnr": None, "warp_error": None, "warp_error_gt": None}
    if prev is None or prev[0] != f - 1:
        return row
    _, sr_p, gt_p = prev
    row["tpsnr"] = metrics.tpsnr(sr, sr_p, gt, gt_p)
    if "hr/motion" in inputs:
        motion = inputs["hr/motion"][0, -1].transpose(1, 2, 0)
        row["warp_error"] = metrics.warp_error(sr, sr_p, motion)
        row["warp_error_gt"] = metrics.warp_error(gt, gt_p, motion)
    return row


def _means(rows: list[dict]) -> dict:
    """Mean of every metric over ``rows`` (median ms per frame), the frame count and the per-region means."""
    m = {k: _mean([r[k] for r in rows]) for k in METRIC_KEYS + EXTRA_KEYS if k != "ms_per_frame"}
    m.update(ms_per_frame=float(statistics.median(r["ms_per_frame"] for r in rows)), frames=len(rows),
             regions=_region_means(rows))
    return m


def group_means(result: dict, group_of=None, metrics=("psnr", "ssim", "tpsnr")) -> dict[str, dict]:
    """{group: {metric: mean over the group's frames}} of an ``evaluate_model`` result; a frame's group is
    ``group_of(clip folder name)`` (default: the clip's name), e.g. the dataset index's scene id."""
    groups: dict[str, list[dict]] = {}
    for r in result["per_frame"]:
        name = Path(r["clip"]).name
        groups.setdefault(group_of(name) if group_of else name, []).append(r)
    return {g: {k: _mean([r.get(k) for r in rows]) for k in metrics} for g, rows in sorted(groups.items())}


def evaluate_model(model, clips, *, frames: dict | None = None, device: torch.device | None = None,
                   amp: torch.dtype | None = None, flip: bool = True, delta_e_itp: bool = False, data_cfg=None,
                   save_images: str | os.PathLike | None = None, warmup: int = 2, progress: bool = False,
                   label: str | None = None, scales: dict | None = None, scale: float | None = None) -> dict:
    """Evaluate ``model`` on ``clips`` (paths); ``frames`` maps a clip path (as given) to the frames to score
    (default: all); ``scales`` maps a clip path to the scales to score (default: ``eval_scales``); ``scale``: every
    clip at this one scale only (an any-scale model is then not averaged over a clip's other LR levels).
    ``delta_e_itp``: also score ``metrics.delta_e_itp`` (None otherwise). Returns {model, transform, device, mean,
    per_scale, per_frame, ...}."""
    if scale is not None:
        if scales is not None:
            raise ValueError("evaluate_model: give scales or scale, not both")
        scales = {str(c): [float(scale)] for c in clips}
    device = device or model_device(model)
    model.to(device).eval()
    eps = data_cfg.demod_eps if data_cfg is not None else getattr(model, "demod_eps", 0.01)
    runner = FlipRunner() if flip else None
    per_frame: list[dict] = []
    warnings: list[str] = []
    try:
        jobs = []  # (clip path, Clip, scale), checked before anything runs
        for c in clips:
            base = open_clip(c)
            jobs += [(c, base, s_) for s_ in eval_scales(model, base, (scales or {}).get(str(c)))]
        for clip_path, base, s_clip in jobs:
            source = ClipFrames(base.at_scale(s_clip), eps=eps)
            state_key = f"{clip_path}@x{s_clip:g}"
            if not source.has("hr/radiance"):
                raise ClipError(f"{clip_path}: clip has no hr/radiance to compare with")
            model.follow_reference_filter(source.clip.manifest)
            mismatch = model.remod_filter_mismatch(source.clip.manifest, clip_path)
            if mismatch:
                log.warning(f"warning: {mismatch}")
            todo = list((frames or {}).get(str(clip_path)) or source.frames)
            first = model_inputs(model, source, todo[0])
            recurrent = is_recurrent(model)
            for _ in range(warmup):  # a recurrent model's warm-up runs start from no state and keep none
                run_step(model, first, None, device, amp) if recurrent else run_model(model, first, device, amp)
            states = ClipState()
            if recurrent:  # the frames before the first scored one, from the clip's start (unscored)
                for g in lead_in(source.frames, todo[0]):
                    states.put(state_key, g, run_step(model, model_inputs(model, source, g, False),
                                                      states.get(state_key, g), device, amp)[2])
            prev = None
            iterator = todo
            if progress:
                from tqdm import tqdm
                iterator = tqdm(todo, desc=f"{label or 'evaluate'} {Path(clip_path).name}", unit="frame",
                                file=sys.stderr, dynamic_ncols=True)
            for f in iterator:
                inputs = model_inputs(model, source, f)
                if recurrent:  # state carried from the previous frame; reset at a clip's start or after a gap
                    sr, ms, new = run_step(model, inputs, states.get(state_key, f), device, amp)
                    states.put(state_key, f, new)
                else:
                    sr, ms = run_model(model, inputs, device, amp)
                gt = inputs["hr/radiance"][0, -1].transpose(1, 2, 0)
                check_ground_truth(gt, clip_path, f)
                sr, bad = sanitize_output(sr)
                if bad:
                    msg = (f"{clip_path} frame {f} (x{s_clip:g}): the model output {bad} non-finite value(s) "
                           "(NaN/Inf), scored as 0; its scores are not the model's")
                    warnings.append(msg)
                    log.warning(f"warning: {msg}")
                row = {"clip": str(clip_path), "frame": int(f), "scale": s_clip, "ms_per_frame": ms,
                       "sr_nonfinite": bad, **_frame_scores(sr, gt, inputs, runner, delta_e_itp),
                       "regions": _regions(source, f, sr, gt), **_temporal_scores(sr, gt, inputs, f, prev)}
                prev = (f, sr, gt)
                per_frame.append(row)
                if save_images:
                    name = Path(clip_path).name
                    _save(Path(save_images), name if len(base.scales) == 1 else f"{name}_x{s_clip:g}", f, sr)
    finally:
        if runner is not None:
            runner.close()
    if not per_frame:
        raise ClipError("no frame evaluated")
    mean, per_scale = _means(per_frame), {}
    for sc in sorted({r["scale"] for r in per_frame}):
        per_scale[f"{sc:g}"] = _means([r for r in per_frame if r["scale"] == sc])
    return {
        "model": label or getattr(model, "spec", type(model).__name__),
        "transform": metrics.TRANSFORM,
        "device": describe_device(device),
        "amp": str(amp).replace("torch.", "") if amp else "none",
        "scale": model.scale,
        "hdr_peak": metrics.HDR_PEAK,
        "itp_white_nits": metrics.ITP_WHITE_NITS if delta_e_itp else None,
        "psnr_cap_db": metrics.PSNR_CAP,
        "timing": f"median over frames of the forward pass after {warmup} warm-up runs, inputs on the device",
        "flip_failures": runner.failures if runner is not None else [],
        "sr_nonfinite_frames": sum(1 for r in per_frame if r["sr_nonfinite"]),
        "warnings": warnings,
        "clips": [str(c) for c in clips],
        "mean": mean,
        "per_scale": per_scale,
        "per_frame": per_frame,
    }


def check_ground_truth(gt: np.ndarray, clip_path, frame: int) -> None:
    """A ground truth with NaN/Inf gives scores that mean nothing: ClipError naming its file."""
    bad = ~np.isfinite(gt)
    if bad.any():
        path = buffer_path(Path(clip_path), frame, "hr", "radiance")
        raise ClipError(f"{path}: the ground truth holds {int(bad.sum())} non-finite value(s) "
                        f"({int(np.isnan(gt).sum())} NaN, {int(np.isinf(gt).sum())} Inf); re-render the frame or "
                        "leave it out with --frames")


def sanitize_output(sr: np.ndarray) -> tuple[np.ndarray, int]:
    """(``sr`` with NaN/Inf replaced by 0, how many there were): a model output is never scored or written with
    non-finite pixels; the caller warns and records the count."""
    bad = int((~np.isfinite(sr)).sum())
    if bad:
        sr = np.nan_to_num(sr, nan=0.0, posinf=0.0, neginf=0.0)
    return sr, bad


def _regions(source, frame: int, sr: np.ndarray, gt: np.ndarray) -> dict | None:
    """{region: {fraction, psnr, err_share}} of one frame (``gbuffer_export.regions``); None without HR flags and
    depth."""
    if not (source.has("hr/flags") and source.has("hr/depth")):
        return None
    regions = pixel_regions(source.read(frame, "hr/flags"), source.read(frame, "hr/depth"))
    sq = ((metrics.tonemapped(sr) - metrics.tonemapped(gt)) ** 2).mean(dim=1)[0].numpy()
    return {name: {"fraction": v["fraction"], "err_share": v["err_share"],
                   "psnr": metrics.psnr_from_mse(v["mse"]) if v["mse"] is not None else None}
            for name, v in error_breakdown(sq, regions).items()}


def _region_means(rows: list[dict]) -> dict | None:
    """The per-frame ``regions`` averaged over the frames that have them (each value over the frames where it is
    not None); None when no frame has them."""
    have = [r["regions"] for r in rows if r.get("regions")]
    if not have:
        return None
    return {name: {k: _mean([h[name][k] for h in have]) for k in ("fraction", "psnr", "err_share")}
            for name in REGIONS}


def _save(root: Path, clip_name: str, frame: int, sr: np.ndarray) -> None:
    d = root / clip_name
    write_exr(d / f"{frame:06d}.exr", {c: sr[..., i] for i, c in enumerate("RGB")})
    import matplotlib.image as mpimg
    tm = metrics.tonemapped(sr)[0].permute(1, 2, 0).numpy()
    mpimg.imsave(d / f"{frame:06d}.png", np.clip(tm, 0, 1))
