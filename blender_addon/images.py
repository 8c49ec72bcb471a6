"""Float images in ``bpy.data.images`` for the preview (linear scene-referred RGB, shown through the view
transform like a render)."""
from __future__ import annotations

import bpy
import numpy as np

SR_IMAGE = "BlendSR SR"
BILINEAR_IMAGE = "BlendSR bilinear"
REFERENCE_IMAGE = "BlendSR reference"


def set_image(name: str, rgb: np.ndarray) -> bpy.types.Image:
    """Create or replace float image ``name`` with ``rgb`` (H x W x 3 linear, row 0 at the top; Blender stores
    rows bottom-up, so rows are flipped). Alpha is 1."""
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.ndim != 3 or rgb.shape[2] < 3:
        raise ValueError(f"image {name!r}: expected H x W x 3, got shape {rgb.shape}")
    h, w = rgb.shape[:2]
    img = bpy.data.images.get(name)
    if img is not None and (tuple(img.size) != (w, h) or not img.is_float or img.source != "GENERATED"):
        bpy.data.images.remove(img)
        img = None
    if img is None:
        img = bpy.data.images.new(name, width=w, height=h, alpha=True, float_buffer=True)
    rgba = np.ones((h, w, 4), dtype=np.float32)
    rgba[..., :3] = np.nan_to_num(rgb[..., :3], nan=0.0, posinf=65504.0, neginf=0.0)
    img.pixels.foreach_set(np.ascontiguousarray(rgba[::-1]).ravel())
    img.update()
    return img


def image_array(img: bpy.types.Image) -> np.ndarray:
    """H x W x 3 float32 of an image, row 0 at the top (the inverse of ``set_image``)."""
    w, h = img.size
    buf = np.empty(w * h * 4, dtype=np.float32)
    img.pixels.foreach_get(buf)
    return buf.reshape(h, w, 4)[::-1, :, :3].copy()


def show_in_image_editors(img: bpy.types.Image, context=None) -> int:
    """Show ``img`` in every open Image Editor; returns how many editors show it."""
    context = context or bpy.context
    wm = getattr(context, "window_manager", None)
    n = 0
    for win in getattr(wm, "windows", []):
        for area in win.screen.areas:
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = img
                area.tag_redraw()
                n += 1
    return n
