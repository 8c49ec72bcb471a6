"""Frames of a clip as the models read them, without torch (the inference API's and ONNX Runtime's reader).

``ClipFrames`` reads a clip's EXRs with the derived buffers of ``ClipCache`` ('irradiance', 'fbeta_used'), computed
with ``gbuffer_export.demod.demodulate`` as the training cache does; ``training.inference.loading.ClipFrames`` computes them
with the torch mirror (``training.demod``) instead, as the torch path always has.
"""
from __future__ import annotations

import os
from collections import OrderedDict
from pathlib import Path

import numpy as np

from gbuffer_export.clip import Clip, open_clip
from gbuffer_export.colour_spaces import TRAINING_SPACE
from gbuffer_export.conventions import LEVELS
from training.cache import DERIVED, lr_jitter
from training.config import DataConfig


class ClipFrames:
    """Frames of a clip read from its EXR files, with the derived buffers of ``ClipCache`` ('irradiance',
    'fbeta_used') and the per-frame depth reference. Keeps the last few decoded buffers."""

    def __init__(self, clip: Clip | str | os.PathLike, eps: float | None = None, keep: int = 64):
        self.clip = clip if isinstance(clip, Clip) else open_clip(clip)
        self.clip.colour_matrix(TRAINING_SPACE)  # ClipError now for a working space blendsr cannot convert
        self.clip_path = Path(self.clip.path)
        self.eps = float(DataConfig.demod_eps if eps is None else eps)  # default: the training default
        self.frames = list(self.clip.frames)
        self.scale = self.clip.scale
        self.sizes = self.clip.sizes
        self._keep = keep
        self._lru: OrderedDict = OrderedDict()

    def jitter(self, frame: int) -> np.ndarray:
        return lr_jitter(self.clip, frame)

    def has(self, key: str) -> bool:
        level, _, name = key.partition("/")
        if level not in LEVELS:
            return False
        if name in DERIVED:
            return {"radiance", "fbeta"} <= set(self.clip.buffers)
        return name in self.clip.buffers

    def _get(self, frame: int, key: str) -> np.ndarray:
        k = (frame, key)
        if k in self._lru:
            self._lru.move_to_end(k)
            return self._lru[k]
        level, _, name = key.partition("/")
        if name in DERIVED:
            irr, fbu = self._demodulate(frame, level)
            self._put((frame, f"{level}/irradiance"), irr)
            self._put((frame, f"{level}/fbeta_used"), fbu)
            return irr if name == "irradiance" else fbu
        a = self.clip.read(frame, key, space=TRAINING_SPACE, exposed=True)
        self._put(k, a)
        return a

    def _put(self, k, a) -> None:
        self._lru[k] = a
        while len(self._lru) > self._keep:
            self._lru.popitem(last=False)

    def _demodulate(self, frame: int, level: str) -> tuple[np.ndarray, np.ndarray]:
        from gbuffer_export.demod import demodulate
        em = self._get(frame, f"{level}/emission") if "emission" in self.clip.buffers else None
        fl = self._get(frame, f"{level}/flags") if "flags" in self.clip.buffers else None
        return demodulate(self._get(frame, f"{level}/radiance"), em, self._get(frame, f"{level}/fbeta"), fl, self.eps)

    def read(self, frame: int, key: str) -> np.ndarray:
        return self._get(frame, key)

    def depth_ref(self, frame: int) -> float:
        d = self._get(frame, "lr/depth")[..., 0]
        fin = d[np.isfinite(d) & (d > 0)]
        return float(np.median(fin)) if fin.size else 1.0


def lead_in(frames, first: int) -> list[int]:
    """The run of consecutive clip frames that ends just before ``first`` (what a recurrent model runs, from the
    clip's start or the last gap, before it reaches ``first``)."""
    have = set(int(f) for f in frames)
    out = []
    g = int(first) - 1
    while g in have:
        out.append(g)
        g -= 1
    return out[::-1]
