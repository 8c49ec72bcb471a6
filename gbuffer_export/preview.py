"""Images a person can look at: tonemapped radiance, false-colour G-buffers and a contact sheet of a clip
(numpy, colour-science and Pillow)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import BlendSRError
from .colour_spaces import srgb_encode
from .conventions import Flag


#: Linear space whose RGB the sRGB encoding displays (the sRGB primaries are BT.709's).
DISPLAY_SPACE = "Linear Rec.709"


def tonemap(radiance: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Display encoding of linear HDR radiance, the numpy reference of the evaluation tonemap
    (``training.transforms.tonemap``): Reinhard v / (1 + v) per channel, v = max(radiance * exposure, 0), then the
    sRGB encoding. NaN and -inf become 0, +inf 1e6. Float64 in [0, 1], shape of ``radiance``."""
    x = np.nan_to_num(np.asarray(radiance, np.float64) * exposure, nan=0.0, posinf=1e6, neginf=0.0)
    x = np.maximum(x, 0.0)
    return srgb_encode(x / (1.0 + x))


def normal_rgb(n: np.ndarray) -> np.ndarray:
    return np.clip(0.5 * (n + 1.0), 0, 1) * (np.linalg.norm(n, axis=-1, keepdims=True) > 0)


def depth_rgb(d: np.ndarray) -> np.ndarray:
    d = d[..., 0]
    fin = np.isfinite(d)
    if not fin.any():
        return np.zeros((*d.shape, 3))
    inv = np.where(fin, 1.0 / np.maximum(d, 1e-6), 0.0)
    lo, hi = np.percentile(inv[fin], [1, 99])
    v = np.clip((inv - lo) / max(hi - lo, 1e-9), 0, 1) * fin
    return np.repeat(v[..., None], 3, axis=-1)


def motion_rgb(m: np.ndarray, max_px: float | None = None) -> np.ndarray:
    """Direction as hue, magnitude as brightness (normalised by ``max_px`` or the 99th percentile)."""
    mag = np.linalg.norm(m, axis=-1)
    scale = max_px or max(float(np.percentile(mag, 99)), 1e-6)
    ang = np.arctan2(m[..., 1], m[..., 0])
    hue = (ang / (2 * np.pi)) % 1.0
    v = np.clip(mag / scale, 0, 1)
    k = (np.array([5.0, 3.0, 1.0]) + hue[..., None] * 6) % 6
    rgb = 1 - np.clip(np.minimum(k, 4 - k), 0, 1)
    return rgb * v[..., None]


def flags_rgb(f: np.ndarray) -> np.ndarray:
    f = f[..., 0].astype(np.int64)
    out = np.zeros((*f.shape, 3))
    out[(f & int(Flag.BACKGROUND)) > 0] = (0.1, 0.1, 0.3)
    from .conventions import UNTRUSTED
    out[(f & int(UNTRUSTED)) > 0] = (0.9, 0.3, 0.1)
    out[(f & int(Flag.MOVING)) > 0] += (0.0, 0.6, 0.0)
    out[(f & int(Flag.EMISSIVE)) > 0] += (0.6, 0.6, 0.0)
    return np.clip(out, 0, 1)


def visualize(name: str, arr: np.ndarray) -> np.ndarray:
    """H x W x 3 display image in [0, 1] of a clip buffer."""
    if name in ("radiance", "emission"):
        return tonemap(arr)
    if name in ("albedo", "fbeta"):
        return srgb_encode(arr)
    if name == "normal":
        return normal_rgb(arr)
    if name == "depth":
        return depth_rgb(arr)
    if name == "motion":
        return motion_rgb(arr)
    if name == "flags":
        return flags_rgb(arr)
    return np.repeat(np.clip(arr[..., :1], 0, 1), 3, axis=-1)


def upscale_nearest(img: np.ndarray, factor: float) -> np.ndarray:
    """Nearest-neighbour upscaling of H x W [x C] to round(H factor) x round(W factor); any factor >= 1."""
    h, w = img.shape[:2]
    ys = np.minimum(((np.arange(round(h * factor)) + 0.5) / factor).astype(np.int64), h - 1)
    xs = np.minimum(((np.arange(round(w * factor)) + 0.5) / factor).astype(np.int64), w - 1)
    return img[ys][:, xs]


