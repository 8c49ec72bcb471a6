"""Batches for training and full frames for inference (numpy; torch conversion happens in the caller).

A batch maps keys ('lr/irradiance', 'hr/radiance', ...) to float32 arrays (B, T, C, H, W) plus 'depth_ref' (B, T),
'lr_jitter' (B, T, 2: each LR frame's sub-pixel sample offset (dx, dy) in LR pixels, augmented like motion) and
'scale' (B,: the upscaling factor s, one per batch). LR keys hold ``lr_window`` consecutive frames ending at the
sample's current frame; HR keys hold the last ``hr_window`` of them. Crops are aligned across levels: an LR crop of
c x c pixels at (x0, y0) pairs with the HR crop of (s c) x (s c) at (s x0, s y0); for a non-integer s = p/q (lowest
terms) x0, y0 and c are multiples of q, so that these are integers. Motion vectors stay in pixels of their own
level. With caches of several scales (one ``ClipCache`` per clip and LR level) each batch first draws its scale,
uniformly among them, then its samples among that scale's caches.

Sampling is a pure function of (seed, rank, step): batch k is the same whether training ran straight or was
resumed, and a background thread may prepare it ahead of time (``Prefetcher``).
"""
from __future__ import annotations

import queue
import threading
from dataclasses import dataclass

import numpy as np

from gbuffer_export.clip import ClipError
from gbuffer_export.conventions import scale_fraction
from gbuffer_export.demod import undivided_mask
from training.augment import Augmentation, apply, apply_vector
from training.cache import DERIVED, DERIVED_FROM
from training.models import OPTIONAL_KEYS


FRAME_KEYS = ("depth_ref", "lr_jitter")  # per-frame values, not images
BATCH_KEYS = ("scale",)  # per-batch-element values, in every batch


@dataclass
class Sample:
    """Where a batch element came from: clip, frames of its LR window, LR crop corner, augmentation."""

    clip: str
    frames: list[int]
    x0: int = 0
    y0: int = 0
    aug: Augmentation | None = None


@dataclass
class BatchSpec:
    """What a batch holds: LR and HR keys, window lengths, crop (LR pixels; 0 = full frame), augmentation."""

    lr_keys: tuple[str, ...]
    hr_keys: tuple[str, ...]
    lr_window: int
    hr_window: int
    crop: int = 0
    flip: bool = False
    rotate: bool = False
    exposure_range: tuple[float, float] = (1.0, 1.0)
    reflectance_range: tuple[float, float] = (1.0, 1.0)
    depth_ref: bool = True
    jitter: bool = False

    @staticmethod
    def for_model(model, targets=("hr/radiance",), temporal: bool = False, window: int = 0, also=None,
                  **kw) -> "BatchSpec":
        """``window`` > 0 (recurrent models): every key, LR and HR, holds ``window`` consecutive frames (a target
        for every frame); ``temporal`` then only adds HR motion. ``also``: a second model whose inputs the batches
        hold too (the baseline of ``loss.baseline_weight``), read on the current frame."""
        needs = tuple(model.needs()) + (tuple(also.needs()) if also is not None else ())
        keys = [k for k in needs if k not in FRAME_KEYS + BATCH_KEYS] + list(targets)
        if temporal:
            keys.append("hr/motion")
        extra = 1 if temporal and not window else 0
        lr = [k for k in keys if k.startswith("lr/")]
        hr = [k for k in keys if k.startswith("hr/")]
        return BatchSpec(lr_keys=tuple(dict.fromkeys(lr)), hr_keys=tuple(dict.fromkeys(hr)),
                         lr_window=window or model.window + extra, hr_window=window or 1 + extra,
                         depth_ref="depth_ref" in needs, jitter="lr_jitter" in needs, **kw)

    @property
    def cache_keys(self) -> list[str]:
        keys = list(self.lr_keys) + list(self.hr_keys)
        if self.depth_ref:
            keys.append("lr/depth")
        return list(dict.fromkeys(keys))


def present_keys(source, keys) -> list[str]:
    """The keys a source can provide; a missing non-optional key is a ClipError naming the clip."""
    out = []
    for k in keys:
        if source.has(k):
            out.append(k)
        elif k not in OPTIONAL_KEYS:
            lvl, _, name = k.partition("/")
            lacking = [f"{lvl}/{b}" for b in DERIVED_FROM if b not in source.clip.buffers] \
                if name in DERIVED else []
            what = (f"{' and '.join(map(repr, lacking))} (from which {k!r} is computed)" if lacking
                    else repr(k))
            raise ClipError(f"{source.clip_path}: clip lacks {what}, which the model needs "
                            f"(has {', '.join(source.clip.buffers)})")
    return out


