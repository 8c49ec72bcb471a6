"""Cycles passes -> clip buffers (bpy layer): which passes a render needs (``plan_passes``) and one converter per
buffer (``CONVERTERS``), each turning the passes of one level into that buffer in the clip's conventions
(``gbuffer_export.conventions``, ``docs/clip-format.md``).

A new buffer gets a row in ``CONVERTERS`` (and, when it reads a new kind of Cycles pass, a row in ``PASSES``). A converter is
``f(src: LevelPasses, out: dict) -> array``; ``out`` holds the buffers converted before it in table order (F_beta
reads the G-buffers). ``radiance`` is not here: it is the Combined pass of the level's radiance render.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..conventions import Flag, background_motion, computed_buffers, scale_intrinsics, world_to_camera_normals
from ..exr import read_exr_channels
from . import materials as mats

BACKGROUND_DEPTH = 1e9  # Cycles writes 1e10 for background in the Depth pass


def colour_sum(passes: dict) -> np.ndarray:
    """H x W x 3: the sum of a render's colour passes (``PASSES["colors"]``), the directional albedo F_beta
    (docs/brdf.md)."""
    return sum(passes[k][..., :3] for k in PASSES["colors"].names)


def reactive_mask(passes: dict) -> np.ndarray:
    """H x W bool: where a transmissive surface is the first hit, from the ``materials.AOV_REACTIVE`` pass of a render
    with ``gbuffer_transmission = "behind"`` (above ``materials.REACTIVE_MIN``): the reactive mask."""
    return passes[mats.AOV_REACTIVE][..., 0] > mats.REACTIVE_MIN


@dataclass(frozen=True)
class PassRow:
    """One kind of Cycles pass: the view-layer switches that enable it (``use_pass_*``), the EXR passes it writes
    (the names the converters read) and when a render needs it (``needed(buffers, fbeta)``: the requested buffers
    with those computed from them, ``conventions.computed_buffers``, and the F_beta source)."""

    switches: tuple[str, ...]
    names: tuple[str, ...]
    needed: Callable[[frozenset, str], bool]


#: The plan's passes (a field of ``PassPlan`` each): enabling a pass (``render.set_passes``) and planning it
#: (``plan_passes``) come from its one row, as Kubric's table of post-processors does.
PASSES: dict[str, PassRow] = {
    "depth": PassRow(("use_pass_z",), ("Depth",),  # every G-buffer's background mask
                     lambda b, fbeta: bool(b - {"radiance"})),
    "normal": PassRow(("use_pass_normal",), ("Normal",), lambda b, fbeta: "normal" in b),
    "vector": PassRow(("use_pass_vector",), ("Vector",),  # one Vector pass holds both motions
                      lambda b, fbeta: "motion" in b or "motion_next" in b),
    "colors": PassRow(("use_pass_diffuse_color", "use_pass_glossy_color", "use_pass_transmission_color"),
                      ("Diffuse Color", "Glossy Color", "Transmission Color"),
                      lambda b, fbeta: "fbeta" in b and fbeta == "cycles"),
    "emit": PassRow(("use_pass_emit", "use_pass_environment"),  # the environment: the emission buffer's
                    ("Emission", "Environment"), lambda b, fbeta: "emission" in b),  # background pixels
    "index": PassRow(("use_pass_material_index", "use_pass_object_index"), ("Material Index", "Object Index"),
                     lambda b, fbeta: "flags" in b or "fbeta" in b),
}


@dataclass(frozen=True)
class PassPlan:
    """Which Cycles passes a render needs (one field per row of ``PASSES``), derived from the requested buffers,
    and the AOVs of the material-derived buffers."""

    depth: bool = False
    normal: bool = False
    vector: bool = False
    colors: bool = False
    emit: bool = False
    index: bool = False
    aovs: tuple[str, ...] = ()

    @property
    def any(self) -> bool:
        return any(getattr(self, k) for k in PASSES) or bool(self.aovs)


def plan_passes(buffers, fbeta: str, aov_names) -> PassPlan:
    """The passes that the G-buffers in ``buffers`` (and, for a table ``fbeta``, its inputs) need, and no others."""
    b = frozenset(computed_buffers(buffers, fbeta))
    return PassPlan(**{k: row.needed(b, fbeta) for k, row in PASSES.items()}, aovs=tuple(aov_names))


def read_passes(path: Path) -> dict[str, np.ndarray]:
    """Passes of a Blender multilayer EXR as {'Combined': HxWx4, 'Depth': HxWx1, ...} (view-layer prefix dropped,
    channels in the order RGBA / XYZW)."""
    raw = read_exr_channels(path)
    groups: dict[str, dict[str, np.ndarray]] = {}
    for full, arr in raw.items():
        parts = full.split(".")
        if len(parts) < 2:
            continue
        groups.setdefault(parts[-2], {})[parts[-1]] = arr
    order = "RGBAXYZW"
    out = {}
    for name, chans in groups.items():
        keys = sorted(chans, key=lambda c: order.index(c) if c in order else 99)
        out[name] = np.stack([chans[k] for k in keys], axis=-1).astype(np.float32)
    return out


@dataclass(frozen=True)
class LevelCameras:
    """The camera of one frame at one level: world_from_camera (4x4 float64, no scale) of frames t, t-1 and t+1
    (``m_next``/``k_next``: None unless ``motion_next`` is rendered) and intrinsics (fx, fy, cx, cy) in pixels of
    the level."""

    m: np.ndarray
    k: tuple
    m_prev: np.ndarray
    k_prev: tuple
    m_next: np.ndarray | None = None
    k_next: tuple | None = None

    def at_scale(self, scale: float) -> "LevelCameras":
        """The same poses with intrinsics of a level ``scale`` times smaller."""
        k_next = scale_intrinsics(self.k_next, 1 / scale) if self.k_next is not None else None
        return LevelCameras(self.m, scale_intrinsics(self.k, 1 / scale), self.m_prev,
                            scale_intrinsics(self.k_prev, 1 / scale), self.m_next, k_next)

    def record(self, **entries) -> dict:
        """A level's frame record: its camera, then ``entries``, then the camera of t+1 when there is one."""
        rec = {"world_from_camera": self.m, "prev_world_from_camera": self.m_prev, "intrinsics": self.k,
               "prev_intrinsics": self.k_prev, **entries}
        if self.m_next is not None:
            rec.update(next_world_from_camera=self.m_next, next_intrinsics=self.k_next)
        return rec


