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
    OUT/meta_info_train.txt             '<scene> <frames> 0 0' per clip (their training meta file, no patches)
    OUT/meta_info_test.txt              '<scene> <frames> 0' per clip (their test meta file)

Their loader reads every file with OpenCV (three channels, BGR order swapped to RGB), so every EXR has R, G, B.
Conversions in ``formats/conventions.py``; docs/formats.md lists what is lost. Pure numpy + OpenEXR.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..clip import open_clip
from ..exr import write_exr
from . import conventions as cv
from .nss import NSS_SPACE, source_clips
from .png import write_png

#: RDG buffer name -> BlendSR buffer it is written from.
BUFFER_MAP = {"Normal": "normal", "BRDF": "fbeta", "Depth": "depth", "Motion": "motion", "Emit": "emission"}


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


def export_rdg(sources, out, *, progress=None) -> dict:
    """Write every clip of ``sources`` in RDG's layout under ``out``; returns {scene: [RDG buffers written]}."""
    out = Path(out)
    written, train, test = {}, [], []
    for i, c in enumerate(source_clips(sources)):
        clip = open_clip(c)
        scene = clip.path.name if clip.path.name not in written else f"{clip.path.name}_{i}"
        have = set(clip.manifest.get("buffers", ()))
        bufs = [b for b, src in BUFFER_MAP.items() if src in have]
        roots = {"hr": out / "GT"}
        for s in clip.scales:
            lvl = clip.level_at(s)
            roots[lvl] = out / ("LR" if lvl == "lr" else f"LR_x{s:g}")
        frames = sorted(clip.frames)
        for j, f in enumerate(frames):
            for lvl, root in roots.items():
                base = root / scene
                img = np.round(cv.srgb_encode(rdg_buffer(clip, f, lvl, "Image")) * 255).astype(np.uint8)
                write_png(base / "Image" / f"{j:03d}.png", img)
                for b in bufs:
                    _rgb_exr(base / b / f"{j:03d}.exr", rdg_buffer(clip, f, lvl, b))
        train.append(f"{scene} {len(frames)} 0 0")
        test.append(f"{scene} {len(frames)} 0")
        written[scene] = bufs
        if progress:
            progress(c, scene)
    out.mkdir(parents=True, exist_ok=True)
    (out / "meta_info_train.txt").write_text("\n".join(train) + "\n")
    (out / "meta_info_test.txt").write_text("\n".join(test) + "\n")
    return written
