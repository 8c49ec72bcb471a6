"""The one place where BlendSR's conventions live: buffers, channels, axes, signs, units.

Everything here is pure numpy (no bpy, no torch). ``docs/clip-format.md`` describes the same
conventions in prose; tests check these functions against independent computations.

Image coordinates
    x to the right, y down, in pixels of the level. Pixel (row i, column j) covers
    [j, j+1) x [i, i+1); its centre is at (j + 0.5, i + 0.5).

Camera space (Blender's camera convention)
    +X right, +Y up, the camera looks along -Z. ``world_from_camera`` is the 4x4 matrix that maps
    camera-space homogeneous points to world space (Blender's ``camera.matrix_world``, without scale).

Pinhole intrinsics (fx, fy, cx, cy), pixels of the level, un-jittered
    A camera-space point (X, Y, Z) with Z < 0 lands at x = cx + fx * X / (-Z), y = cy - fy * Y / (-Z).

Depth
    View-space distance along the viewing axis: depth = -Z > 0, in scene units; +inf on background.

Motion
    Two channels (X, Y) in pixels of the level, image coordinates. For pixel centre p of frame t,
    ``p + motion`` is where the same surface point was in frame t-1 (backward vector, jitter excluded).
    Background pixels carry the motion caused by the camera's rotation (points at infinity).

Forward motion (``motion_next``)
    The same units, axes and jitter rule, pointing to frame t+1: ``p + motion_next`` is where the surface seen at
    p will be in frame t+1. On a clip's last frame it points to frame t+1 as Blender evaluates the scene there
    (past the last key, animation holds its value), so consumers pair it only with an existing frame t+1.

Jitter (dx, dy)
    Pixels of the level, image coordinates. The radiance sample of pixel centre p was taken at
    image position ``p + (dx, dy)`` of the un-jittered camera described by the intrinsics.

Exposure
    Radiance and emission are stored physical (as rendered); the manifest's ``exposure`` is one multiplier that
    every reader applies (``expose``, ``exposure_of``; absent: 1). Auto exposure meters the HR frames
    (``luminance_stats``, ``metered_exposure``).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from enum import IntFlag
from fractions import Fraction

import numpy as np
from .errors import BlendSRError

SCHEMA = "blendsr.clip"
SCHEMA_VERSION = 2  # 2: several LR levels (``levels[...]["scale"]``, ``lr_x<s>``); version 1 clips are still read
LEVELS = ("hr", "lr")  # the levels every clip has; a clip may add LR levels named by ``level_name``
_EXTRA_LEVEL = re.compile(r"^lr_x([0-9]+(?:\.[0-9]+)?)$")


@dataclass(frozen=True)
class BufferSpec:
    """A semantic buffer: its EXR channel names, whether it is stored as float32 or uint32, and its meaning."""

    name: str
    channels: tuple[str, ...]
    dtype: str  # "float32" or "uint32"
    meaning: str


BUFFERS: dict[str, BufferSpec] = {
    spec.name: spec
    for spec in (
        BufferSpec("radiance", ("R", "G", "B"), "float32",
                   "linear scene-referred RGB (scene_linear primaries of the manifest); hr: ground truth"),
        BufferSpec("albedo", ("R", "G", "B"), "float32", "Principled base colour, linear"),
        BufferSpec("normal", ("X", "Y", "Z"), "float32",
                   "unit shading normal in camera space (+X right, +Y up, +Z towards the viewer); 0 on background"),
        BufferSpec("depth", ("Z",), "float32", "view-space depth -Z > 0 in scene units; +inf on background"),
        BufferSpec("roughness", ("Y",), "float32", "Principled roughness in [0, 1] (perceptual, alpha = r^2)"),
        BufferSpec("metallic", ("Y",), "float32", "Principled metallic in [0, 1]"),
        BufferSpec("specular", ("Y",), "float32",
                   "dielectric F0 = ((ior-1)/(ior+1))^2 * 2 * specular_ior_level, clamped to [0, 1]"),
        BufferSpec("emission", ("R", "G", "B"), "float32",
                   "emitted radiance seen directly (a surface's emission; on background the environment), so that "
                   "radiance = fbeta * L_D + emission"),
        BufferSpec("fbeta", ("R", "G", "B"), "float32",
                   "pre-integrated BRDF (directional albedo) per pixel; 1 on background"),
        BufferSpec("motion", ("X", "Y"), "float32",
                   "backward motion in pixels of the level, image coords: p_prev = p + motion"),
        BufferSpec("motion_next", ("X", "Y"), "float32",
                   "forward motion in pixels of the level, image coords: p_next = p + motion_next"),
        BufferSpec("flags", ("F",), "uint32", "per-pixel bit mask, see Flag"),
    )
}

#: Buffers the default model (FuseSR) consumes; what ``blendsr render`` writes unless told otherwise. Material
#: parameters (roughness, metallic, specular) are rendered only when asked for or when a table fbeta needs them;
#: ``motion_next`` (free to render: the Vector pass holds it) only when asked for (it costs disk).
DEFAULT_BUFFERS: tuple[str, ...] = (
    "radiance", "albedo", "normal", "depth", "emission", "fbeta", "motion", "flags",
)
ALL_BUFFERS: tuple[str, ...] = tuple(BUFFERS)


class Flag(IntFlag):
    """Bits of the ``flags`` buffer. Any bit in ``UNTRUSTED`` means demodulation cannot be trusted there."""

    BACKGROUND = 1 << 0       # no surface: world/HDRI seen directly
    ANISOTROPIC = 1 << 1      # Principled anisotropy > 0
    SPECULAR_TINT = 1 << 2    # non-white specular tint
    SUBSURFACE = 1 << 3       # subsurface weight > 0
    ALPHA = 1 << 4            # alpha < 1 (or driven by a texture)
    VOLUME = 1 << 5           # the material has a volume shader
    NON_PRINCIPLED = 1 << 6   # surface shader is not a single Principled BSDF
    NO_MATERIAL = 1 << 7      # object without material (Cycles' default grey)
    EMISSIVE = 1 << 8         # emission > 0 (informative; demodulation subtracts it)
    MOVING = 1 << 9           # the object is animated (informative; not static for reprojection checks)
    SINGLE_SCATTER_GGX = 1 << 10  # Principled with a non-multiscatter distribution: loses energy on rough metals
    TRANSMISSION = 1 << 11    # transmission weight > 0 (informative; see FBETA_UNMODELED)
    COAT = 1 << 12            # coat weight > 0 (informative)
    SHEEN = 1 << 13           # sheen weight > 0 (informative)
    THIN_FILM = 1 << 14       # thin-film thickness > 0 (informative)
    FBETA_UNMODELED = 1 << 15  # the clip's fbeta source cannot represent this material (FBETA_UNMODELED_BY)


UNTRUSTED = (Flag.ANISOTROPIC | Flag.SPECULAR_TINT | Flag.SUBSURFACE | Flag.ALPHA | Flag.VOLUME
             | Flag.NON_PRINCIPLED | Flag.NO_MATERIAL | Flag.SINGLE_SCATTER_GGX | Flag.FBETA_UNMODELED)

#: Per fbeta source, the material features it cannot represent: a pixel with any of them also gets
#: FBETA_UNMODELED (untrusted). Cycles' colour passes carry transmission, coat, sheen and thin film (measured on the
#: white furnace, docs/brdf.md); the split-sum tables and the Principled model describe only the base dielectric /
#: metal layers. Features untrusted for every source (anisotropy, specular tint, alpha, ...) are in UNTRUSTED already.
FBETA_UNMODELED_BY: dict[str, Flag] = {
    "cycles": Flag(0),
    "lut": Flag.TRANSMISSION | Flag.COAT | Flag.SHEEN | Flag.THIN_FILM,
    "lut-paper": Flag.TRANSMISSION | Flag.COAT | Flag.SHEEN | Flag.THIN_FILM,
    "model": Flag.TRANSMISSION | Flag.COAT | Flag.SHEEN | Flag.THIN_FILM,
}


def material_flags_for_source(flags: int, fbeta_source: str) -> int:
    """A material's flag bits with FBETA_UNMODELED added when ``fbeta_source`` cannot represent it."""
    if int(flags) & int(FBETA_UNMODELED_BY[fbeta_source]):
        return int(flags) | int(Flag.FBETA_UNMODELED)
    return int(flags)


