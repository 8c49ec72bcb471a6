"""The clips a command runs on (torch-free): ``--data`` arguments expanded to clip directories, and their one scale.
Used by ``blendsr train/evaluate`` (``training.commands.cli``) and ``bench models`` (``training.commands.bench_models``)."""
from __future__ import annotations

from pathlib import Path

from gbuffer_export.errors import BlendSRError


def dataset_clips(paths, split: str, missing_ok: bool = False) -> list[Path]:
    """--data arguments with every dataset folder replaced by the finished clips of its ``split``; with
    ``missing_ok`` only the dataset folders' clips of that (optional) split. A dataset whose index puts one scene in
    two splits is refused (``refuse_split_leak``)."""
    from gbuffer_export.dataset.build import DatasetError, expand_data_paths, is_dataset, split_clips
    for p in paths:
        if is_dataset(p):
            refuse_split_leak(Path(p))
    if missing_ok:  # the optional split of dataset folders only
        out = []
        for p in paths:
            if is_dataset(p):
                out += split_clips(p, split)
        return out
    try:
        return expand_data_paths(paths, split)  # every index path checked first (clip_dir)
    except DatasetError as exc:
        raise BlendSRError(str(exc)) from None


def refuse_split_leak(root: Path) -> None:
    """A dataset whose index puts one scene (asset, region) in two splits is refused, in validate's words
    (gbuffer_export.dataset.check.split_leaks): nothing is trained or scored on a leaked split."""
    from gbuffer_export.dataset.build import INDEX, read_index
    from gbuffer_export.dataset.check import split_leaks
    leaks = split_leaks(root, read_index(root))
    if leaks:
        more = f" (and {len(leaks) - 1} more)" if len(leaks) > 1 else ""
        raise BlendSRError(f"{root / INDEX}: {leaks[0]}{more}: a split leak; 'blendsr validate {root}' reports the "
                           "same, fix the index or re-export the dataset")


def scale_of(clips) -> int:
    """The one scale of ``clips`` (their 'lr' level); BlendSRError when they differ."""
    from gbuffer_export.clip import open_clip
    scales = {open_clip(c).scale for c in clips}
    if len(scales) != 1:
        raise BlendSRError(f"clips have different scales {sorted(scales)}; evaluate one scale at a time")
    return scales.pop()