def windows(frames: list[int], length: int) -> list[int]:
    """Positions i in ``frames`` such that frames[i-length+1 .. i] are consecutive frame numbers."""
    out = []
    for i in range(length - 1, len(frames)):
        if frames[i] - frames[i - length + 1] == length - 1:
            out.append(i)
    return out


def crop_grid(scale: float, crop: int) -> tuple[int, int]:
    """(q, c): LR crop corners on multiples of q (the denominator of ``scale`` = p/q) and the LR crop size ``crop``
    rounded down to a multiple of q, so that the HR corner s x0 and size s c are integers. Integer scales: (1, crop)."""
    q = scale_fraction(float(scale)).denominator
    return q, (crop // q) * q


class TrainSampler:
    """Random aligned crops of random frame windows from several cached clips (one cache per clip and LR level;
    each batch is of one scale)."""

    def __init__(self, caches, spec: BatchSpec, batch_size: int, seed: int, rank: int = 0, val_frames: int = 0):
        self.caches = caches
        self.spec = spec
        self.batch_size = batch_size
        self.seed = int(seed)
        self.rank = int(rank)
        out_keys = list(spec.lr_keys) + list(spec.hr_keys)
        self.keys = [present_keys(c, out_keys) for c in caches]
        self.items: list[tuple[int, int]] = []
        for ci, c in enumerate(caches):
            frames = c.frames[:len(c.frames) - val_frames] if val_frames else c.frames
            w, h = c.sizes["lr"]
            if spec.crop > min(w, h):
                raise ClipError(f"{c.clip_path}: LR size {w}x{h} at scale {c.scale:g} is smaller than data.crop = "
                                f"{spec.crop}; data.crop = {min(w, h)} (or less) fits it")
            if spec.crop and crop_grid(c.scale, spec.crop)[1] == 0:
                raise ClipError(f"{c.clip_path}: data.crop = {spec.crop} is smaller than the crop grid of scale "
                                f"{c.scale:g} ({crop_grid(c.scale, 1)[0]} LR pixels); raise data.crop")
            self.items += [(ci, i) for i in windows(frames, spec.lr_window)]
        if not self.items:
            raise ClipError(f"no window of {spec.lr_window} consecutive training frames in "
                            f"{', '.join(str(c.clip_path) for c in caches)} (lower history/val_frames or add frames)")
        #: the scales of the caches (sorted) and, per scale, the items of its caches
        self.scales: list[float] = sorted({float(c.scale) for c in caches})
        self.items_by_scale = [[it for it in self.items if float(caches[it[0]].scale) == s] for s in self.scales]
        self.scale = caches[0].scale if len(self.scales) == 1 else None

    def state_dict(self) -> dict:
        return {"seed": self.seed, "rank": self.rank, "items": len(self.items)}

    def batch(self, step: int) -> tuple[dict[str, np.ndarray], list[Sample]]:
        rng = np.random.default_rng([self.seed, self.rank, int(step)])
        samples = []
        parts: dict[str, list[np.ndarray]] = {}
        si = int(rng.integers(len(self.scales))) if len(self.scales) > 1 else 0
        s, items = self.scales[si], self.items_by_scale[si]
        q, c = crop_grid(s, self.spec.crop) if self.spec.crop else (1, 0)
        all_keys = list(dict.fromkeys(k for ci, _ in items for k in self.keys[ci]))
        for _ in range(self.batch_size):
            ci, pos = items[int(rng.integers(len(items)))]
            cache = self.caches[ci]
            w, h = cache.sizes["lr"]
            y0 = q * int(rng.integers((h - c) // q + 1))
            x0 = q * int(rng.integers((w - c) // q + 1))
            aug = Augmentation.draw(rng, self.spec.flip, self.spec.rotate, self.spec.exposure_range,
                                    self.spec.reflectance_range)
            frames = cache.frames[pos - self.spec.lr_window + 1: pos + 1]
            samples.append(Sample(str(cache.clip_path), list(frames), x0, y0, aug))
            for key in all_keys:
                parts.setdefault(key, []).append(
                    crop_window(cache, key, pos, self.spec, (x0, y0), aug, s, c) if key in self.keys[ci]
                    else zeros_like_key(cache, key, self.spec, s, c))
            if self.spec.depth_ref:
                refs = np.array([cache.depth_ref(f) for f in frames], dtype=np.float32)
                parts.setdefault("depth_ref", []).append(refs)
            if self.spec.jitter:
                jit = np.stack([cache.jitter(f) for f in frames]).astype(np.float32)
                parts.setdefault("lr_jitter", []).append(apply_vector(jit, aug))
        out = {k: np.stack(v) for k, v in parts.items()}
        out["scale"] = np.full(self.batch_size, s, np.float32)
        return out, samples


def _window_len(key: str, spec: BatchSpec) -> int:
    return spec.lr_window if key.startswith("lr/") else spec.hr_window


def crop_window(cache, key: str, pos: int, spec: BatchSpec, xy: tuple[int, int], aug: Augmentation,
                scale: float, crop: int | None = None) -> np.ndarray:
    """(T, C, h, w) float32 crop of ``key`` for the window ending at row ``pos``, augmented. ``xy`` and ``crop``
    (default ``spec.crop``) in LR pixels; HR keys are cropped at ``scale`` times them (integers: ``crop_grid``)."""
    t = _window_len(key, spec)
    x0, y0 = xy
    c = spec.crop if crop is None else crop
    if key.startswith("hr/"):
        x0, y0, c = round(x0 * scale), round(y0 * scale), round(c * scale)
    rows, cols = slice(pos - t + 1, pos + 1), (slice(y0, y0 + c), slice(x0, x0 + c))
    a = np.asarray(cache.array(key)[(rows, *cols)], dtype=np.float32)
    unit = None
    level, _, name = key.partition("/")
    if aug.reflectance != (1.0, 1.0, 1.0) and name in ("irradiance", "fbeta_used"):
        # F_used is cached together with the irradiance
        f = a if name == "fbeta_used" else cache.array(f"{level}/fbeta_used")[(rows, *cols)]
        unit = undivided_mask(f)
    a = apply(key, a, aug, unit)
    return a.transpose(0, 3, 1, 2)


def zeros_like_key(cache, key: str, spec: BatchSpec, scale: float, crop: int | None = None) -> np.ndarray:
    c = spec.crop if crop is None else crop
    c = round(c * scale) if key.startswith("hr/") else c
    return np.zeros((_window_len(key, spec), 3, c, c), np.float32)


def frame_window(source, frame: int, spec: BatchSpec) -> dict[str, np.ndarray]:
    """Full-frame inputs (1, T, C, H, W) for ``frame`` from a cache or a ``ClipFrames`` reader. Frames before the
    clip's first frame (or missing) are replaced by the oldest available frame of the window, with zero motion."""
    frames = source.frames
    if frame not in frames:
        raise ClipError(f"{source.clip_path}: frame {frame} is not a finished frame")
    t = spec.lr_window
    wanted = [frame - t + 1 + i for i in range(t)]
    have = set(frames)
    first_ok = next(f for f in wanted if all(g in have for g in range(f, frame + 1)))
    out = {}
    keys = present_keys(source, list(spec.lr_keys) + list(spec.hr_keys))
    for key in keys:
        n = _window_len(key, spec)
        stack = []
        for f in wanted[t - n:]:
            a = source.read(max(f, first_ok), key).astype(np.float32)
            if f < first_ok and key.endswith(("/motion", "/motion_next")):
                a = np.zeros_like(a)
            stack.append(a.transpose(2, 0, 1))
        out[key] = np.stack(stack)[None]
    if spec.depth_ref:
        out["depth_ref"] = np.array([[source.depth_ref(max(f, first_ok)) for f in wanted]], dtype=np.float32)
    if spec.jitter:
        out["lr_jitter"] = np.stack([source.jitter(max(f, first_ok)) for f in wanted])[None].astype(np.float32)
    out["scale"] = np.array([source.scale], np.float32)
    return out


class Prefetcher:
    """Prepares ``sampler.batch(step)`` for the next steps in a background thread (numpy releases the GIL in
    copies). Deterministic: batch k only depends on k."""

    def __init__(self, sampler: TrainSampler, start_step: int, depth: int):
        self.sampler = sampler
        self.depth = depth
        self.next_step = start_step
        if depth > 0:
            self.q: queue.Queue = queue.Queue(maxsize=depth)
            self.stop = threading.Event()
            self.thread = threading.Thread(target=self._run, args=(start_step,), daemon=True)
            self.thread.start()

    def _run(self, step: int) -> None:
        while not self.stop.is_set():
            try:
                item = (step, self.sampler.batch(step), None)
            except Exception as exc:  # surfaced in get()
                item = (step, None, exc)
            while not self.stop.is_set():
                try:
                    self.q.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if item[2] is not None:
                return
            step += 1

    def get(self, step: int):
        if self.depth == 0:
            return self.sampler.batch(step)
        got, value, exc = self.q.get()
        if exc is not None:
            raise exc
        assert got == step, f"prefetcher out of order ({got} != {step})"
        return value

    def close(self) -> None:
        if self.depth > 0:
            self.stop.set()
            self.thread.join(timeout=5)