#: The G-buffers a table F_beta source (every source but ``cycles``) computes F_beta from (``flags``: background and
#: material flags). Whenever such an ``fbeta`` is requested they are rendered, written or not: ``computed_buffers``.
TABLE_FBETA_INPUTS = ("albedo", "normal", "roughness", "metallic", "specular", "flags")


def computed_buffers(buffers, fbeta_source: str) -> tuple[str, ...]:
    """The buffers a render computes for the requested ``buffers``: those, plus ``TABLE_FBETA_INPUTS`` when
    ``fbeta`` comes from a table source (the one statement of that rule)."""
    out = tuple(buffers)
    if "fbeta" in out and fbeta_source != "cycles":
        out += tuple(b for b in TABLE_FBETA_INPUTS if b not in out)
    return out


def buffer_spec(name: str) -> BufferSpec:
    """Return the spec of a buffer name; ValueError naming the valid ones otherwise."""
    try:
        return BUFFERS[name]
    except KeyError:
        raise BlendSRError(f"unknown buffer {name!r}; known buffers: {', '.join(BUFFERS)}") from None


def parse_buffer_list(text: str) -> tuple[str, ...]:
    """Parse ``--buffers``: 'default', 'all' or a comma-separated list of names (radiance always included)."""
    text = text.strip()
    if text in ("", "default"):
        return DEFAULT_BUFFERS
    if text == "all":
        return ALL_BUFFERS
    names = [t.strip() for t in text.split(",") if t.strip()]
    for n in names:
        buffer_spec(n)
    ordered = [n for n in ALL_BUFFERS if n in names or n == "radiance"]
    return tuple(ordered)


