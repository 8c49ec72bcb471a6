"""A window batch (every ``lr/`` key has a time axis T): its length and one frame of it (the recurrent models' step
inputs; ``training.recurrent`` runs the windows)."""
from __future__ import annotations


def window_length(batch: dict) -> int:
    return next(v.shape[1] for k, v in batch.items() if k.startswith("lr/"))


def frame_slice(batch: dict, i: int) -> dict:
    """The one-frame batch of frame ``i`` of a window batch (every key keeps its time axis, of length 1). Keys with
    fewer frames (HR keys of an inference batch) end at the same current frame: their frame i - (T - T_key),
    clamped to their first. A per-batch value without a time axis, ``scale`` (B,), is kept as it is."""
    t = window_length(batch)
    out = {}
    for k, v in batch.items():
        if v.dim() < 2:
            out[k] = v
            continue
        j = max(i - (t - v.shape[1]), 0)
        out[k] = v[:, j:j + 1]
    return out
