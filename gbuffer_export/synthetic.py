"""A synthetic clip written without Blender: an analytic ray-cast scene (checkered ground, spheres, sky) seen by a
moving pinhole camera. Every buffer is exact and consistent with the conventions, so tests of validation,
loading and training can run with numpy only. It is not a renderer substitute: radiance is simple diffuse
shading (fbeta = albedo), and the scene is static (motion and motion_next are pure reprojection).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .clip import ClipWriter, levels_header, scale_value
from .conventions import (ALL_BUFFERS, Flag, exposure_header, pixel_grid, rays_camera, reprojection_motion,
                          scale_intrinsics, world_to_camera_normals)

SPHERES = ((np.array([0.0, 1.0, 0.0]), 1.0), (np.array([2.2, 0.6, -0.8]), 0.6), (np.array([-2.0, 0.8, 1.0]), 0.8))
SUN = np.array([0.4, 0.8, 0.45]) / np.linalg.norm([0.4, 0.8, 0.45])


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """world_from_camera (4x4) of a camera at ``eye`` looking at ``target`` (camera -Z forward, +Y up).
    The synthetic world is y-up; the convention only concerns the camera's local axes."""
    f = target - eye
    f = f / np.linalg.norm(f)
    r = np.cross(f, np.asarray(up, float))
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, u, -f, eye
    return m


def camera_at(t: float) -> np.ndarray:
    """A camera orbiting slowly and bobbing, looking near the origin."""
    a = 0.6 + 0.05 * t
    eye = np.array([6.0 * math.sin(a), 2.2 + 0.1 * math.sin(0.7 * t), 6.0 * math.cos(a)])
    return look_at(eye, np.array([0.1 * math.sin(0.3 * t), 0.7, 0.0]))


def trace(width: int, height: int, k, world_from_camera, jitter=(0.0, 0.0)) -> dict[str, np.ndarray]:
    """Ray-cast one image: returns depth, world normal, albedo, radiance, flags (H x W [x C])."""
    with np.errstate(invalid="ignore", over="ignore"):
        return _trace(width, height, k, world_from_camera, jitter)


def _trace(width, height, k, world_from_camera, jitter):
    xs, ys = pixel_grid(height, width)
    d_cam = rays_camera(xs + jitter[0], ys + jitter[1], k)  # Z = -1, so ray parameter t equals view depth
    r = world_from_camera[:3, :3]
    o = world_from_camera[:3, 3]
    d = d_cam @ r.T
    best = np.full((height, width), np.inf)
    normal = np.zeros((height, width, 3))
    albedo = np.zeros((height, width, 3))
    # ground plane y = 0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[..., 1] < -1e-9, -o[1] / d[..., 1], np.inf)
    hit = t < best
    p = o + d * t[..., None]
    checker = ((np.floor(p[..., 0] * 4) + np.floor(p[..., 2] * 4)) % 2)[..., None]
    best = np.where(hit, t, best)
    normal[hit] = (0.0, 1.0, 0.0)
    albedo = np.where(hit[..., None], 0.15 + 0.7 * checker * np.array([0.9, 0.85, 0.7]), albedo)
    for i, (c, rad) in enumerate(SPHERES):
        oc = o - c
        b = d @ oc
        a2 = np.sum(d * d, axis=-1)
        disc = b * b - a2 * (oc @ oc - rad * rad)
        with np.errstate(invalid="ignore"):
            t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / a2, np.inf)
        t = np.where(t > 1e-6, t, np.inf)
        hit = t < best
        p = o + d * t[..., None]
        n = (p - c) / rad
        stripes = 0.5 + 0.5 * np.sign(np.sin(p[..., 1] * 20 + i))
        col = np.array([[0.8, 0.2, 0.2], [0.2, 0.7, 0.3], [0.3, 0.4, 0.9]][i]) * (0.4 + 0.6 * stripes[..., None])
        best = np.where(hit, t, best)
        normal = np.where(hit[..., None], n, normal)
        albedo = np.where(hit[..., None], col, albedo)
    surface = np.isfinite(best)
    sky = 0.6 + 0.4 * np.clip(d[..., 1:2] / np.linalg.norm(d, axis=-1, keepdims=True), 0, 1) * np.array([0.5, 0.7, 1.0])
    shade = 0.25 + 2.0 * np.clip(normal @ SUN, 0, None)[..., None]
    radiance = np.where(surface[..., None], albedo * shade, sky)
    flags = np.where(surface, 0, int(Flag.BACKGROUND)).astype(np.uint32)
    return {"depth": best, "normal_world": normal, "albedo": albedo, "radiance": radiance, "flags": flags}


@dataclass(frozen=True)
class SyntheticLook:
    """How a synthetic clip is lit, filtered, declared and framed. HR radiance is supersampled ``hr_supersample``^2
    times (anti-aliased); ``scene_linear`` is the working space the manifest declares (the values are the same
    whatever it says); ``light`` multiplies the radiance (a scene lit in other units); ``exposure``: the render
    setting ('auto' or a multiplier; 1 writes no ``exposure`` key, as ``blendsr render`` does); ``camera``:
    t -> world_from_camera."""
    hr_supersample: int = 2
    scene_linear: str = "Linear Rec.709"
    light: float = 1.0
    exposure: str | float = 1.0
    camera: Callable = camera_at


