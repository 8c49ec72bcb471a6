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


def depth_range(d: np.ndarray) -> tuple[float, float] | None:
    """(near, far) in scene units that ``depth_rgb`` shows as white and black: the 99th and 1st percentiles of
    inverse depth over finite pixels; None when no pixel is finite (all background)."""
    d = d[..., 0]
    fin = np.isfinite(d)
    if not fin.any():
        return None
    inv = 1.0 / np.maximum(d[fin], 1e-6)
    lo, hi = np.percentile(inv, [1, 99])
    return 1.0 / max(hi, 1e-9), 1.0 / max(lo, 1e-9)


def depth_rgb(d: np.ndarray) -> np.ndarray:
    """Inverse depth as grey: white at the near end of ``depth_range``, black at the far end and on background."""
    rng = depth_range(d)
    d = d[..., 0]
    if rng is None:
        return np.zeros((*d.shape, 3))
    fin = np.isfinite(d)
    inv = np.where(fin, 1.0 / np.maximum(d, 1e-6), 0.0)
    lo, hi = 1.0 / rng[1], 1.0 / rng[0]
    v = np.clip((inv - lo) / max(hi - lo, 1e-9), 0, 1) * fin
    return np.repeat(v[..., None], 3, axis=-1)


def motion_scale(m: np.ndarray) -> float:
    """Motion length in pixels that ``motion_rgb`` shows at full brightness: the 99th percentile."""
    return max(float(np.percentile(np.linalg.norm(m, axis=-1), 99)), 1e-6)


def motion_rgb(m: np.ndarray, max_px: float | None = None) -> np.ndarray:
    """Direction as hue, magnitude as brightness (normalised by ``max_px`` or the 99th percentile)."""
    mag = np.linalg.norm(m, axis=-1)
    scale = max_px or motion_scale(m)
    ang = np.arctan2(m[..., 1], m[..., 0])
    hue = (ang / (2 * np.pi)) % 1.0
    v = np.clip(mag / scale, 0, 1)
    k = (np.array([5.0, 3.0, 1.0]) + hue[..., None] * 6) % 6
    rgb = 1 - np.clip(np.minimum(k, 4 - k), 0, 1)
    return rgb * v[..., None]


#: The colours of ``flags_rgb`` (also its legend): name, bits, colour; the first two are set, the others added.
FLAG_COLOURS = (
    ("background", int(Flag.BACKGROUND), (0.1, 0.1, 0.3), "set"),
    ("untrusted (demodulation)", None, (0.9, 0.3, 0.1), "set"),
    ("moving", int(Flag.MOVING), (0.0, 0.6, 0.0), "add"),
    ("emissive", int(Flag.EMISSIVE), (0.6, 0.6, 0.0), "add"),
)


def flags_rgb(f: np.ndarray) -> np.ndarray:
    from .conventions import UNTRUSTED
    f = f[..., 0].astype(np.int64)
    out = np.zeros((*f.shape, 3))
    for _, bits, colour, how in FLAG_COLOURS:
        sel = (f & (int(UNTRUSTED) if bits is None else bits)) > 0
        if how == "set":
            out[sel] = colour
        else:
            out[sel] += colour
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
    if name in ("motion", "motion_next"):
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


def tile_label(name: str, arr: np.ndarray) -> str:
    """A tile's label with the range its false colours stand for (depth: near-far, motion: full-brightness px)."""
    if name.endswith("/depth"):
        rng = depth_range(arr)
        return f"{name} {rng[0]:.3g}-{rng[1]:.3g}" if rng else f"{name} (none)"
    if name.endswith(("/motion", "/motion_next")):
        return f"{name} <={motion_scale(arr):.3g}px"
    return name