# ----------------------------------------------------------------------------------------------
# Exposure
# ----------------------------------------------------------------------------------------------
# Radiance is stored physical: ``radiance`` and ``emission`` hold what Cycles rendered, in the scene's own light
# units. A clip's exposure is one multiplier in its manifest (``exposure.value``; a manifest without ``exposure``
# reads as 1, as every clip rendered before the key), and every reader of radiance multiplies by it through
# ``expose`` (``Clip.read(..., exposed=True)``): training, evaluation, previews, upscaling, the add-on and the
# exporters. ``validate`` checks the exposed frames. F_beta and albedo are ratios and stay as they are, so
# L_D = (radiance - emission) / fbeta scales with the exposure like the radiance.

#: The buffers in units of radiance, which the exposure multiplies.
EXPOSED_BUFFERS = ("radiance", "emission")
#: Auto exposure aims the clip's log-average luminance at this value (middle grey), as a game camera does.
EXPOSURE_KEY = 0.18
#: Auto exposure keeps exposure 1 for a clip whose log-average luminance already lies in this range (well exposed;
#: measured: clips of the built-in scene 0.15-0.37, HDRI-lit glTF assets 0.20 and 0.48, the town level under the
#: added sun and sky 0.84 at a sun elevation of 38 degrees), so existing data keep their values; a clip outside it
#: is brought to EXPOSURE_KEY. Its edges leave 1.3 stops (0.05 / 0.02) and 0.4 stops (2.0 / 1.5) for frames darker
#: or brighter than their clip before ``validate`` calls them practically black or blown out.
AUTO_EXPOSURE_BAND = (0.05, 1.5)
#: The multipliers an exposure may take, auto or set (2^-16 .. 2^20, 36 stops): auto exposure clamps to them, so a
#: clip darker than 0.18 / 2^20 (about 2e-7: practically unlit) stays dark and ``validate`` refuses it.
EXPOSURE_LIMITS = (2.0 ** -16, 2.0 ** 20)


def parse_exposure(value) -> str | float:
    """A render's ``exposure`` setting: ``"auto"``, or a multiplier of the rendered radiance (a number or its text,
    ``2``, ``"0.5"``) within ``EXPOSURE_LIMITS``. BlendSRError saying what is wrong otherwise."""
    if isinstance(value, str):
        if value.strip().lower() == "auto":
            return "auto"
        try:
            value = float(value)
        except ValueError:
            raise BlendSRError("expected 'auto' or a positive multiplier such as 1 or 0.5") from None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise BlendSRError("expected 'auto' or a positive multiplier such as 1 or 0.5")
    lo, hi = EXPOSURE_LIMITS
    if not (math.isfinite(value) and lo <= value <= hi):
        raise BlendSRError(f"a multiplier must lie in [2^{math.log2(lo):g}, 2^{math.log2(hi):g}]")
    return float(value)


