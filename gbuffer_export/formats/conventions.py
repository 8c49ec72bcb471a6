"""Conversions between BlendSR's conventions (docs/clip-format.md) and Arm's NSS capture layout, written once.

Read from Arm's specification (``docs/nss/nss_dataset_specification.md`` of ``arm/neural-graphics-model-gym``) and
its readers (``scripts/safetensors_generator``); see docs/formats.md for the evidence behind each sign.

- **Motion** (NSS ``motion``, ``motion_gt``): UV units (pixels / level size), u right, v down, *current minus
  previous* (the model gym warps history by sampling at ``p - motion``). BlendSR's ``motion`` is ``p_prev - p`` in
  pixels, so ``uv = -motion / (W, H)``. Jitter is excluded in both.
- **Depth** (NSS ``depth``): forward-Z device depth in [0, 1] of a D3D-style projection with the frame's near and
  far planes (FSR2's ``depth_to_view_space_params``, non-inverted, finite): ``d = f (z - n) / (z (f - n))`` for
  view depth ``z``; BlendSR's background (+inf) becomes 1 (the far plane).
- **ViewProjection**: ``P @ view`` for column vectors, ``view = inverse(world_from_camera)`` (Blender world, scene
  units), ``P`` the un-jittered projection from the level's intrinsics to clip space with NDC x right, y up,
  w = view depth and z = 1 - the stored device depth (reverse-Z: 1 at the near plane, 0 at the far one). The depth
  files stay forward-Z (``ReverseZ`` false); Arm's captures pair them the same way (the z row of their sample
  matrices is the reverse-Z infinite ``[0, 0, 0, near]``) and the model gym's NFRU reader reprojects with
  ``1 - depth`` through these matrices; written as 16 floats row by row (``M[r][c]`` at ``4 r + c``): the
  specification's "column-major, assuming row-vector math", the layout of Arm's sample captures
  (``tests/datasets/test_nss_exr/0002.json``: the translation column at elements 3, 7, 11, 15, the unit view
  direction at 12-14) and what the model gym's readers reshape to 4 x 4 and multiply column vectors with.
- **Jitter**: pixels of the level, x right, y down, the sample of pixel centre p taken at p + jitter (BlendSR's);
  ``NormalizedPerRatioJitter`` = jitter / (W, H) of that level.
- **Field of view**: ``FovX = 2 atan(W / (2 fx))``, ``FovY = 2 atan(H / (2 fy))`` (radians).
- **Ratio names**: ``x2``, ``x2_5`` (directory ``x{name}``, JSON key ``x{name}_index``).
"""
from __future__ import annotations

import math

import numpy as np


def ratio_name(scale: float) -> str:
    """'2' for 2.0, '2_5' for 2.5, '1_5' for 1.5: the NSS directory ``x<name>`` and key ``x<name>_index``."""
    return format(float(scale), "g").replace(".", "_")


def motion_to_uv(motion_px: np.ndarray) -> np.ndarray:
    """BlendSR backward motion (H x W x 2, pixels, p_prev = p + motion) -> NSS UV motion (current - previous)."""
    h, w = motion_px.shape[:2]
    return -np.asarray(motion_px, np.float64) / np.array([w, h], np.float64)


def uv_to_motion(motion_uv: np.ndarray) -> np.ndarray:
    """NSS UV motion (H x W x 2) -> BlendSR backward motion in pixels (the inverse of ``motion_to_uv``)."""
    h, w = motion_uv.shape[:2]
    return -np.asarray(motion_uv, np.float64) * np.array([w, h], np.float64)