def legend_strip(width: int) -> np.ndarray:
    """The contact sheet's legend, ``width`` pixels wide: flag colours, the motion colour wheel, the depth ramp."""
    from PIL import Image, ImageDraw
    h = 46
    canvas = Image.new("RGB", (width, h), (24, 24, 24))
    draw = ImageDraw.Draw(canvas)
    x = 4
    draw.text((x, 2), "flags:", fill=(255, 255, 255))
    x += 40
    for name, _, colour, _ in FLAG_COLOURS:
        draw.rectangle([x, 3, x + 10, 13], fill=tuple(int(255 * c) for c in colour), outline=(200, 200, 200))
        draw.text((x + 14, 2), name, fill=(255, 255, 255))
        x += 14 + 6 * len(name) + 10
    draw.text((x, 2), "(moving and emissive add to the others)", fill=(170, 170, 170))
    r = 13  # motion colour wheel: each pixel's offset from the centre as a motion vector (image axes, +y down)
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1].astype(np.float64)
    wheel = motion_rgb(np.stack([xx, yy], axis=-1) / r, max_px=1.0) * (np.hypot(xx, yy) <= r)[..., None]
    canvas.paste(Image.fromarray((wheel * 255 + 0.5).astype(np.uint8)), (4, 18))
    draw.text((4 + 2 * r + 6, 18), "motion: hue = direction (as on this wheel), brightness = length, full at",
              fill=(255, 255, 255))
    draw.text((4 + 2 * r + 6, 30), "the px in the tile's label", fill=(255, 255, 255))
    x0 = 4 + 2 * r + 6 + 6 * 74
    ramp = np.repeat(np.linspace(1.0, 0.0, 60)[None, :, None], 10, axis=0).repeat(3, axis=-1)
    if x0 + 70 < width:
        canvas.paste(Image.fromarray((ramp * 255 + 0.5).astype(np.uint8)), (x0, 21))
        draw.text((x0 + 66, 18), "depth: near ... far (scene units in the tile's label;", fill=(255, 255, 255))
        draw.text((x0 + 66, 30), "1/depth percentiles 99, 1; background black)", fill=(255, 255, 255))
    return np.asarray(canvas).astype(np.float64) / 255.0