def exposure_header(value) -> dict:
    """The manifest header's ``exposure`` for a render's setting: {} for 1 (a clip without the key reads as 1, so
    a clip rendered at exposure 1 keeps the identity it had before the key), ``{"exposure": {"mode": "fixed",
    "value", "ev"}}`` for a set multiplier, ``{"exposure": {"mode": "auto", "key", "band", "limits"}}`` for auto
    (its ``value`` is metered from the frames as they finish: ``metered_exposure``)."""
    value = parse_exposure(value)
    if value == "auto":
        return {"exposure": {"mode": "auto", "key": EXPOSURE_KEY, "band": list(AUTO_EXPOSURE_BAND),
                             "limits": list(EXPOSURE_LIMITS)}}
    if value == 1.0:
        return {}
    return {"exposure": {"mode": "fixed", "value": value, "ev": math.log2(value)}}


def luminance(rgb: np.ndarray, scene_linear: str) -> np.ndarray:
    """Luminance Y (H x W float64) of linear RGB (H x W x 3) in the working space ``scene_linear``; BT.709's weights
    for a space blendsr does not convert (``validate`` warns about such a clip: ``manifest-colour-space``)."""
    from .colour_spaces import BT709_LUMA, luminance_weights
    try:
        w = luminance_weights(scene_linear)
    except BlendSRError:
        w = BT709_LUMA
    return np.asarray(rgb, np.float64)[..., :3] @ np.asarray(w, np.float64)


def luminance_stats(radiance: np.ndarray, scene_linear: str) -> dict:
    """The metering of one HR frame: ``log_mean``, the mean natural log of the luminance over its lit pixels
    (luminance > 0 and finite; None when none is), ``lit_pixels`` and ``pixels``. Luminance is Y of the clip's
    working space ``scene_linear`` (BT.709's weights for a space blendsr does not convert). Pixels without light
    (exact 0: a black void) are left out of the metering, as a camera's meter ignores them; ``validate`` counts them
    (``dark-frame``)."""
    lum = luminance(radiance, scene_linear)
    with np.errstate(invalid="ignore"):
        lit = np.isfinite(lum) & (lum > 0)
    n = int(lit.sum())
    return {"log_mean": float(np.log(lum[lit]).mean()) if n else None, "lit_pixels": n, "pixels": int(lum.size)}


def log_average_luminance(stats) -> float | None:
    """exp of the mean log luminance over the lit pixels of every frame's ``luminance_stats``; None when no frame
    has a lit pixel."""
    total, n = 0.0, 0
    for s in stats:
        if s.get("lit_pixels") and s.get("log_mean") is not None:
            total += float(s["log_mean"]) * int(s["lit_pixels"])
            n += int(s["lit_pixels"])
    return math.exp(total / n) if n else None


def auto_exposure_value(log_average: float | None) -> float:
    """The auto exposure of a clip whose log-average luminance is ``log_average``: 1 inside AUTO_EXPOSURE_BAND (and
    for a clip without any lit pixel), else EXPOSURE_KEY / log_average clamped to EXPOSURE_LIMITS."""
    lo, hi = AUTO_EXPOSURE_BAND
    if log_average is None or lo <= log_average <= hi:
        return 1.0
    return float(min(max(EXPOSURE_KEY / log_average, EXPOSURE_LIMITS[0]), EXPOSURE_LIMITS[1]))


def frame_luminance(record) -> dict | None:
    """The metering a frame record carries (``record["hr"]["luminance"]``), None when it has none or a malformed
    one (``log_mean`` a finite number or None, ``lit_pixels`` an integer >= 0)."""
    hr = record.get("hr") if isinstance(record, dict) else None
    lum = hr.get("luminance") if isinstance(hr, dict) else None
    if not isinstance(lum, dict):
        return None
    lm, n = lum.get("log_mean"), lum.get("lit_pixels")
    if not (isinstance(n, int) and not isinstance(n, bool) and n >= 0):
        return None
    if lm is not None and (isinstance(lm, bool) or not isinstance(lm, (int, float)) or not math.isfinite(lm)):
        return None
    return lum