def make_synthetic_clip(path: str | Path, frames=range(1, 5), hr_size=(64, 36), scale: float = 4,
                        buffers=ALL_BUFFERS, jitter: bool = False, scales=None,
                        look: SyntheticLook = SyntheticLook()) -> Path:
    """Write a complete synthetic clip to ``path`` and return it. LR radiance is point-sampled (optionally
    Halton-jittered); ``scales`` (e.g. (2, 2.5, 4)): one LR level per scale, the first is 'lr'; None: ``(scale,)``;
    ``look``: lighting, filtering, declared colour space and camera (``SyntheticLook``)."""
    from .conventions import halton_jitter

    w, h = hr_size
    scales = tuple(float(s) for s in (scales or (scale,)))
    levels = levels_header(hr_size, scales)
    frames = list(frames)
    sizes = {lvl: (v["width"], v["height"]) for lvl, v in levels.items()}
    k_hr = (0.9 * w, 0.9 * w, w / 2, h / 2)
    header = _synthetic_header(levels, scales, frames, buffers, jitter, look)
    with ClipWriter(path, header) as wr:
        for i, f in enumerate(frames):
            m, m_prev, m_next = look.camera(f), look.camera(f - 1), look.camera(f + 1)
            record = {}
            for lvl, (lw, lh) in sizes.items():
                k = scale_intrinsics(k_hr, lw / w)
                jit = halton_jitter(i) if (jitter and lvl != "hr") else (0.0, 0.0)
                bufs = _synthetic_buffers((lw, lh), k, (m, m_prev, m_next), jit,
                                          look.hr_supersample if lvl == "hr" else 1, look.light)
                for b in header["buffers"]:
                    wr.write_buffer(f, lvl, b, bufs[b])
                record[lvl] = {"world_from_camera": m, "prev_world_from_camera": m_prev, "intrinsics": k,
                               "prev_intrinsics": k, "jitter": jit, "spp": 1, "seed": 0, "seconds": {}}
                if "motion_next" in header["buffers"]:
                    record[lvl].update(next_world_from_camera=m_next, next_intrinsics=k)
            wr.commit_frame(f, record)
    return Path(path)


def _synthetic_header(levels: dict, scales: tuple, frames: list, buffers, jitter: bool, look: SyntheticLook) -> dict:
    """The manifest header of a synthetic clip (BlendSR's renders write the same keys)."""
    n = look.hr_supersample
    return {
        "blendsr_version": "synthetic", "blender_version": None,
        "scene": {"file": None, "sha256": None, "builtin": "synthetic-numpy"},
        "scale": scale_value(scales[0]), "levels": levels,
        "frames": frames, "buffers": [b for b in ALL_BUFFERS if b in buffers], "fbeta_source": "synthetic",
        "scene_linear": look.scene_linear, "render": {
            "jitter": "halton" if jitter else "none",
            # n x n samples spread evenly over each HR pixel: a box filter of 1 px (n = 1: a point sample)
            "hr": {"pixel_filter": "BOX" if n > 1 else "GAUSSIAN", "filter_width_px": 1.0 if n > 1 else 0.01},
            "lr": {"pixel_filter": "GAUSSIAN", "filter_width_px": 0.01}},
        "materials": {}, "material_summary": {}, **exposure_header(look.exposure),
    }


def _synthetic_buffers(size: tuple[int, int], k, poses: tuple, jit, supersample: int, light: float) -> dict:
    """Every buffer of one frame and level: ray-traced at the (jittered) pixel centres, the radiance averaged over
    ``supersample``^2 samples spread evenly over each pixel when above 1; ``poses``: this frame's, the previous and
    the next world_from_camera."""
    (lw, lh), (m, m_prev, m_next) = size, poses
    g = trace(lw, lh, k, m)  # G-buffers: un-jittered pixel centres would differ from radiance; use jittered
    if jit != (0.0, 0.0):
        g = trace(lw, lh, k, m, jit)
    if supersample > 1:
        n, acc = supersample, 0
        for sy in range(n):
            for sx in range(n):
                acc = acc + trace(lw, lh, k, m, ((sx + 0.5) / n - 0.5, (sy + 0.5) / n - 0.5))["radiance"]
        radiance = acc / (n * n)
    else:
        radiance = g["radiance"]
    depth = g["depth"]
    return {
        "radiance": radiance * light,
        "albedo": g["albedo"],
        "normal": world_to_camera_normals(g["normal_world"], m),
        "depth": depth,
        "roughness": np.where(np.isfinite(depth), 0.5, 0.0),
        "metallic": np.zeros_like(depth),
        "specular": np.where(np.isfinite(depth), 0.04, 0.0),
        "emission": np.zeros_like(g["albedo"]),
        "fbeta": np.where(np.isfinite(depth)[..., None], g["albedo"], 1.0),
        "motion": reprojection_motion(depth, k, m, k, m_prev, jit),
        "motion_next": reprojection_motion(depth, k, m, k, m_next, jit),
        "flags": g["flags"],
    }
