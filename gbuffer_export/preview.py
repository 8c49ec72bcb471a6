"""Images a person can look at: tonemapped radiance, false-colour G-buffers and a contact sheet of a clip
(numpy, colour-science and Pillow)."""
from __future__ import annotations

from dataclasses import dataclass, field
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
    """(near, far) in scene units that ``depth_rgb`` shows as white and black: the 1st and 99th percentiles of the
    finite depths; None when no pixel is finite (all background)."""
    d = np.asarray(d, np.float64)[..., 0]
    fin = d[np.isfinite(d)]
    if not fin.size:
        return None
    near, far = np.percentile(np.maximum(fin, 1e-6), [1, 99])
    return float(near), float(far)


def depth_rgb(d: np.ndarray) -> np.ndarray:
    """Depth as grey on a log scale: white at the near end of ``depth_range``, black at the far end, in between
    log(far / depth) / log(far / near); background (not finite) black; a view at one depth white."""
    rng = depth_range(d)
    d = np.asarray(d, np.float64)[..., 0]
    if rng is None:
        return np.zeros((*d.shape, 3))
    fin = np.isfinite(d)
    near, far = rng
    if far <= near * (1 + 1e-6):  # one depth (a flat wall): white, told apart from the black background
        return np.repeat(fin[..., None].astype(np.float64), 3, axis=-1)
    logd = np.log(np.maximum(np.where(fin, d, far), 1e-6))
    v = np.clip((np.log(far) - logd) / np.log(far / near), 0, 1) * fin
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


def scalar_range(arr: np.ndarray) -> tuple[float, float] | None:
    """(black, white) of ``scalar_rgb``: min(0, minimum) and the maximum over finite pixels; None when no pixel is
    finite."""
    v = np.asarray(arr, np.float64)[..., 0]
    v = v[np.isfinite(v)]
    if not v.size:
        return None
    return min(0.0, float(v.min())), float(v.max())


def scalar_rgb(arr: np.ndarray) -> np.ndarray:
    """A one-channel buffer (roughness, metallic, specular...) as grey normalised per buffer: ``scalar_range``'s
    black end (0, or the minimum when negative) black, its maximum white; non-finite pixels black. A buffer whose
    maximum is its black end (all 0) is black."""
    rng = scalar_range(arr)
    v = np.asarray(arr, np.float64)[..., 0]
    if rng is None or rng[1] <= rng[0]:
        return np.zeros((*v.shape, 3))
    g = np.clip((np.nan_to_num(v, nan=rng[0], posinf=rng[0], neginf=rng[0]) - rng[0]) / (rng[1] - rng[0]), 0, 1)
    return np.repeat(g[..., None], 3, axis=-1)


def visualize(name: str, arr: np.ndarray) -> np.ndarray:
    """H x W x 3 display image in [0, 1] of a clip buffer (the mappings of ``describe``)."""
    if name in ("radiance", "emission"):
        return tonemap(arr)
    if name in ("albedo", "fbeta"):
        return srgb_encode(np.clip(np.nan_to_num(arr), 0, 1))
    if name == "normal":
        return normal_rgb(arr)
    if name == "depth":
        return depth_rgb(arr)
    if name in ("motion", "motion_next"):
        return motion_rgb(arr)
    if name == "flags":
        return flags_rgb(arr)
    return scalar_rgb(arr)


def _g(v: float) -> str:
    return f"{v:.3g}"


def _pct(mask: np.ndarray) -> str:
    return f"{100.0 * float(np.mean(mask)):.0f}%"


