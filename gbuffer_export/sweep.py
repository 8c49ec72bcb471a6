"""Where a moving thing may go without passing through anything else (pure numpy, no bpy): axis-aligned boxes,
frame by frame. The bpy layer measures the boxes (``gbuffer_export.blender.default_scene.placement``); this module
judges candidate starts against them, so that the rule is tested without Blender.

A mover's boxes are measured once, relative to its start point with its heading +X, and moved to each candidate
``(x, y, direction)``: direction -1 turns the walk by 180 degrees about +Z through the start (x and y negated), so
that a walk whose body motion does not depend on its heading (``character.key_walk``) is measured once for both.
Boxes are judged at the clip's frames only: two boxes could pass through each other between frames only if they
moved by more than their extents along the motion in one frame (the built-in movers travel at most 13 cm a frame
towards each other, a walker is over 30 cm long). Units are metres, +Z up. Everything topped within ``STEP_M`` of
the ground is stepped through, not walked round (a rug, a slab, pebbles below the ankle); ground boxes never block.
"""
from __future__ import annotations

import numpy as np

#: The highest top (m above z = 0) that a walker steps through rather than around: below its ankle (pebbles, a slab).
STEP_M = 0.04


def placed(local: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """(C, 2, 3) boxes (lo, hi) of ``local`` (2, 3), measured at start (0, 0) heading +X, moved to each of ``starts``
    (C, 3): x, y and direction (+1: +X, -1: -X, turned 180 degrees about +Z)."""
    local = np.asarray(local, np.float64)
    starts = np.asarray(starts, np.float64)
    turned = np.stack([np.array([-local[1, 0], -local[1, 1], local[0, 2]]),
                       np.array([-local[0, 0], -local[0, 1], local[1, 2]])])
    out = np.where((starts[:, 2] < 0)[:, None, None], turned[None], local[None]).copy()
    out[:, :, :2] += starts[:, None, :2]
    return out


def blocking(obstacles: np.ndarray, ground: np.ndarray | None = None) -> np.ndarray:
    """The boxes of ``obstacles`` (K, 2, 3) that block a walker: not ``ground`` (K,) and topped above ``STEP_M``."""
    obstacles = np.asarray(obstacles, np.float64).reshape(-1, 2, 3)
    keep = obstacles[:, 1, 2] > STEP_M
    if ground is not None:
        keep &= ~np.asarray(ground, bool)
    return obstacles[keep]


def clear_starts(local: np.ndarray, obstacles: np.ndarray, starts: np.ndarray, clearance: float) -> np.ndarray:
    """(C,) bool: which of ``starts`` (C, 3: x, y, direction) put the box ``local`` (2, 3; one frame, relative to the
    start heading +X) at least ``clearance`` metres (on some axis) from every box of ``obstacles`` (K, 2, 3) of the
    same frame. Call once per frame and AND the results: movers are judged frame by frame, not by their sweep."""
    boxes = placed(local, starts)                                     # (C, 2, 3)
    obstacles = np.asarray(obstacles, np.float64).reshape(-1, 2, 3)
    if len(obstacles) == 0:
        return np.ones(len(boxes), bool)
    apart = ((boxes[:, None, 0] >= obstacles[None, :, 1] + clearance)
             | (obstacles[None, :, 0] >= boxes[:, None, 1] + clearance))  # (C, K, 3): separated on that axis
    return ~np.any(np.all(~apart, axis=2), axis=1)


def half_width(frames: list) -> float:
    """The mover's largest reach (m) across its path's line, either side, over ``frames`` (the list of
    ``clear_mask``): the lane's half width in either direction."""
    return float(max(np.abs(np.asarray(own, np.float64)[:, 1]).max() for own, *_ in frames))


def clear_mask(frames: list, starts: np.ndarray, clearance: float) -> np.ndarray:
    """(C,) bool: which of ``starts`` (C, 3) are clear of the blocking boxes (``blocking``) in every frame of
    ``frames`` (a list of (own (2, 3), others (K, 2, 3), ground (K,)))."""
    ok = np.ones(len(starts), bool)
    for own, others, ground in frames:
        ok &= clear_starts(own, blocking(others, ground), starts, clearance)
    return ok

