"""The clips a command runs on (torch-free): ``--data`` arguments expanded to clip directories, and their one scale.
Used by ``blendsr train/evaluate`` (``training.commands``) and ``bench models`` (``training.bench_models``)."""
from __future__ import annotations

from pathlib import Path

from gbuffer_export.errors import BlendSRError


def dataset_clips(paths, split: str, missing_ok: bool = False) -> list[Path]:
    """--data arguments with every dataset folder replaced by the finished clips of its ``split``; with
    ``missing_ok`` only the dataset folders' clips of that (optional) split."""
    from gbuffer_export.dataset.build import DatasetError, expand_data_paths, is_dataset, split_clips
    if missing_ok:  # the optional split of dataset folders only
        out = []
        for p in paths:
            if is_dataset(p):
                out += split_clips(p, split)
        return out
    try:
        return expand_data_paths(paths, split)
    except DatasetError as exc:
        raise BlendSRError(str(exc)) from None


def scale_of(clips) -> int:
    """The one scale of ``clips`` (their 'lr' level); BlendSRError when they differ."""
    from gbuffer_export.clip import open_clip
    scales = {open_clip(c).scale for c in clips}
    if len(scales) != 1:
        raise BlendSRError(f"clips have different scales {sorted(scales)}; evaluate one scale at a time")
    return scales.pop()