def describe(name: str, arr: np.ndarray) -> list[str]:
    """What a tile of buffer ``name`` shows, as label lines after its name: the mapping of ``visualize`` and the
    range of values it stands for (radiance and emission: as read, exposed; Y is BT.709 luminance)."""
    a = np.asarray(arr)
    if name in ("radiance", "emission"):
        from .colour_spaces import BT709_LUMA
        y = np.asarray(a[..., :3], np.float64) @ np.asarray(BT709_LUMA)
        fin = y[np.isfinite(y)]
        p1, p99 = np.percentile(fin, [1, 99]) if fin.size else (0.0, 0.0)
        bad = y.size - fin.size
        return ["Reinhard v/(1+v), then sRGB",
                f"Y p1 {_g(p1)} p99 {_g(p99)} max {_g(fin.max() if fin.size else 0.0)}"
                + (f"; {bad} px not finite" if bad else "")]
    if name in ("albedo", "fbeta"):
        fin = a[np.isfinite(a)]
        return ["sRGB of the value (0..1)", f"min {_g(fin.min())} max {_g(fin.max())}" if fin.size else "no value"]
    if name == "normal":
        bg = np.linalg.norm(a, axis=-1) == 0
        return ["RGB = (n + 1) / 2, camera space", f"x right, y up, z to viewer; bg black ({_pct(bg)})"]
    if name == "depth":
        rng = depth_range(a)
        if rng is None:
            return ["log depth", "no finite depth (all background)"]
        fin = a[np.isfinite(a)]
        return [f"log: white {_g(rng[0])} (p1) .. black {_g(rng[1])} (p99)",
                f"min {_g(fin.min())} max {_g(fin.max())}; bg {_pct(~np.isfinite(a))} black"]
    if name in ("motion", "motion_next"):
        mag = np.linalg.norm(a, axis=-1)
        return ["hue: direction, brightness: length",
                f"full at {_g(motion_scale(a))} px (p99); max {_g(float(np.nanmax(mag)))} px"]
    if name == "flags":
        from .conventions import UNTRUSTED
        f = a[..., 0].astype(np.int64)
        parts = [f"{label.split(' ')[0].replace('background', 'bg')} "
                 f"{_pct((f & (int(UNTRUSTED) if bits is None else bits)) > 0)}" for label, bits, _, _ in FLAG_COLOURS]
        return ["colours: legend below", " ".join(parts)]
    rng = scalar_range(a)
    if rng is None:
        return ["grey", "no finite value"]
    fin = a[np.isfinite(a)]
    if fin.min() == fin.max():
        return [f"grey: {_g(rng[0])} black .. {_g(rng[1])} white", f"constant {_g(fin.min())}"]
    return [f"grey: {_g(rng[0])} black .. {_g(rng[1])} white",
            f"min {_g(fin.min())} max {_g(fin.max())} mean {_g(fin.mean())}"]


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
    Image.fromarray(_u8(img)).save(tmp)
    os.replace(tmp, path)


