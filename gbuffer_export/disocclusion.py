"""Disocclusion masks (pure numpy): which pixels of frame t show a surface that frame t-1 did not see.

Warping frame t-1 to frame t with the backward ``motion`` fetches, at a pixel whose surface was hidden in frame t-1,
the occluder that hid it (ghosting). Two ways to find those pixels, each an H x W bool mask (True: disoccluded, or
the motion leaves frame t-1's image):

- ``from_motion`` (NSRD's dual motion vectors, Zeng et al. 2021): follow ``motion`` of frame t from p to q in frame
  t-1, then frame t-1's forward motion ``motion_next`` from q. A surface that stayed visible comes back to p; an
  occluder seen at q goes where the occluder went. Disoccluded where ``|motion(p) + motion_next_{t-1}(q)|`` exceeds
  ``tol_px``. Exact for moving objects; needs clips rendered with ``motion_next``.
- ``from_depth`` (clips without ``motion_next``): the view depth that the surface at p had in frame t-1, computed
  from the two cameras, against frame t-1's depth at q. Disoccluded where the inverse depths differ by more than
  ``rel_tol`` (inverse depth is affine in image coordinates on a plane, so bilinear sampling is exact there).
  It assumes static geometry: an object moving along the view axis by more than ``rel_tol`` of its depth per frame
  is flagged too.

Both sample frame t-1 bilinearly at q = p + motion + jitter_t - jitter_(t-1) (pixels of the level; the jitter
difference brings frame t's sample position to frame t-1's pixel grid, as ``training.models.base.history_offsets``
does), so along an occluder's edge the mixed samples are flagged too.
"""
from __future__ import annotations

import numpy as np

from .errors import BlendSRError
from .conventions import backward_warp, transform_points, unproject

#: Round-trip tolerance of ``from_motion``, pixels of the level (NSRD's code gates each component at 0.1 px).
TOL_PX = 0.1
#: Relative inverse-depth tolerance of ``from_depth``.
DEPTH_REL_TOL = 0.02


def sample_offset(motion: np.ndarray, jitter=(0.0, 0.0), jitter_prev=(0.0, 0.0)) -> np.ndarray:
    """(H x W x 2) offset from pixel centre p of frame t to the position q - p in frame t-1's pixel grid."""
    d = np.asarray(jitter, np.float64) - np.asarray(jitter_prev, np.float64)
    return np.asarray(motion, np.float64) + d


def from_motion(motion: np.ndarray, motion_next_prev: np.ndarray, *, tol_px: float = TOL_PX, jitter=(0.0, 0.0),
                jitter_prev=(0.0, 0.0)) -> np.ndarray:
    """Disocclusion of frame t w.r.t. t-1 (H x W bool) from ``motion`` of frame t and ``motion_next`` of frame t-1
    (both H x W x 2, pixels of the level) and the two frames' jitters (dx, dy)."""
    off = sample_offset(motion, jitter, jitter_prev)
    fwd, valid = backward_warp(np.asarray(motion_next_prev, np.float64), off)
    err = np.linalg.norm(np.asarray(motion, np.float64) + fwd, axis=-1)
    return ~valid | ~(err <= tol_px)


def from_depth(depth: np.ndarray, motion: np.ndarray, depth_prev: np.ndarray, cam: dict, *,
               rel_tol: float = DEPTH_REL_TOL, jitter_prev=(0.0, 0.0)) -> np.ndarray:
    """Disocclusion of frame t w.r.t. t-1 (H x W bool) from view depth of both frames (H x W, +inf on background),
    ``motion`` of frame t and frame t's camera record as ``Clip.camera`` gives it: ``intrinsics`` (fx, fy, cx, cy),
    ``world_from_camera``, ``prev_world_from_camera`` (frame t-1's) and ``jitter`` (default 0, 0)."""
    intrinsics, world_from_camera = cam["intrinsics"], cam["world_from_camera"]
    prev_world_from_camera, jitter = cam["prev_world_from_camera"], cam.get("jitter", (0.0, 0.0))
    depth = np.asarray(depth, np.float64)
    surface = np.isfinite(depth) & (depth > 0)
    pts = unproject(np.where(surface, depth, 1.0), intrinsics, jitter)
    prev_from_cur = np.linalg.inv(np.asarray(prev_world_from_camera, np.float64)) @ \
        np.asarray(world_from_camera, np.float64)
    z_prev = -transform_points(prev_from_cur, pts)[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_exp = np.where(surface, 1.0 / z_prev, 0.0)  # background: a point at infinity
        dp = np.asarray(depth_prev, np.float64)
        inv_prev = np.where(np.isfinite(dp) & (dp > 0), 1.0 / dp, 0.0)
    inv_got, valid = backward_warp(inv_prev, sample_offset(motion, jitter, jitter_prev))
    behind = surface & ~(z_prev > 0)  # the point was behind frame t-1's camera
    diff = np.abs(inv_got - inv_exp)
    return ~valid | behind | (diff > rel_tol * np.maximum(inv_got, inv_exp))


def clip_mask(clip, frame: int, level: str, method: str = "auto", **kw) -> np.ndarray:
    """Disocclusion mask (H x W bool) of ``frame`` of a clip (``gbuffer_export.open_clip``) w.r.t. ``frame - 1``.
    ``method``: 'motion' (needs ``motion_next``), 'depth', or 'auto' (motion when the clip has it)."""
    if method == "auto":
        method = "motion" if "motion_next" in clip.buffers else "depth"
    if method not in ("motion", "depth"):
        raise BlendSRError(f"disocclusion method {method!r}: choose motion, depth or auto")
    if frame - 1 not in clip.frames or frame not in clip.frames:
        raise BlendSRError(f"{clip.path}: frames {frame - 1} and {frame} must both be finished for a disocclusion mask")
    cam, cam_prev = clip.camera(frame, level), clip.camera(frame - 1, level)
    jit = dict(jitter=cam["jitter"], jitter_prev=cam_prev["jitter"])
    motion = clip.read(frame, f"{level}/motion")
    if method == "motion":
        return from_motion(motion, clip.read(frame - 1, f"{level}/motion_next"), **jit, **kw)
    depth, depth_prev = (clip.read(f, f"{level}/depth")[..., 0] for f in (frame, frame - 1))
    return from_depth(depth, motion, depth_prev, cam, jitter_prev=cam_prev["jitter"], **kw)