def contact_sheet(clip, path: str | Path, frames: list[int] | None = None, max_frames: int = 3,
                  legend: bool = True) -> Path:
    """PNG contact sheet of a clip: per frame one row with LR radiance (nearest-upscaled), HR radiance and every HR
    G-buffer the clip holds; radiance and emission exposed (the clip's exposure), colours converted from the clip's
    working space to Linear Rec.709 (sRGB primaries).
    Depth and motion tiles name the range their grey / colours stand for; ``legend`` adds a strip below with the
    flag colours, the motion colour wheel and the depth ramp."""
    frames = frames or clip.frames[:: max(1, len(clip.frames) // max_frames)][:max_frames]
    rows = []
    for f in frames:
        lr = clip.read(f, "lr/radiance", space=DISPLAY_SPACE, exposed=True)
        row = [(f"f{f} lr/radiance", upscale_nearest(visualize("radiance", lr), clip.scale))]
        for b in clip.buffers:
            arr = clip.read(f, f"hr/{b}", space=DISPLAY_SPACE, exposed=True)
            row.append((tile_label(f"hr/{b}", arr), visualize(b, arr)))
        rows.append(row)
    grid = labelled_grid(rows)
    if legend:
        grid = np.concatenate([grid, legend_strip(grid.shape[1])], axis=0)
    save_png(path, grid)
    return Path(path)


def _fit(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """``img`` resized (nearest) to h x w."""
    ys = np.minimum((np.arange(h) + 0.5) * img.shape[0] / h, img.shape[0] - 1).astype(np.int64)
    xs = np.minimum((np.arange(w) + 0.5) * img.shape[1] / w, img.shape[1] - 1).astype(np.int64)
    return img[ys][:, xs]


def dataset_sheet(root: str | Path, path: str | Path, width: int = 256, splits=None) -> tuple[Path, int]:
    """PNG contact sheet of a dataset: one row per finished clip (index order, or only ``splits``) with its first
    and last frame's HR radiance (exposed) at ``width`` pixels wide, labelled with the clip id, camera kind and split.
    Returns (path, clips shown); BlendSRError when the dataset has no finished clip. Every clip folder comes
    from the index through the one path rule (``dataset.build.clip_dir``): a path that leaves the dataset is refused
    with one line before anything is drawn."""
    from .clip import ClipError, UnsafePathError, open_clip
    from .dataset.build import clip_dir, read_index
    root = Path(root)
    index = read_index(root)
    dirs = [(c, clip_dir(root, c)) for c in index["clips"] if not splits or c.get("split") in splits]
    rows = []
    for c, folder in dirs:
        try:
            clip = open_clip(folder)
        except UnsafePathError:
            raise
        except ClipError:
            continue
        if not clip.frames:
            continue
        row = []
        for f in (clip.frames[0], clip.frames[-1]):
            img = visualize("radiance", clip.read(f, "hr/radiance", space=DISPLAY_SPACE, exposed=True))
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


def _fit_lines(lines: list[str], width: int) -> list[str]:
    """Wrap ``lines`` to ``width`` pixels of Pillow's default font (6 px per character)."""
    import textwrap
    out = []
    for ln in lines:
        out += textwrap.wrap(ln, max(8, (width - 4) // 6)) or [""]
    return out


def comparison_sheet(panels: list[tuple[list[str], np.ndarray]], crop: tuple[int, int, int, int] | None = None,
                     zoom: int = 2, notes: list[str] = (), max_panel: int = 480) -> np.ndarray:
    """Side-by-side comparison: the whole frames (scaled to at most ``max_panel`` wide), each under its title lines
    in a strip of its own (never clipped), then the same crop of every panel magnified ``zoom`` times without
    interpolation (pixels at full resolution or larger), the crop outlined on the frames, then ``notes`` lines.

    ``panels``: (title lines, H x W x 3 display image in [0, 1]) of equal size. ``crop``: (x, y, w, h) in pixels
    of the images; None: the window where the panels differ most (``most_different_window``)."""
    from PIL import Image, ImageDraw
    h, w = panels[0][1].shape[:2]
    pw = min(w, max_panel)
    ph = max(1, round(h * pw / w))
    if crop is None:
        crop = most_different_window([img for _, img in panels], (max(1, pw // zoom), max(1, ph // zoom)))
    cx, cy, cw, ch = crop
    pad, line = 6, 12
    titles = [_fit_lines(t, pw) for t, _ in panels]
    th = line * max(len(t) for t in titles) + 4
    note_lines = _fit_lines(list(notes), len(panels) * (pw + pad) - pad)
    crop_h = ch * zoom
    width = len(panels) * (pw + pad) + pad
    height = pad + th + ph + pad + line + crop_h + pad + line * len(note_lines) + (pad if note_lines else 0)
    canvas = Image.new("RGB", (width, height), (24, 24, 24))
    draw = ImageDraw.Draw(canvas)
    sx, sy = pw / w, ph / h
    for i, ((_, img), t) in enumerate(zip(panels, titles)):
        x = pad + i * (pw + pad)
        for k, text in enumerate(t):
            draw.text((x + 2, pad + k * line), text, fill=(255, 255, 255))
        full = Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
        if (pw, ph) != (w, h):
            full = full.resize((pw, ph), Image.Resampling.BOX)
        canvas.paste(full, (x, pad + th))
        draw.rectangle([x + int(cx * sx), pad + th + int(cy * sy), x + int((cx + cw) * sx) - 1,
                        pad + th + int((cy + ch) * sy) - 1], outline=(255, 220, 0))
        part = img[cy:cy + ch, cx:cx + cw]
        part = np.repeat(np.repeat(part, zoom, axis=0), zoom, axis=1)
        canvas.paste(Image.fromarray((np.clip(part, 0, 1) * 255 + 0.5).astype(np.uint8)),
                     (x, pad + th + ph + pad + line))
    draw.text((pad + 2, pad + th + ph + pad), f"crop x{cx} y{cy} {cw}x{ch} px, each pixel drawn {zoom}x{zoom}"
              if zoom > 1 else f"crop x{cx} y{cy} {cw}x{ch} px at full resolution", fill=(255, 220, 0))
    y = pad + th + ph + pad + line + crop_h + pad
    for k, text in enumerate(note_lines):
        draw.text((pad + 2, y + k * line), text, fill=(200, 200, 200))
    return np.asarray(canvas).astype(np.float64) / 255.0


def most_different_window(images: list[np.ndarray], size: tuple[int, int]) -> tuple[int, int, int, int]:
    """(x, y, w, h) of the ``size`` window (on a grid of steps of a quarter window) where ``images`` differ most from
    the last one (the reference: the sum of absolute differences over the others)."""
    ref = images[-1]
    h, w = ref.shape[:2]
    cw, ch = min(size[0], w), min(size[1], h)
    err = sum(np.abs(np.asarray(im, np.float64) - ref).sum(axis=-1) for im in images[:-1])
    integ = np.pad(np.cumsum(np.cumsum(err, 0), 1), ((1, 0), (1, 0)))
    best, at = -1.0, (0, 0)
    for y in range(0, h - ch + 1, max(1, ch // 4)):
        for x in range(0, w - cw + 1, max(1, cw // 4)):
            v = integ[y + ch, x + cw] - integ[y, x + cw] - integ[y + ch, x] + integ[y, x]
            if v > best:
                best, at = v, (x, y)
    return at[0], at[1], cw, ch