def _u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def _fit(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """``img`` resized (nearest) to h x w."""
    ys = np.minimum((np.arange(h) + 0.5) * img.shape[0] / h, img.shape[0] - 1).astype(np.int64)
    xs = np.minimum((np.arange(w) + 0.5) * img.shape[1] / w, img.shape[1] - 1).astype(np.int64)
    return img[ys][:, xs]


def _resize(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """A display image at h x w: nearest when enlarged (pixels stay visible), box-filtered when reduced."""
    if h >= img.shape[0] and w >= img.shape[1]:
        return _fit(img, h, w)
    from PIL import Image
    return np.asarray(Image.fromarray(_u8(img)).resize((w, h), Image.Resampling.BOX)).astype(np.float64) / 255.0


# ------------------------------------------------------------------------------------------------ sheet layout
#: Layout of the sheets: grey background, gaps between tiles, text colours.
BACKGROUND, PAD = (24, 24, 24), 6
WHITE, GREY, HEADING = (255, 255, 255), (170, 170, 170), (255, 220, 0)


def _font():
    """Pillow's default font at 12 px (its bitmap font where Pillow has no FreeType)."""
    from PIL import ImageFont
    global _FONT
    if _FONT is None:
        try:
            _FONT = ImageFont.load_default(size=12)
        except (TypeError, ImportError, OSError):
            _FONT = ImageFont.load_default()
    return _FONT


_FONT = None


def line_height() -> int:
    box = _font().getbbox("Ag|")
    return int(box[3] - min(box[1], 0)) + 3


def text_width(text: str) -> int:
    return int(np.ceil(_font().getlength(text)))


def wrap(text: str, width: int) -> list[str]:
    """``text`` in lines of at most ``width`` pixels of ``_font`` (words split only when one alone is wider)."""
    out: list[str] = []
    for word in text.split(" "):
        cur = f"{out[-1]} {word}" if out else word
        if out and text_width(cur) <= width:
            out[-1] = cur
            continue
        while text_width(word) > width and len(word) > 1:
            k = len(word) - 1
            while k > 1 and text_width(word[:k]) > width:
                k -= 1
            out.append(word[:k])
            word = word[k:]
        out.append(word)
    return out or [""]


@dataclass
class Tile:
    """One picture of a sheet: its image at ``(x, y)`` under its label lines, which fill ``label_box``."""
    key: str
    frame: int | None
    lines: list[str]
    image: np.ndarray = field(repr=False)
    x: int = 0
    y: int = 0
    label_y: int = 0
    label_h: int = 0
    col_w: int = 0

    @property
    def box(self) -> tuple[int, int, int, int]:
        """(x, y, w, h) of the image on the sheet."""
        return self.x, self.y, self.image.shape[1], self.image.shape[0]

    @property
    def label_box(self) -> tuple[int, int, int, int]:
        """(x, y, w, h) of the label strip above the image (no text is drawn over an image)."""
        return self.x, self.label_y, self.col_w, self.label_h


@dataclass
class SheetLayout:
    """Where everything of a sheet goes: ``texts`` (x, y, line, colour), ``tiles``, and ``legend`` (an image) at
    ``legend_y``; ``render_sheet`` draws it."""
    width: int
    height: int = 0
    tiles: list[Tile] = field(default_factory=list)
    texts: list[tuple[int, int, str, tuple]] = field(default_factory=list)
    legend: np.ndarray | None = field(default=None, repr=False)
    legend_y: int = 0

    def tile(self, key: str, frame: int | None = None) -> Tile:
        """The tile of ``key`` (and ``frame``); KeyError when the sheet has none."""
        for t in self.tiles:
            if t.key == key and (frame is None or t.frame == frame):
                return t
        raise KeyError(f"{key} (frame {frame})")

    def heading(self, text: str, colour=WHITE) -> None:
        """Lines of ``text`` across the sheet, wrapped to its width, below what is placed so far."""
        y = self.height or PAD
        for ln in wrap(text, self.width - 2 * PAD):
            self.texts.append((PAD, y, ln, colour))
            y += line_height()
        self.height = y

    def row(self, cells: list[tuple[str, int | None, list[str], np.ndarray]], col_w: int) -> None:
        """A row of tiles (key, frame, label lines, image), ``col_w`` apart, each label wrapped to ``col_w``."""
        y = self.height or PAD
        labels = [[ln for text in lines for ln in wrap(text, col_w)] for _, _, lines, _ in cells]
        label_h = line_height() * max(len(lb) for lb in labels) + 2
        for j, ((key, frame, _, img), lb) in enumerate(zip(cells, labels)):
            self.tiles.append(Tile(key, frame, lb, img, PAD + j * (col_w + PAD), y + label_h, y, label_h, col_w))
        self.height = y + label_h + max(img.shape[0] for *_, img in cells) + PAD

    def add_legend(self, img: np.ndarray) -> None:
        self.legend_y = self.height or PAD
        self.legend = img
        self.height = self.legend_y + img.shape[0]


def render_sheet(layout: SheetLayout) -> np.ndarray:
    """The picture of ``layout``: H x W x 3 in [0, 1]."""
    from PIL import Image, ImageDraw
    canvas = Image.new("RGB", (layout.width, layout.height), BACKGROUND)
    draw = ImageDraw.Draw(canvas)
    font = _font()
    for x, y, text, colour in layout.texts:
        draw.text((x, y), text, fill=colour, font=font)
    lh = line_height()
    for t in layout.tiles:
        for k, text in enumerate(t.lines):
            draw.text((t.x, t.label_y + k * lh), text, fill=WHITE if k == 0 else GREY, font=font)
        canvas.paste(Image.fromarray(_u8(t.image)), (t.x, t.y))
    if layout.legend is not None:
        canvas.paste(Image.fromarray(_u8(layout.legend)), (0, layout.legend_y))
    return np.asarray(canvas).astype(np.float64) / 255.0


def grid_columns(n: int, max_width: int, min_col: int = 240) -> tuple[int, int]:
    """(columns, widest column) of a grid of ``n`` tiles within ``max_width`` pixels: as many columns of at least
    ``min_col`` as fit, then as few as give the same number of rows (no half-empty last row)."""
    most = max(1, min(n, (max_width - PAD) // (min_col + PAD)))
    rows = -(-n // most)
    cols = -(-n // rows)
    return cols, max(16, (max_width - PAD) // cols - PAD)


def tile_size(size: tuple[int, int], col_max: int) -> tuple[int, int]:
    """(w, h) of a tile of an image of ``size`` (W, H) in a column of ``col_max``: enlarged by the largest whole
    factor that fits when that fills at least 80% of the column, else scaled to the column's width, keeping the
    aspect."""
    w, h = size
    f = col_max // w
    if f >= 1 and w * f >= 0.8 * col_max:
        return w * f, h * f
    return col_max, max(1, round(h * col_max / w))


def _legend_text(x: int, lines: list[str]):
    """A painter of ``lines`` from ``x``: (canvas, draw, y) -> None."""
    def paint(canvas, draw, y):
        for k, ln in enumerate(lines):
            draw.text((x, y + k * line_height()), ln, fill=WHITE, font=_font())
    return paint


def _legend_flags(width: int):
    """(height, painter) of the flag swatches, wrapped to ``width``."""
    lh, x0 = line_height(), PAD + text_width("flags:") + 8
    rows, cur, x = [], [], x0
    for name, _, colour, _ in FLAG_COLOURS:
        wd = 16 + text_width(name) + 12
        if cur and x + wd > width - PAD:
            rows.append(cur)
            cur, x = [], x0
        cur.append((x, name, tuple(int(255 * c) for c in colour)))
        x += wd
    rows.append(cur)
    note = wrap("(moving and emissive add their colour to the others)", width - 2 * PAD)

    def paint(canvas, draw, y):
        draw.text((PAD, y), "flags:", fill=WHITE, font=_font())
        for i, row in enumerate(rows):
            for x, name, colour in row:
                yy = y + i * lh
                draw.rectangle([x, yy + 2, x + 11, yy + 13], fill=colour, outline=(200, 200, 200))
                draw.text((x + 16, yy), name, fill=WHITE, font=_font())
        for k, ln in enumerate(note):
            draw.text((PAD, y + (len(rows) + k) * lh), ln, fill=GREY, font=_font())
    return (len(rows) + len(note)) * lh, paint


def _legend_motion(width: int):
    """(height, painter) of the motion colour wheel: each pixel's offset from the centre as a motion vector."""
    from PIL import Image
    r = 14
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1].astype(np.float64)
    wheel = motion_rgb(np.stack([xx, yy], axis=-1) / r, max_px=1.0) * (np.hypot(xx, yy) <= r)[..., None]
    lines = wrap("motion: hue = direction of p_prev - p (as on this wheel, image axes, y down), brightness = "
                 "length, full at the px its tile names", width - 2 * PAD - 2 * r - 8)
    text = _legend_text(PAD + 2 * r + 8, lines)

    def paint(canvas, draw, y):
        canvas.paste(Image.fromarray(_u8(wheel)), (PAD, y))
        text(canvas, draw, y)
    return max(2 * r + 1, len(lines) * line_height()), paint


def _legend_depth(width: int):
    """(height, painter) of the depth ramp."""
    from PIL import Image
    ramp = np.repeat(np.linspace(1.0, 0.0, 60)[None, :, None], 12, axis=0).repeat(3, axis=-1)
    lines = wrap("depth: log scale, near (white) to far (black) at the 1st and 99th percentile its tile names "
                 "(scene units); background black", width - 2 * PAD - 68)
    text = _legend_text(PAD + 68, lines)

    def paint(canvas, draw, y):
        canvas.paste(Image.fromarray(_u8(ramp)), (PAD, y + 2))
        text(canvas, draw, y)
    return max(14, len(lines) * line_height()), paint


def legend_strip(width: int, buffers=("depth", "motion", "flags")) -> np.ndarray:
    """The contact sheet's legend, ``width`` pixels wide, for the ``buffers`` shown: the flag colours, the motion
    colour wheel, the depth ramp (log scale) and the grey of the material buffers; wrapped to the width."""
    from PIL import Image, ImageDraw
    items = []  # (height, painter)
    if "flags" in buffers:
        items.append(_legend_flags(width))
    if "motion" in buffers or "motion_next" in buffers:
        items.append(_legend_motion(width))
    if "depth" in buffers:
        items.append(_legend_depth(width))
    if any(b in ("roughness", "metallic", "specular") for b in buffers):
        lines = wrap("roughness, metallic, specular: grey normalised per buffer, the values at black and white on "
                     "its tile", width - 2 * PAD)
        items.append((len(lines) * line_height(), _legend_text(PAD, lines)))
    canvas = Image.new("RGB", (width, PAD + sum(h + PAD for h, _ in items)), BACKGROUND)
    draw = ImageDraw.Draw(canvas)
    y = PAD
    for h, paint in items:
        paint(canvas, draw, y)
        y += h + PAD
    return np.asarray(canvas).astype(np.float64) / 255.0


def contact_sheet_layout(clip, frames: list[int] | None = None, max_frames: int = 3, legend: bool = True, *,
                         max_width: int = 1600) -> SheetLayout:
    """The layout of ``contact_sheet``: a title naming the clip, its sizes and exposure; per frame a heading and
    a grid of tiles (LR radiance enlarged by nearest neighbours, HR radiance, every other HR buffer of the clip),
    each under its name, mapping and value range (``describe``); the legend below. At most ``max_width`` wide."""
    frames = frames or clip.frames[:: max(1, len(clip.frames) // max_frames)][:max_frames]
    buffers = ["radiance", *(b for b in clip.buffers if b != "radiance")]
    cols, col_max = grid_columns(1 + len(buffers), max_width)
    tw, th = tile_size(clip.sizes["hr"], col_max)
    col_w = max(tw, min(col_max, 240))
    layout = SheetLayout(width=PAD + cols * (col_w + PAD))
    (w, h), (lw, lh) = clip.sizes["hr"], clip.sizes["lr"]
    block = clip.manifest.get("exposure") or {}
    layout.heading(f"{clip.path.name}: HR {w}x{h}, LR {lw}x{lh} (scale {clip.scale:g}); frames "
                   f"{', '.join(map(str, frames))} of {len(clip.frames)}; exposure x{clip.exposure:.4g} "
                   f"({block.get('mode', 'none')}); colours in Linear Rec.709 shown as sRGB; tiles {tw}x{th}")
    for f in frames:
        layout.heading(f"frame {f}", HEADING)
        lr = clip.read(f, "lr/radiance", space=DISPLAY_SPACE, exposed=True)
        cells = [("lr/radiance", f, [f"lr/radiance {lw}x{lh}, nearest", *describe("radiance", lr)],
                  _fit(visualize("radiance", lr), th, tw))]
        for b in buffers:
            arr = clip.read(f, f"hr/{b}", space=DISPLAY_SPACE, exposed=True)
            cells.append((f"hr/{b}", f, [f"hr/{b}", *describe(b, arr)], _resize(visualize(b, arr), th, tw)))
        for i in range(0, len(cells), cols):
            layout.row(cells[i:i + cols], col_w)
    if legend:
        layout.add_legend(legend_strip(layout.width, buffers))
    return layout


def contact_sheet(clip, path: str | Path, frames: list[int] | None = None, max_frames: int = 3,
                  legend: bool = True, *, max_width: int = 1600) -> Path:
    """PNG contact sheet of a clip (``contact_sheet_layout``): per frame a grid of LR radiance (nearest-upscaled),
    HR radiance and every HR G-buffer the clip holds, each tile labelled with its buffer, mapping and value range;
    radiance and emission exposed (the clip's exposure), colours converted from the clip's working space to
    Linear Rec.709 (sRGB primaries); depth log-scaled, motion as a colour wheel, material buffers normalised.
    ``legend`` adds the flag colours, the motion wheel and the depth ramp below. At most ``max_width`` wide."""
    save_png(path, render_sheet(contact_sheet_layout(clip, frames, max_frames, legend, max_width=max_width)))
    return Path(path)


def dataset_sheet_layout(root: str | Path, width: int = 256, splits=None, *, max_width: int = 1600) -> SheetLayout:
    """The layout of ``dataset_sheet``: every finished clip (index order, or only ``splits``) as two tiles, its
    first and last frame's HR radiance (exposed, tonemapped) at ``width`` pixels wide, labelled with the clip id,
    camera kind, split, frame and exposure; as many clips side by side as fit ``max_width``. BlendSRError when the
    dataset has no finished clip; a clip path that leaves the dataset is refused (``dataset.build.clip_dir``)."""
    from .clip import ClipError, UnsafePathError, open_clip
    from .dataset.build import clip_dir, read_index
    from .validate.gate import require_valid
    root = Path(root)
    index = read_index(root)
    dirs = [(c, clip_dir(root, c)) for c in index["clips"] if not splits or c.get("split") in splits]
    cells = []
    for c, folder in dirs:
        try:
            clip = open_clip(folder)
        except UnsafePathError:
            raise
        except ClipError:
            continue
        if not clip.frames:
            continue
        if clip.complete:  # a finished clip is shown only if it passes validation (a clip still rendering is shown)
            require_valid(folder)
        for f, which in ((clip.frames[0], "first"), (clip.frames[-1], "last")):
            img = visualize("radiance", clip.read(f, "hr/radiance", space=DISPLAY_SPACE, exposed=True))
            h = max(1, round(img.shape[0] * width / img.shape[1]))
            lines = [str(c["id"]), f"{c.get('camera')}, {c.get('split')}; {which} frame {f}",
                     f"HR {img.shape[1]}x{img.shape[0]}, exposure x{clip.exposure:.3g}"]
            cells.append((str(c["id"]), f, lines, _resize(img, h, width)))
    if not cells:
        raise BlendSRError(f"{root}: no finished clip to show")
    per_row = 2 * max(1, (max_width - PAD) // (2 * (width + PAD)))
    layout = SheetLayout(width=PAD + min(per_row, len(cells)) * (width + PAD))
    layout.heading(f"{root.name}: {len(cells) // 2} finished clips{' in ' + ', '.join(splits) if splits else ''}; "
                   "HR radiance of the first and last frame, exposed, Reinhard v/(1+v) then sRGB")
    for i in range(0, len(cells), per_row):
        layout.row(cells[i:i + per_row], width)
    return layout


def dataset_sheet(root: str | Path, path: str | Path, width: int = 256, splits=None, *,
                  max_width: int = 1600) -> tuple[Path, int]:
    """PNG contact sheet of a dataset (``dataset_sheet_layout``). Returns (path, clips shown)."""
    layout = dataset_sheet_layout(root, width, splits, max_width=max_width)
    save_png(path, render_sheet(layout))
    return Path(path), len(layout.tiles) // 2


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