#: The keys ``metered_exposure`` adds to an auto exposure block: they follow the finished frames, so they are no part
#: of the clip's identity (``clip.header_identity``).
METERED_KEYS = ("value", "ev", "log_average", "frames_metered")


def metered_exposure(block: dict, records: dict) -> dict:
    """A header's auto ``exposure`` block completed from the finished frames' records (``frame_luminance``):
    ``value`` (the multiplier), ``ev`` (log2 of it), ``log_average`` (of the physical HR radiance) and
    ``frames_metered``. A fixed block is returned as it is."""
    if block.get("mode") != "auto":
        return block
    stats = [s for s in (frame_luminance(r) for r in records.values()) if s is not None]
    la = log_average_luminance(stats)
    value = auto_exposure_value(la)
    return {**block, "value": value, "ev": math.log2(value), "log_average": la, "frames_metered": len(stats)}


def exposure_of(manifest: dict) -> float:
    """The multiplier every reader applies to the clip's radiance and emission: the manifest's ``exposure.value``;
    1 when the manifest has no ``exposure`` (rendered before the key, or at exposure 1) or its auto exposure has no
    finished frame yet. BlendSRError naming the key when the block is malformed."""
    block = manifest.get("exposure")
    if block is None:
        return 1.0
    if not isinstance(block, dict) or block.get("mode") not in ("auto", "fixed"):
        raise BlendSRError(f"exposure {block!r:.80}: expected an object with mode 'auto' or 'fixed'")
    value = block.get("value")
    if value is None and block["mode"] == "auto":
        return 1.0
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        raise BlendSRError(f"exposure.value {value!r}: expected a positive number (the radiance multiplier)")
    return float(value)


def expose(name: str, arr: np.ndarray, exposure: float) -> np.ndarray:
    """Buffer ``name`` as the clip's readers see it: multiplied by ``exposure`` when it is one of
    ``EXPOSED_BUFFERS``, unchanged (the same array) otherwise or at exposure 1. Keeps a float dtype."""
    if name not in EXPOSED_BUFFERS or exposure == 1.0:
        return arr
    return (np.asarray(arr) * np.float32(exposure)).astype(arr.dtype if arr.dtype.kind == "f" else np.float32,
                                                            copy=False)


# ----------------------------------------------------------------------------------------------
# Cameras
# ----------------------------------------------------------------------------------------------