def view_depth_to_device(z: np.ndarray, near: float, far: float) -> np.ndarray:
    """View depth (> 0, +inf on background) -> forward-Z device depth in [0, 1] (0 at near, 1 at far).
    Surfaces must lie before the far plane: a depth of 1 reads back as background (``depth_planes`` leaves room)."""
    z = np.asarray(z, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = far * (z - near) / (z * (far - near))
    return np.where(np.isfinite(z), d, 1.0)


def device_to_view_depth(d: np.ndarray, near: float, far: float) -> np.ndarray:
    """Forward-Z device depth -> view depth; 1 (the far plane) and beyond -> +inf (background)."""
    d = np.asarray(d, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = near * far / (far - d * (far - near))
    return np.where(d >= 1.0, np.inf, z)


def projection(k, width: int, height: int, near: float, far: float, *, reverse_z: bool = False) -> np.ndarray:
    """4 x 4 clip-from-camera matrix (column vectors) of intrinsics ``k`` for a ``width`` x ``height`` image:
    camera space is Blender's (looks along -Z, +Y up); NDC x right, y up in [-1, 1], z in [0, 1]: the forward-Z
    device depth of ``view_depth_to_device`` (0 at near), or with ``reverse_z`` one minus it (1 at near)."""
    fx, fy, cx, cy = (float(v) for v in k)
    p = np.zeros((4, 4))
    p[0, 0], p[0, 2] = 2 * fx / width, 1 - 2 * cx / width
    p[1, 1], p[1, 2] = 2 * fy / height, 2 * cy / height - 1
    if reverse_z:  # z_ndc = n (f - z) / (z (f - n)) for view depth z = -z_cam
        p[2, 2], p[2, 3] = near / (far - near), far * near / (far - near)
    else:  # z_ndc = f (z - n) / (z (f - n))
        p[2, 2], p[2, 3] = far / (near - far), far * near / (near - far)
    p[3, 2] = -1.0
    return p


def view_projection(world_from_camera, k, width: int, height: int, near: float, far: float, *,
                    reverse_z: bool = False) -> np.ndarray:
    """4 x 4 clip-from-world matrix (column vectors); ``reverse_z`` as in ``projection``."""
    return (projection(k, width, height, near, far, reverse_z=reverse_z)
            @ np.linalg.inv(np.asarray(world_from_camera, np.float64)))


def matrix_to_list(m: np.ndarray) -> list[float]:
    """16 floats of a column-vector matrix, row by row: the ``ViewProjection`` layout of the specification
    (column-major storage of the row-vector form) and of Arm's sample files (translation at 3, 7, 11, 15)."""
    return [float(v) for v in np.asarray(m, np.float64).reshape(-1)]


def list_to_matrix(values) -> np.ndarray:
    """Inverse of ``matrix_to_list``."""
    return np.asarray(values, np.float64).reshape(4, 4)


def camera_from_view_projection(vp, width: int, height: int):
    """(world_from_camera, intrinsics) of a ViewProjection built by ``view_projection`` (rigid camera).
    VP = P @ view with P's rows [a 0 b 0], [0 c e 0], [0 0 g h], [0 0 -1 0]: VP's last row is minus view's third
    row, and its first two rows are a * view_x + b * view_z and c * view_y + e * view_z (view's rows orthonormal)."""
    vp = np.asarray(vp, np.float64)
    vz = -vp[3]
    b = float(np.dot(vp[0, :3], vz[:3]))
    e = float(np.dot(vp[1, :3], vz[:3]))
    vx, vy = vp[0] - b * vz, vp[1] - e * vz
    a, c = float(np.linalg.norm(vx[:3])), float(np.linalg.norm(vy[:3]))
    view = np.stack([vx / a, vy / c, vz, [0.0, 0.0, 0.0, 1.0]])
    k = (a * width / 2, c * height / 2, (1 - b) * width / 2, (1 + e) * height / 2)
    return np.linalg.inv(view), k


def fov(k, width: int, height: int) -> tuple[float, float]:
    """(FovX, FovY) in radians of intrinsics ``k`` for a ``width`` x ``height`` image."""
    fx, fy = float(k[0]), float(k[1])
    return 2 * math.atan(width / (2 * fx)), 2 * math.atan(height / (2 * fy))


def normalized_jitter(jitter_px, width: int, height: int) -> dict[str, float]:
    """NormalizedPerRatioJitter entry {"X", "Y"}: jitter in pixels / the level's size."""
    return {"X": float(jitter_px[0]) / width, "Y": float(jitter_px[1]) / height}


def depth_planes(depths) -> tuple[float, float]:
    """(near, far) enclosing every finite view depth of ``depths`` (arrays): half the least, twice the largest."""
    lo, hi = math.inf, 0.0
    for d in depths:
        f = np.asarray(d)[np.isfinite(d) & (np.asarray(d) > 0)]
        if f.size:
            lo, hi = min(lo, float(f.min())), max(hi, float(f.max()))
    if not math.isfinite(lo):
        return 0.1, 1000.0
    return 0.5 * lo, 2.0 * hi


# ----------------------------------------------------------------------------------------------
# RDG (the RDG authors' basicsr/data/render_dataset.py and basicsr/utils/render_data_util.py)
# ----------------------------------------------------------------------------------------------
# Their loader reads Motion with OpenCV, negates the second channel ("correct the Y direction") and warps the
# previous frame by sampling it at p + motion (pixels): the file holds BlendSR's backward motion with y up
# (Blender's Vector-pass orientation). Image is an 8-bit PNG divided by 255; Depth, BRDF and Emit are min-max
# normalised per image by the loader, Normal mapped from [-1, 1] to [0, 1]: their absolute scale is not used.

def motion_to_rdg(motion_px: np.ndarray) -> np.ndarray:
    """BlendSR backward motion (pixels, y down) -> RDG's stored motion (pixels, y up)."""
    m = np.asarray(motion_px, np.float64).copy()
    m[..., 1] *= -1
    return m


def rdg_to_motion(stored: np.ndarray) -> np.ndarray:
    """RDG's stored motion -> BlendSR backward motion (the inverse of ``motion_to_rdg``)."""
    return motion_to_rdg(stored)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear Rec.709 -> sRGB-encoded values in [0, 1] (IEC 61966-2-1 transfer; values clipped to [0, 1] first:
    Blender's 'Standard' view transform, no tone curve): ``colour_spaces.srgb_encode`` (colour-science)."""
    from ..colour_spaces import srgb_encode as encode
    return encode(linear)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """sRGB-encoded [0, 1] -> linear (the inverse of ``srgb_encode`` on [0, 1]): ``colour_spaces.srgb_decode``."""
    from ..colour_spaces import srgb_decode as decode
    return decode(encoded)


def depth_for_rdg(depth: np.ndarray) -> np.ndarray:
    """View depth with +inf on background -> finite depth: background gets the frame's largest surface depth
    (their loader min-max normalises depth per image, so an infinite or 1e10 background would flatten it)."""
    d = np.asarray(depth, np.float64)
    fin = np.isfinite(d)
    return np.where(fin, d, d[fin].max() if fin.any() else 1.0)