def save_png(path: str | Path, img: np.ndarray) -> None:
    """Write an H x W x 3 image in [0, 1] as 8-bit PNG (atomically)."""
    import os

    from PIL import Image
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}.png")
    Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)).save(tmp)
    os.replace(tmp, path)


def labelled_grid(tiles: list[list[tuple[str, np.ndarray]]], pad: int = 4) -> np.ndarray:
    """Compose rows of (label, image) tiles of equal size into one image with labels drawn on the tiles."""
    from PIL import Image, ImageDraw
    h, w = tiles[0][0][1].shape[:2]
    ncol = max(len(r) for r in tiles)
    canvas = Image.new("RGB", (ncol * (w + pad) + pad, len(tiles) * (h + pad) + pad), (24, 24, 24))
    draw = ImageDraw.Draw(canvas)
    for i, row in enumerate(tiles):
        for j, (label, img) in enumerate(row):
            x, y = pad + j * (w + pad), pad + i * (h + pad)
            canvas.paste(Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)), (x, y))
            draw.rectangle([x, y, x + 6 * len(label) + 4, y + 12], fill=(0, 0, 0))
            draw.text((x + 2, y), label, fill=(255, 255, 255))
    return np.asarray(canvas).astype(np.float64) / 255.0


def contact_sheet(clip, path: str | Path, frames: list[int] | None = None, max_frames: int = 3) -> Path:
    """PNG contact sheet of a clip: per frame one row with LR radiance (nearest-upscaled), HR radiance and every HR
    G-buffer the clip holds; colours converted from the clip's working space to Linear Rec.709 (sRGB primaries)."""
    frames = frames or clip.frames[:: max(1, len(clip.frames) // max_frames)][:max_frames]
    rows = []
    for f in frames:
        lr = clip.read(f, "lr/radiance", space=DISPLAY_SPACE)
        row = [(f"f{f} lr/radiance", upscale_nearest(visualize("radiance", lr), clip.scale))]
        for b in clip.buffers:
            row.append((f"hr/{b}", visualize(b, clip.read(f, f"hr/{b}", space=DISPLAY_SPACE))))
        rows.append(row)
    save_png(path, labelled_grid(rows))
    return Path(path)


def _fit(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """``img`` resized (nearest) to h x w."""
    ys = np.minimum((np.arange(h) + 0.5) * img.shape[0] / h, img.shape[0] - 1).astype(np.int64)
    xs = np.minimum((np.arange(w) + 0.5) * img.shape[1] / w, img.shape[1] - 1).astype(np.int64)
    return img[ys][:, xs]


def dataset_sheet(root: str | Path, path: str | Path, width: int = 256, splits=None) -> tuple[Path, int]:
    """PNG contact sheet of a dataset: one row per finished clip (index order, or only ``splits``) with its first
    and last frame's HR radiance at ``width`` pixels wide, labelled with the clip id, camera kind and split.
    Returns (path, clips shown); ValueError when the dataset has no finished clip."""
    from .clip import ClipError, open_clip
    from .dataset.build import read_index
    root = Path(root)
    index = read_index(root)
    rows = []
    for c in index["clips"]:
        if splits and c.get("split") not in splits:
            continue
        try:
            clip = open_clip(root / c["path"])
        except ClipError:
            continue
        if not clip.frames:
            continue
        row = []
        for f in (clip.frames[0], clip.frames[-1]):
            img = visualize("radiance", clip.read(f, "hr/radiance", space=DISPLAY_SPACE))
            h = max(1, round(img.shape[0] * width / img.shape[1]))
            label = f"{c['id']} f{f}" if f == clip.frames[0] else f"{c.get('camera')} {c.get('split')} f{f}"
            row.append((label, _fit(img, h, width)))
        rows.append(row)
    if not rows:
        raise BlendSRError(f"{root}: no finished clip to show")
    h = max(r[0][1].shape[0] for r in rows)
    rows = [[(lab, _fit(img, h, width)) for lab, img in r] for r in rows]
    save_png(path, labelled_grid(rows))
    return Path(path), len(rows)