def intrinsics_from_projection(proj: np.ndarray, width: int, height: int) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) in pixels from an OpenGL-style 4x4 perspective projection (Blender's
    ``calc_matrix_camera``) for an image of ``width`` x ``height`` pixels."""
    p = np.asarray(proj, dtype=np.float64)
    fx = 0.5 * width * p[0, 0]
    fy = 0.5 * height * p[1, 1]
    cx = 0.5 * width * (1.0 - p[0, 2])
    cy = 0.5 * height * (1.0 + p[1, 2])
    return float(fx), float(fy), float(cx), float(cy)


def scale_intrinsics(k: tuple[float, float, float, float], factor: float) -> tuple[float, float, float, float]:
    """Intrinsics of the same camera for an image ``factor`` times as large in each dimension."""
    fx, fy, cx, cy = k
    return fx * factor, fy * factor, cx * factor, cy * factor


def scale_fraction(scale: float) -> Fraction:
    """``scale`` as p/q in lowest terms (q <= 1000): 2.5 -> 5/2, 3.75 -> 15/4. ValueError for a scale that is not
    a finite number >= 1 or has no such fraction."""
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale < 1:
        raise BlendSRError(f"scale {scale!r} is not a number >= 1")
    fr = Fraction(scale).limit_denominator(1000)
    if abs(float(fr) - scale) > 1e-9 * scale:
        raise BlendSRError(f"scale {scale!r} is not a ratio of integers with a denominator up to 1000")
    return fr


def level_name(scale: float, primary: float) -> str:
    """Directory and record name of the LR level at ``scale`` in a clip whose primary (first) scale is
    ``primary``: 'lr' for the primary level, 'lr_x{scale:g}' (e.g. 'lr_x2.5', 'lr_x4') for the others."""
    return "lr" if float(scale) == float(primary) else f"lr_x{float(scale):g}"


def is_level_name(name: str) -> bool:
    """True for 'hr', 'lr' and 'lr_x<scale>'."""
    return name in LEVELS or bool(_EXTRA_LEVEL.match(name))


def lr_size(hr_size: tuple[int, int], scale: float) -> tuple[int, int] | None:
    """(W / scale, H / scale) when both are integers, else None."""
    fr = scale_fraction(scale)
    w, h = hr_size
    if (w * fr.denominator) % fr.numerator or (h * fr.denominator) % fr.numerator:
        return None
    return w * fr.denominator // fr.numerator, h * fr.denominator // fr.numerator


def nearest_divisible_sizes(hr_size: tuple[int, int], scales) -> tuple[tuple[int, int], tuple[int, int]]:
    """The HR sizes nearest to ``hr_size`` (one at or below, one above, per axis) that every scale divides into
    integer LR sizes: ((w_below, h_below), (w_above, h_above)); a width or height below is at least one step."""
    step = 1
    for s in scales:
        step = math.lcm(step, scale_fraction(s).numerator)
    below = tuple(max(step, v // step * step) for v in hr_size)
    above = tuple((v // step + 1) * step if v % step else v for v in hr_size)
    return below, above


def pass_seed(seed: int, frame: int, level: int) -> int:
    """Cycles seed of one render pass of a frame: ``level`` 0 is the HR G-buffer pass, 1 the HR ground truth,
    2 + i the i-th LR level (in the order of the manifest's ``levels``). ``validate`` checks every record by it."""
    return (seed * 1000003 + frame * 7 + level) % (2 ** 31 - 1)


def check_level_sizes(hr_size: tuple[int, int], scales, option: str = "--hr-size") -> dict[float, tuple[int, int]]:
    """{scale: (W / scale, H / scale)} for every scale; ValueError naming ``option``, the first scale that does not
    divide the size and the nearest sizes that every scale divides otherwise."""
    out = {}
    w, h = hr_size
    for s in scales:
        size = lr_size(hr_size, s)
        if size is None:
            (wb, hb), (wa, ha) = nearest_divisible_sizes(hr_size, scales)
            near = f"{wb}x{hb} or {wa}x{ha}" if (wb, hb) != (wa, ha) else f"{wa}x{ha}"
            raise BlendSRError(f"{option} {w}x{h} is not divisible by scale {s:g} ({w}/{s:g} = {w / s:g}, "
                             f"{h}/{s:g} = {h / s:g}); nearest sizes that every scale divides: {near}")
        out[float(s)] = size
    return out


def pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates (x, y), each H x W float64."""
    ys, xs = np.meshgrid(np.arange(height, dtype=np.float64) + 0.5,
                         np.arange(width, dtype=np.float64) + 0.5, indexing="ij")
    return xs, ys


def rays_camera(xs: np.ndarray, ys: np.ndarray, k) -> np.ndarray:
    """Camera-space directions (..., 3) with Z = -1 through image positions (xs, ys)."""
    fx, fy, cx, cy = k
    return np.stack([(xs - cx) / fx, -(ys - cy) / fy, -np.ones_like(xs)], axis=-1)


def unproject(depth: np.ndarray, k, jitter=(0.0, 0.0)) -> np.ndarray:
    """Camera-space points H x W x 3 at view depth ``depth`` (H x W) on the rays through pixel centre + jitter."""
    xs, ys = pixel_grid(*depth.shape)
    return rays_camera(xs + jitter[0], ys + jitter[1], k) * depth[..., None]


def project(points_cam: np.ndarray, k) -> tuple[np.ndarray, np.ndarray]:
    """Image positions (x, y) of camera-space points (..., 3); points behind the camera give NaN."""
    fx, fy, cx, cy = k
    z = -points_cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(z > 0, 1.0 / z, np.nan)
    return cx + fx * points_cam[..., 0] * inv, cy - fy * points_cam[..., 1] * inv


def transform_points(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 4x4 affine matrix to points (..., 3)."""
    m = np.asarray(m, dtype=np.float64)
    return pts @ m[:3, :3].T + m[:3, 3]


def reprojection_motion(depth: np.ndarray, k, world_from_camera, k_prev, world_from_camera_prev,
                        jitter=(0.0, 0.0)) -> np.ndarray:
    """Backward motion (H x W x 2, pixels) that static geometry at ``depth`` has between the previous and
    the current camera. Background pixels (depth not finite) get the rotation-only motion. With a ``jitter``,
    depth was sampled at p + jitter and the motion is that point's displacement (jitter excluded)."""
    depth = np.asarray(depth, dtype=np.float64)
    finite = np.isfinite(depth) & (depth > 0)
    xs, ys = pixel_grid(*depth.shape)
    xs, ys = xs + jitter[0], ys + jitter[1]
    pts = rays_camera(xs, ys, k) * np.where(finite, depth, 1.0)[..., None]
    prev_from_cur = np.linalg.inv(np.asarray(world_from_camera_prev, np.float64)) @ np.asarray(world_from_camera,
                                                                                                np.float64)
    p_prev = transform_points(prev_from_cur, pts)
    # Points at infinity: rotate the direction only.
    d_prev = rays_camera(xs, ys, k) @ prev_from_cur[:3, :3].T
    p_prev = np.where(finite[..., None], p_prev, d_prev)
    xp, yp = project(p_prev, k_prev)
    return np.stack([xp - xs, yp - ys], axis=-1)


def background_motion(height: int, width: int, k, world_from_camera, k_prev, world_from_camera_prev,
                      jitter=(0.0, 0.0)) -> np.ndarray:
    """Backward motion (H x W x 2) of points at infinity: what the camera's rotation (and zoom) causes."""
    depth = np.full((height, width), np.inf)
    return reprojection_motion(depth, k, world_from_camera, k_prev, world_from_camera_prev, jitter)


def world_to_camera_normals(normals_world: np.ndarray, world_from_camera) -> np.ndarray:
    """Rotate world-space normals (..., 3) into camera space and renormalise (zero vectors stay zero)."""
    r = np.asarray(world_from_camera, dtype=np.float64)[:3, :3]
    r = r / np.linalg.norm(r, axis=0, keepdims=True)  # strip scale
    n = normals_world.astype(np.float64) @ r  # (R^T n) written for row vectors
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(norm > 1e-12, n / norm, 0.0)
    return out.astype(np.float32)


def halton(index: int, base: int) -> float:
    """Radical inverse of ``index`` (>= 1) in ``base``: the Halton sequence in [0, 1)."""
    f, r = 1.0, 0.0
    while index > 0:
        f /= base
        r += f * (index % base)
        index //= base
    return r


def halton_jitter(frame_index: int, period: int = 16) -> tuple[float, float]:
    """Sub-pixel jitter (dx, dy) in [-0.5, 0.5) pixels from the Halton(2, 3) sequence, as TAA engines use it.
    ``frame_index`` counts frames from 0; the sequence repeats every ``period`` frames."""
    i = frame_index % period + 1
    return halton(i, 2) - 0.5, halton(i, 3) - 0.5


def backward_warp(image: np.ndarray, motion: np.ndarray, fill: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Warp ``image`` of frame t-1 (H x W x C) to frame t with the backward motion of frame t (H x W x 2) by
    bilinear sampling at p + motion. Returns (warped, valid) where valid is False where the sample left the image."""
    h, w = image.shape[:2]
    xs, ys = pixel_grid(h, w)
    sx = xs + motion[..., 0] - 0.5
    sy = ys + motion[..., 1] - 0.5
    valid = np.isfinite(sx) & np.isfinite(sy) & (sx >= -0.5) & (sx <= w - 0.5) & (sy >= -0.5) & (sy <= h - 0.5)
    sx = np.clip(np.nan_to_num(sx), 0, w - 1)
    sy = np.clip(np.nan_to_num(sy), 0, h - 1)
    x0 = np.floor(sx).astype(int)
    y0 = np.floor(sy).astype(int)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = (sx - x0)[..., None]
    fy = (sy - y0)[..., None]
    img = image if image.ndim == 3 else image[..., None]
    out = (img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x1] * fx * (1 - fy)
           + img[y1, x0] * (1 - fx) * fy + img[y1, x1] * fx * fy)
    out = np.where(valid[..., None], out, fill)
    if image.ndim == 2:
        out = out[..., 0]
    return out.astype(image.dtype, copy=False), valid
