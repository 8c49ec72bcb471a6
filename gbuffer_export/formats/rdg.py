"""BlendSR clips -> the layout the RDG authors' loader reads (``basicsr/data/render_dataset.py``,
``RenderRecurrentDataset`` and ``RenderRecurrentTestDataset``, of github.com/sunny2109/RDG)::

    OUT/GT/<scene>/Image/000.png        HR radiance, 8-bit sRGB PNG (their loader divides by 255)
    OUT/GT/<scene>/Normal/000.exr       world-space unit normal (Blender's Normal pass), RGB float32
    OUT/GT/<scene>/BRDF/000.exr         fbeta (pre-integrated BRDF), RGB
    OUT/GT/<scene>/Depth/000.exr        view depth, RGB (the same in each channel; background = largest depth)
    OUT/GT/<scene>/Motion/000.exr       backward motion in pixels, y up (R, G; B = 0)
    OUT/GT/<scene>/Emit/000.exr         emission, RGB
    OUT/LR/<scene>/...                  the same at the clip's primary LR level ('lr')
    OUT/LR_x<s>/<scene>/...             further LR levels of multi-scale clips
    OUT/meta_info_train.txt             '<scene> <frames> 0 0' per scene (their training meta file, no patches)
    OUT/meta_info_test.txt              '<scene> <frames> 0' per scene (their test meta file)

One scene per clip (or per contiguous run of frames of a clip with missing frames), named after the clip's folder
with anything but letters, digits, '_' and '-' made '_' and a suffix where a name repeats (``scene_name``).

Their loader reads every file with OpenCV (three channels, BGR order swapped to RGB), so every EXR has R, G, B.
Conversions in ``formats/conventions.py``; docs/formats.md lists what is lost. Pure numpy + OpenEXR.
"""
from __future__ import annotations

import logging
import re
import shutil
from pathlib import Path

import numpy as np

from ..clip import check_no_links, write_bytes_atomic
from ..exr import write_exr
from ..validate.gate import open_valid_clip
from ..errors import BlendSRError
from . import conventions as cv
from .nss import NSS_SPACE, frame_runs, source_clips
from .output import ExportOptions, Target, clean_temp_files
from ..format_limits import FORMATS, check_clips
from .png import write_png

log = logging.getLogger(__name__)

#: RDG buffer name -> BlendSR buffer it is written from.
BUFFER_MAP = {"Normal": "normal", "BRDF": "fbeta", "Depth": "depth", "Motion": "motion", "Emit": "emission"}
#: The buffers RDG's shipped configs read (``use_lq_normal``, ``use_lq_brdf``, ``use_lq_motion``, ``use_lq_depth``:
#: true in options/train/train_RDG_x4.yml, train_RDG-s_x4.yml and both test configs of github.com/sunny2109/RDG).
CONFIG_BUFFERS = tuple(b for b, src in BUFFER_MAP.items() if src in FORMATS["rdg"].read_buffers)
META_TRAIN, META_TEST = "meta_info_train.txt", "meta_info_test.txt"


class RdgError(BlendSRError):
    """An RDG export that cannot be written as asked (one line, exit code 2)."""


def scene_name(raw: str, taken) -> str:
    """A scene name RDG's meta-info files can hold (they split lines on whitespace) and a folder name can be:
    characters other than letters, digits, '_', '-' become '_', leading dots and '_' go, an empty name becomes
    'clip'; made unique against ``taken`` with '_2', '_3', ..."""
    base = re.sub(r"[^A-Za-z0-9_-]+", "_", raw).strip("_.-")[:100] or "clip"
    name, n = base, 1
    while name in taken:
        n += 1
        name = f"{base}_{n}"
    return name


def read_meta(out: Path) -> tuple[list[str], list[str]]:
    """The lines of an RDG export's meta-info files (train, test); empty when there are none."""
    lines = []
    for f in (META_TRAIN, META_TEST):
        p = out / f
        lines.append([ln for ln in check_no_links(out, p).read_text().splitlines() if ln.strip()]
                     if p.is_file() else [])
    return lines[0], lines[1]


def is_rdg_export(out: Path) -> bool:
    return (out / META_TRAIN).is_file()


def remove_orphan_scenes(out: Path, scenes: set[str]) -> None:
    """Remove scene folders (``GT/<scene>``, ``LR*/<scene>``) that the meta-info files do not list: an append
    killed while moving its files in."""
    for root in sorted(p for p in out.iterdir() if p.is_dir() and not p.is_symlink()
                       and (p.name == "GT" or p.name.startswith("LR"))):
        for d in sorted(root.iterdir()):
            if d.is_dir() and not d.is_symlink() and d.name not in scenes:
                log.warning(f"{d}: removing a scene folder the meta-info files do not list (an interrupted append)")
                shutil.rmtree(d)