class LevelPasses:
    """The passes of one level's render and what converters share: depth (float64, H x W), the background mask,
    the per-pixel flags (uint32, H x W; from the index passes and ``flag_lut``, material index -> flag bits)."""

    def __init__(self, passes: dict, plan: PassPlan, cams: LevelCameras, jitter, flag_lut: np.ndarray,
                 fbeta_source: str):
        self.passes, self.plan, self.cams, self.jitter = passes, plan, cams, jitter
        self.flag_lut, self.fbeta_source = flag_lut, fbeta_source

    @functools.cached_property
    def depth(self) -> np.ndarray:
        return self.passes["Depth"][..., 0].astype(np.float64)

    @functools.cached_property
    def bg(self) -> np.ndarray:
        return self.depth >= BACKGROUND_DEPTH

    @functools.cached_property
    def flags(self) -> np.ndarray:
        lut = self.flag_lut
        mat_index = np.clip(np.rint(self.passes["Material Index"][..., 0]).astype(np.int64), 0, len(lut) - 1)
        obj_index = np.rint(self.passes["Object Index"][..., 0]).astype(np.int64)
        flags = lut[mat_index].astype(np.uint32)
        flags |= np.where(obj_index > 0, int(Flag.MOVING), 0).astype(np.uint32)
        flags = np.where(self.bg, int(Flag.BACKGROUND), flags).astype(np.uint32)
        if mats.AOV_REACTIVE in self.plan.aovs:  # gbuffer_transmission "behind": a transmissive surface in front
            flags |= np.where(reactive_mask(self.passes), int(Flag.TRANSMISSION), 0).astype(np.uint32)
        return flags


def _depth(src: LevelPasses, out: dict) -> np.ndarray:
    return np.where(src.bg, np.inf, src.depth)[..., None]


def _normal(src: LevelPasses, out: dict) -> np.ndarray:
    n = world_to_camera_normals(src.passes["Normal"][..., :3], src.cams.m)
    return np.where(src.bg[..., None], 0.0, n)


