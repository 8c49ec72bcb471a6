"""Evaluation of a model on clips (torch): ``evaluate_model`` -> the JSON-ready dict of ``blendsr evaluate``.

Every model is fed the same inputs (``inference.model_inputs``) and scored against ``hr/radiance`` with the metrics of
``training.metrics`` on one declared tonemap. Nothing of the ground truth ever enters an output pixel. Pixels with an
UNTRUSTED flag (demodulation not trustworthy there) are scored separately (``psnr_flagged``, ``psnr_unflagged``,
``flagged_fraction``); the main metrics cover all pixels. Timing: the model runs ``warmup`` times on the first frame,
then each frame's forward pass is timed (inputs already on the device, GPU synchronised); ``mean.ms_per_frame`` is
the median over frames. Recurrent models (``training.recurrent``) run the frames in order with their state carried
from frame to frame (``InferenceModel.step``), reset at the clip's first frame and after a gap in the frame numbers;
when a scored frame does not follow the previous one (the first scored frame starts later in the clip), the frames
before it are run first (unscored) from the clip's start (``inference.run_frame``).

The worst case (docs/evaluation.md, "The worst case"): every frame is also scored by its ``worst_share`` and, against
the baseline ``metrics.BASELINE`` (``demod-jbu``, scored on the same frames: ``Baseline``), by its artifact pixels;
``per_clip`` holds each clip's margin over the baseline, and the means add the smallest one (``margin_min``).

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
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from gbuffer_export.clip import ClipError, buffer_path
from gbuffer_export.validate.gate import open_valid_clip
from gbuffer_export.conventions import UNTRUSTED, Flag
from gbuffer_export.exr import write_exr
from gbuffer_export.regions import MATERIALS, REGIONS, error_breakdown, material_regions, pixel_regions
from training import metrics
from training.flip_worker import FlipRunner
from training.video_metric import ClipVideo, VideoScorer, clip_fps
from training.inference.loading import ClipFrames, missing_keys, model_inputs, run_frame
from training.inference.model import InferenceModel


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
    """The scales at which ``model`` (a module) is evaluated on ``clip`` (a Clip): ``wanted`` when given, else every LR level
    for a model that takes any scale, else ``model.scale``. ClipError (one line) when the clip lacks a level or the
    model cannot take it."""
    scales = [float(s) for s in wanted] if wanted else (
        list(clip.scales) if model.SCALES is None else [float(model.scale)])
    for s in scales:
        if model.SCALES is not None and s != float(model.scale):
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
    """Mean of every metric over ``rows`` (median ms per frame), the frame count, the per-region means and the
    worst case (``_worst_means``)."""
    m = {k: _mean([r[k] for r in rows]) for k in METRIC_KEYS + EXTRA_KEYS if k != "ms_per_frame"}
    m.update(ms_per_frame=float(statistics.median(r["ms_per_frame"] for r in rows)), frames=len(rows),
             regions=_region_means(rows), materials=_region_means(rows, "materials", MATERIALS),
             **_worst_means(rows))
    return m


def group_means(result: dict, group_of=None, metrics=("psnr", "ssim", "tpsnr")) -> dict[str, dict]:
    """{group: {metric: mean over the group's frames}} of an ``evaluate_model`` result; a frame's group is
    ``group_of(clip folder name)`` (default: the clip's name), e.g. the dataset index's scene id."""
    groups: dict[str, list[dict]] = {}
    for r in result["per_frame"]:
        name = Path(r["clip"]).name
        groups.setdefault(group_of(name) if group_of else name, []).append(r)
    return {g: {k: _mean([r.get(k) for r in rows]) for k in metrics} for g, rows in sorted(groups.items())}


@dataclass(frozen=True)
class EvalOptions:
    """What ``evaluate_model`` scores and how. ``frames``: clip path (as given) -> the frames to score (default: all);
    ``scales``: clip path -> the scales to score (default: ``eval_scales``); ``scale``: every clip at this one scale
    only (an any-scale model is then not averaged over a clip's other LR levels; not with ``scales``); ``amp``:
    autocast dtype over the model's prepared precision; ``flip``: HDR-FLIP; ``delta_e_itp``: also
    ``metrics.delta_e_itp`` (None otherwise); ``save_images``: write SR EXR + PNG per frame under this folder;
    ``warmup``: untimed runs on the first frame; ``progress``: a bar per clip on stderr; ``label``: the result's
    model name (default: the model's spec); ``baseline``: the model of the worst-case metrics (a name, a shared
    ``Baseline``, or None: none computed); ``cvvdp``: ColorVideoVDP per clip (``training.video_metric``; the
    ``video`` extra)."""

    frames: dict | None = None
    scales: dict | None = None
    scale: float | None = None
    amp: torch.dtype | None = None
    flip: bool = True
    delta_e_itp: bool = False
    save_images: str | os.PathLike | None = None
    warmup: int = 2
    progress: bool = False
    label: str | None = None
    baseline: "str | Baseline | None" = metrics.BASELINE
    cvvdp: bool = False


class Baseline:
    """The baseline of the worst-case metrics (``metrics.BASELINE``) on the frames a model is scored on, as
    ``blendsr evaluate --model NAME`` scores it: per (clip, scale, frame) its PSNR and where its ``pixel_error`` is
    below ``metrics.ARTIFACT_BASELINE``, computed once and kept (bit-packed), so one object serves several models
    (``bench models``). A clip that lacks the baseline's buffers, or a scale it does not take, has none
    (``missing``: (clip, scale) -> reason). It runs on ``device`` (default: the CPU)."""

    def __init__(self, name: str = metrics.BASELINE, device=None):
        self.name = name
        self.device = device
        self.missing: dict[tuple[str, float], str] = {}
        self._models: dict = {}
        self._sources: dict = {}
        self._frames: dict = {}

    def frame(self, clip_path, clip, scale: float, frame: int) -> tuple[float, np.ndarray] | None:
        """(PSNR, H x W bool: baseline error below ARTIFACT_BASELINE) of ``frame`` of ``clip`` (an opened Clip)
        at ``scale``; None when the clip lacks the baseline's buffers."""
        key = (str(clip_path), float(scale), int(frame))
        if key not in self._frames:
            src = self._source(clip_path, clip, scale)
            if src is None:
                return None
            model = self._models[float(scale)]
            model.module.follow_reference_filter(src.clip.manifest)  # this clip's ground-truth filter
            sr, _, inputs = run_frame(model, src, frame, f"{clip_path}@x{scale:g}")
            gt = inputs["hr/radiance"][0, -1].transpose(1, 2, 0)
            sr, _ = sanitize_output(sr)
            ok = metrics.baseline_good(metrics.pixel_error(sr, gt))
            self._frames[key] = (metrics.psnr_tm(sr, gt), np.packbits(ok), ok.shape)
        psnr, bits, shape = self._frames[key]
        return psnr, np.unpackbits(bits, count=shape[0] * shape[1]).reshape(shape).astype(bool)

    def _source(self, clip_path, clip, scale: float):
        from training.inference.loading import load_model
        from training.models import model_class
        skey = (str(clip_path), float(scale))
        if skey not in self._sources and not model_class(self.name).supports_scale(scale):
            self.missing[skey] = f"{self.name} does not upscale by {scale:g}"
            self._sources[skey] = None
        if skey not in self._sources:
            if float(scale) not in self._models:
                self._models[float(scale)] = load_model(self.name, scale).to(self.device or "cpu")
            src = ClipFrames(clip.at_scale(scale))
            lacking = missing_keys(self._models[float(scale)], src)
            if lacking:
                self.missing[skey] = f"the clip lacks {', '.join(lacking)}"
                src = None
            self._sources[skey] = src
        return self._sources[skey]


def evaluate_model(model: InferenceModel, clips, options: EvalOptions = EvalOptions()) -> dict:
    """Evaluate ``model`` (on its device) on ``clips`` (paths) with ``options``. Returns {model, transform, device,
    mean, per_scale, per_clip, per_frame, ...} (docs/evaluation.md)."""
    o = options
    scales = o.scales
    if o.scale is not None:
        if scales is not None:
            raise ValueError("evaluate_model: give scales or scale, not both")
        scales = {str(c): [float(o.scale)] for c in clips}
    model.eval()
    video = VideoScorer(model.device) if o.cvvdp else None  # before any work: a missing extra is one line
    runner = FlipRunner() if o.flip else None
    baseline = Baseline(o.baseline, model.device) if isinstance(o.baseline, str) else o.baseline
    per_frame: list[dict] = []
    warnings: list[str] = []
    try:
        jobs = []  # (clip path, Clip, scale), checked before anything runs
        for c in clips:
            base = open_valid_clip(c)
            jobs += [(c, base, s_) for s_ in eval_scales(model.module, base, (scales or {}).get(str(c)))]
        for job in jobs:
            per_frame += _score_clip(model, job, o, runner, baseline, warnings, video)
    finally:
        if runner is not None:
            runner.close()
    if not per_frame:
        raise ClipError("no frame evaluated")
    if baseline is not None:
        mine = {(str(c), float(sc)) for c, _, sc in jobs}
        warnings += [f"{c} (x{sc:g}): no {baseline.name} baseline ({why})"
                     for (c, sc), why in baseline.missing.items() if (c, sc) in mine]
    return _result(model, clips, o, per_frame, warnings, runner, video)


def _score_clip(model: InferenceModel, job, o: EvalOptions, runner, baseline, warnings: list,
                video: "VideoScorer | None" = None) -> list[dict]:
    """The per-frame rows of one (clip path, Clip, scale) job; with ``video``, its ColorVideoVDP score too."""
    clip_path, base, s_clip = job
    source = ClipFrames(base.at_scale(s_clip), eps=model.demod_eps)
    key = f"{clip_path}@x{s_clip:g}"
    if not source.has("hr/radiance"):
        raise ClipError(f"{clip_path}: clip has no hr/radiance to compare with")
    model.module.follow_reference_filter(source.clip.manifest)
    mismatch = model.module.remod_filter_mismatch(source.clip.manifest, clip_path)
    if mismatch:
        log.warning(f"warning: {mismatch}")
    todo = list((o.frames or {}).get(str(clip_path)) or source.frames)
    first = model_inputs(model, source, todo[0])
    for _ in range(o.warmup):  # a recurrent model's warm-up runs start from no state and keep none
        model.step(first, None, o.amp)
    model.reset()  # a clip starts from no state (its first scored frame runs the frames before it)
    rows, prev = [], None
    frames = ClipVideo(clip_fps(source.clip.manifest)) if video is not None else None
    iterator = todo
    if o.progress:
        from tqdm import tqdm
        iterator = tqdm(todo, desc=f"{o.label or 'evaluate'} {Path(clip_path).name}", unit="frame",
                        file=sys.stderr, dynamic_ncols=True)
    for f in iterator:
        sr, ms, inputs = run_frame(model, source, f, key, o.amp)
        gt = inputs["hr/radiance"][0, -1].transpose(1, 2, 0)
        check_ground_truth(gt, clip_path, f)
        sr, bad = sanitize_output(sr)
        if bad:
            msg = (f"{clip_path} frame {f} (x{s_clip:g}): the model output {bad} non-finite value(s) "
                   "(NaN/Inf), scored as 0; its scores are not the model's")
            warnings.append(msg)
            log.warning(f"warning: {msg}")
        sq = metrics.squared_error(sr, gt)
        row = {"clip": str(clip_path), "frame": int(f), "scale": s_clip, "ms_per_frame": ms,
               "sr_nonfinite": bad, **_frame_scores(sr, gt, inputs, runner, o.delta_e_itp),
               "regions": _regions(source, f, sq), "materials": _materials(source, f, sq),
               **_temporal_scores(sr, gt, inputs, f, prev),
               **_worst_scores(sr, gt, sq, baseline.frame(clip_path, base, s_clip, f) if baseline else None)}
        prev = (f, sr, gt)
        rows.append(row)
        if frames is not None:
            frames.add(sr, gt)
        if o.save_images:
            name = Path(clip_path).name
            _save(Path(o.save_images), name if len(base.scales) == 1 else f"{name}_x{s_clip:g}", f, sr)
    if frames is not None:
        video.scores[(str(clip_path), s_clip)] = frames.score(video.metric)
    return rows


def _worst_scores(sr, gt, sq: np.ndarray, base) -> dict:
    """The worst-case scores of one frame: ``worst_share`` of the squared error ``sq`` and, with the baseline's
    (PSNR, pixels where its error is small) ``base``, its PSNR and the artifact pixels."""
    row = {"worst_share": metrics.worst_share(sq), "pixels": int(sq.size), "baseline_psnr": None,
           "artifact_pixels": None}
    if base is not None:
        row["baseline_psnr"] = base[0]
        row["artifact_pixels"] = int(metrics.artifact_mask(metrics.pixel_error(sr, gt), base[1]).sum())
    return row


def _result(model: InferenceModel, clips, o: EvalOptions, per_frame: list[dict], warnings: list, runner,
            video: "VideoScorer | None" = None) -> dict:
    mean, per_scale = _means(per_frame), {}
    for sc in sorted({r["scale"] for r in per_frame}):
        per_scale[f"{sc:g}"] = _means([r for r in per_frame if r["scale"] == sc])
    clips_rows = per_clip(per_frame)
    for c in clips_rows:
        c["cvvdp"] = video.scores.get((c["clip"], c["scale"])) if video is not None else None
    mean["cvvdp"] = _mean([c["cvvdp"] for c in clips_rows]) if video is not None else None
    for sc, m in per_scale.items():
        m["cvvdp"] = _mean([c["cvvdp"] for c in clips_rows if f"{c['scale']:g}" == sc]) if video else None
    return {
        "model": o.label or model.spec,
        "transform": metrics.TRANSFORM,
        "device": describe_device(model.device),
        "amp": str(o.amp).replace("torch.", "") if o.amp else "none",
        "scale": model.module.scale,
        "hdr_peak": metrics.HDR_PEAK,
        "itp_white_nits": metrics.ITP_WHITE_NITS if o.delta_e_itp else None,
        "psnr_cap_db": metrics.PSNR_CAP,
        "worst_case": {"baseline": None if o.baseline is None else getattr(o.baseline, "name", o.baseline),
                       "worst_fraction": metrics.WORST_FRACTION, "artifact_error": metrics.ARTIFACT_ERROR,
                       "artifact_baseline_error": metrics.ARTIFACT_BASELINE},
        "timing": f"median over frames of the forward pass after {o.warmup} warm-up runs, inputs on the device",
        "flip_failures": runner.failures if runner is not None else [],
        "cvvdp": None if video is None else {"unit": "JOD (10: no visible difference)", "display": video.display,
                                             "frames": "the evaluation tonemap (display-encoded sRGB)",
                                             "per": "clip (one video per clip and scale; mean over clips)"},
        "sr_nonfinite_frames": sum(1 for r in per_frame if r["sr_nonfinite"]),
        "warnings": warnings,
        "clips": [str(c) for c in clips],
        "mean": mean,
        "per_scale": per_scale,
        "per_clip": clips_rows,
        "per_frame": per_frame,
    }


def worst_case_line(result: dict) -> str:
    """One line of an ``evaluate_model`` result's worst case, for the terminal."""
    m, base = result["mean"], result["worst_case"]["baseline"]
    parts = []
    if m.get("margin") is not None:
        parts.append(f"margin over {base} {m['margin']:+.2f} dB, smallest per clip {m['margin_min']:+.2f} dB "
                     f"({Path(m['margin_min_clip']).name})")
    if m.get("worst_share") is not None:
        parts.append(f"the worst {metrics.WORST_FRACTION:.0%} of pixels carry {m['worst_share']:.0%} of the squared "
                     "error")
    if m.get("artifact_pixels") is not None:
        parts.append(f"{m['artifact_pixels']} artifact pixels ({m['artifact_fraction']:.3%})")
    return "  worst case: " + ("; ".join(parts) if parts else "not measured")


def per_clip(rows: list[dict]) -> list[dict]:
    """One summary per (clip, scale) of per-frame rows: frames, mean PSNR, the baseline's mean PSNR and the margin
    over it (None without a baseline), mean ``worst_share``, artifact pixels (sum) and their fraction."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["clip"], r["scale"]), []).append(r)
    out = []
    for (clip, scale), rs in groups.items():
        both = [r for r in rs if r.get("baseline_psnr") is not None]
        margin = _mean([r["psnr"] for r in both]) - _mean([r["baseline_psnr"] for r in both]) if both else None
        counted = [r for r in rs if r.get("artifact_pixels") is not None]
        n_art = sum(r["artifact_pixels"] for r in counted) if counted else None
        out.append({"clip": clip, "scale": scale, "frames": len(rs), "psnr": _mean([r["psnr"] for r in rs]),
                    "baseline_psnr": _mean([r["baseline_psnr"] for r in both]) if both else None, "margin": margin,
                    "worst_share": _mean([r.get("worst_share") for r in rs]), "artifact_pixels": n_art,
                    "artifact_fraction": n_art / sum(r["pixels"] for r in counted) if counted else None})
    return out


def _worst_means(rows: list[dict]) -> dict:
    """The worst case of ``rows`` beside their means: the mean baseline PSNR and margin over it (over the frames
    that have a baseline), the per-clip margins' minimum and its clip, the mean and largest per-clip
    ``worst_share``, the artifact pixels' count and fraction (all clips) and the largest per-clip fraction."""
    clips = per_clip(rows)
    have = [c for c in clips if c["margin"] is not None]
    worst = min(have, key=lambda c: c["margin"]) if have else None
    counted = [c for c in clips if c["artifact_pixels"] is not None]
    pixels = sum(r["pixels"] for r in rows if r.get("artifact_pixels") is not None)
    both = [r for r in rows if r.get("baseline_psnr") is not None]
    n_art = sum(c["artifact_pixels"] for c in counted) if counted else None
    return {"baseline_psnr": _mean([r["baseline_psnr"] for r in both]) if both else None,
            "margin": _mean([r["psnr"] for r in both]) - _mean([r["baseline_psnr"] for r in both]) if both else None,
            "margin_min": worst["margin"] if worst else None, "margin_min_clip": worst["clip"] if worst else None,
            "worst_share": _mean([r.get("worst_share") for r in rows]),
            "worst_share_max": max((c["worst_share"] for c in clips if c["worst_share"] is not None), default=None),
            "artifact_pixels": n_art, "artifact_fraction": n_art / pixels if counted else None,
            "artifact_fraction_max": max((c["artifact_fraction"] for c in counted), default=None)}


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


def _regions(source, frame: int, sq: np.ndarray) -> dict | None:
    """{region: {fraction, psnr, err_share}} of one frame's squared tonemapped error ``sq``
    (``metrics.squared_error``; ``gbuffer_export.regions``); None without HR flags and depth."""
    if not (source.has("hr/flags") and source.has("hr/depth")):
        return None
    return _breakdown(sq, pixel_regions(source.read(frame, "hr/flags"), source.read(frame, "hr/depth")))


def _materials(source, frame: int, sq: np.ndarray) -> dict | None:
    """{material class: {fraction, psnr, err_share}} of one frame's squared tonemapped error ``sq``
    (``gbuffer_export.regions.material_regions``); None without HR flags and roughness."""
    if not (source.has("hr/flags") and source.has("hr/roughness")):
        return None
    return _breakdown(sq, material_regions(source.read(frame, "hr/flags"), source.read(frame, "hr/roughness")))


def _breakdown(sq: np.ndarray, masks: dict) -> dict:
    return {name: {"fraction": v["fraction"], "err_share": v["err_share"],
                   "psnr": metrics.psnr_from_mse(v["mse"]) if v["mse"] is not None else None}
            for name, v in error_breakdown(sq, masks).items()}


def _region_means(rows: list[dict], key: str = "regions", names: tuple[str, ...] = REGIONS) -> dict | None:
    """The per-frame breakdown ``key`` (``regions`` or ``materials``) averaged over the frames that have it (each
    value over the frames where it is not None); None when no frame has it."""
    have = [r[key] for r in rows if r.get(key)]
    if not have:
        return None
    return {name: {k: _mean([h[name][k] for h in have]) for k in ("fraction", "psnr", "err_share")}
            for name in names}


def _save(root: Path, clip_name: str, frame: int, sr: np.ndarray) -> None:
    d = root / clip_name
    write_exr(d / f"{frame:06d}.exr", {c: sr[..., i] for i, c in enumerate("RGB")})
    import matplotlib.image as mpimg
    tm = metrics.tonemapped(sr)[0].permute(1, 2, 0).numpy()
    mpimg.imsave(d / f"{frame:06d}.png", np.clip(tm, 0, 1))