def _rgb_exr(path: Path, a: np.ndarray) -> None:
    a = np.asarray(a, np.float32)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, -1)
    if a.shape[-1] == 2:
        a = np.concatenate([a, np.zeros(a.shape[:2] + (1,), np.float32)], -1)
    write_exr(path, {"R": a[..., 0], "G": a[..., 1], "B": a[..., 2]})


def rdg_buffer(clip, frame: int, level: str, name: str) -> np.ndarray:
    """RDG buffer ``name`` (a key of BUFFER_MAP, or 'Image' as linear values before sRGB encoding) of a frame;
    radiance and emission exposed (the clip's exposure), so Image = BRDF * irradiance + Emit holds as in the clip."""
    if name == "Image":
        return clip.read(frame, f"{level}/radiance", space=NSS_SPACE, exposed=True)
    src = BUFFER_MAP[name]
    if src in ("fbeta", "emission"):
        return clip.read(frame, f"{level}/{src}", space=NSS_SPACE, exposed=True)
    a = clip.read(frame, f"{level}/{src}")
    if name == "Depth":
        return cv.depth_for_rdg(a[..., 0])
    if name == "Motion":
        return cv.motion_to_rdg(a)
    # Normal: camera space -> world space (Blender's Normal pass), 0 stays 0 on background
    r = clip.camera(frame, level)["world_from_camera"][:3, :3]
    return a @ r.T


def _export_scene(clip, frames: list[int], work: Path, scene: str, bufs: list[str]) -> None:
    roots = {"hr": work / "GT"}
    for sc in clip.scales:
        lvl = clip.level_at(sc)
        roots[lvl] = work / ("LR" if lvl == "lr" else f"LR_x{sc:g}")
    for j, f in enumerate(frames):
        for lvl, root in roots.items():
            base = root / scene
            img = np.round(cv.srgb_encode(rdg_buffer(clip, f, lvl, "Image")) * 255).astype(np.uint8)
            write_png(base / "Image" / f"{j:03d}.png", img)
            for b in bufs:
                _rgb_exr(base / b / f"{j:03d}.exr", rdg_buffer(clip, f, lvl, b))


def export_rdg(sources, out, options: ExportOptions = ExportOptions()) -> dict:
    """Write every clip of ``sources`` in RDG's layout under ``out`` (one scene per clip, or per contiguous run of
    a clip with missing frames), by the output rules of ``formats.output``; returns {scene: [RDG buffers
    written]}. A clip lacking a buffer RDG's shipped configs read is exported with a warning naming them."""
    options.validate()
    out = Path(out)
    target = Target(out, sources, options.mode, is_export=is_rdg_export, fmt="rdg")
    clips = [open_valid_clip(p) for p in source_clips(sources)]
    if not clips:
        raise RdgError(f"{', '.join(map(str, sources))}: no finished clips to export")
    check_clips("rdg", clips, RdgError)  # every limit of the consumer, before anything is written
    train, test = [], []
    written: dict[str, list[str]] = {}
    with target:  # holds OUT's lock when appending: the scenes read below are the export's as this one ends
        if target.appending:
            train, test = read_meta(out)
            remove_orphan_scenes(out, {ln.split()[0] for ln in train + test})
            clean_temp_files(out)
        taken = {ln.split()[0] for ln in train + test}
        for clip in clips:
            bufs = [b for b, src in BUFFER_MAP.items() if src in clip.buffers]
            lacking = [f"{b} ({BUFFER_MAP[b]})" for b in CONFIG_BUFFERS if b not in bufs]
            if lacking:
                log.warning(f"{clip.path}: lacks {', '.join(lacking)}, which RDG's shipped configs read "
                            "(use_lq_*: true); render it with --buffers all or --for-models rdg")
            runs = frame_runs(clip.frames)
            if len(runs) > 1:
                log.warning(f"{clip.path}: frames missing between {', '.join(f'{r[0]}-{r[-1]}' for r in runs)}: "
                            f"exported as {len(runs)} scenes")
            raw = clip.path.resolve().name
            for run in runs:
                scene = scene_name(raw if len(runs) == 1 else f"{raw}_f{run[0]}", taken)
                taken.add(scene)
                _export_scene(clip, run, target.work, scene, bufs)
                train.append(f"{scene} {len(run)} 0 0")
                test.append(f"{scene} {len(run)} 0")
                written[scene] = bufs
            if options.progress:
                options.progress(clip.path, scene)
        write_bytes_atomic(target.work / META_TRAIN, ("\n".join(train) + "\n").encode())  # a full disk names it
        write_bytes_atomic(target.work / META_TEST, ("\n".join(test) + "\n").encode())
        target.commit(last=(META_TRAIN, META_TEST))
    return written