#: Both motions come from the one Vector pass (y up): ``motion`` = (X, -Y) toward frame t-1; Z, W = p(t) - p(t+1),
#: so ``motion_next`` = p(t+1) - p(t) = (-Z, +W) (image coordinates, y down). Per buffer: (channel, sign) of x,
#: (channel, sign) of y, and the camera (``prev`` or ``next``) its background motion is computed with.
MOTION_CHANNELS = {"motion": ((0, 1.0), (1, -1.0), "prev"), "motion_next": ((2, -1.0), (3, 1.0), "next")}


def _motion(buffer: str, src: LevelPasses, out: dict) -> np.ndarray:
    """``motion`` or ``motion_next`` (``MOTION_CHANNELS``); background pixels move with the camera alone."""
    (cx, sx), (cy, sy), other = MOTION_CHANNELS[buffer]
    vec, c = src.passes["Vector"], src.cams
    mv = np.stack([sx * vec[..., cx], sy * vec[..., cy]], axis=-1).astype(np.float64)
    k_o, m_o = (c.k_prev, c.m_prev) if other == "prev" else (c.k_next, c.m_next)
    h, w = mv.shape[:2]
    return np.where(src.bg[..., None], background_motion(h, w, c.k, c.m, k_o, m_o, src.jitter), mv)


def _flags(src: LevelPasses, out: dict) -> np.ndarray:
    return src.flags[..., None]


def _aov(buffer: str, src: LevelPasses, out: dict) -> np.ndarray:
    """A material parameter written by BlendSR's Shader AOV outputs (``materials.install_aovs``); 0 on background."""
    if buffer in mats.AOV_COLOR:
        arr = src.passes[mats.AOV_COLOR[buffer]][..., :3]
    else:
        arr = src.passes[mats.AOV_VALUE[buffer]][..., :1]
    return np.where(src.bg[..., None], 0.0, arr)


def _emission(src: LevelPasses, out: dict) -> np.ndarray:
    """Surfaces: their emission; background: the environment seen directly (conventions: emission)."""
    p = src.passes
    return np.maximum(np.where(src.bg[..., None], p["Environment"][..., :3], p["Emission"][..., :3]), 0.0)


def _fbeta(src: LevelPasses, out: dict) -> np.ndarray:
    """'cycles': the sum of the colour passes; a table source: ``brdf.compute_fbeta`` of the G-buffers in ``out``."""
    p = src.passes
    if src.fbeta_source == "cycles":
        fb = colour_sum(p)
    else:
        from ..brdf import compute_fbeta
        gbuf = {key: out[key] for key in ("albedo", "normal", "roughness", "metallic", "specular") if key in out}
        gbuf["flags"] = src.flags[..., None]
        fb = compute_fbeta(src.fbeta_source, gbuf, src.cams.k, src.jitter)
    return np.where(src.bg[..., None], 1.0, fb)


#: One converter per G-buffer, in the order they run (F_beta last: it reads the G-buffers before it).
CONVERTERS = {
    "depth": _depth,
    "normal": _normal,
    "motion": functools.partial(_motion, "motion"),
    "motion_next": functools.partial(_motion, "motion_next"),
    "flags": _flags,
    **{b: functools.partial(_aov, b) for b in (*mats.AOV_COLOR, *mats.AOV_VALUE)},
    "emission": _emission,
    "fbeta": _fbeta,
}


def convert(passes: dict, plan: PassPlan, buffers, cams: LevelCameras, *, jitter, flag_lut: np.ndarray,
            fbeta_source: str) -> dict[str, np.ndarray]:
    """The G-buffers of ``buffers`` (and a table F_beta's inputs: ``computed_buffers``) from the Cycles passes of
    one level (``cams``: its camera, ``jitter``: its (dx, dy) in pixels of the level)."""
    wanted = set(computed_buffers(buffers, fbeta_source))
    src = LevelPasses(passes, plan, cams, jitter, flag_lut, fbeta_source)
    out: dict[str, np.ndarray] = {}
    for name, fn in CONVERTERS.items():
        if name in wanted:
            out[name] = fn(src, out)
    return out
