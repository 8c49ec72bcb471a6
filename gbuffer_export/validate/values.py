"""Value checks of one frame and level, buffer by buffer: finite values; depth > 0 on surfaces and +inf exactly
on background; unit normals on surfaces, zero on background; fbeta in [0, fbeta_max] on surfaces and 1 on
background; material buffers in [0, 1]; emission >= 0; radiance and emission below ``RADIANCE_CAP``; only known
flag bits; and, for clips whose emission holds the environment on background, that the point-sampled LR radiance
is that environment there (``check_background_emission``)."""
from __future__ import annotations

import numpy as np

from ..conventions import Flag
from ..demod import RADIANCE_CAP
from ..regions import dilate
from .report import ERROR, WARNING, Collector, fmt_frac


_KNOWN_FLAG_BITS = 0
for _f in Flag:
    _KNOWN_FLAG_BITS |= int(_f)


#: ``negative-radiance``: a surface pixel is negative when a channel is below -NEGATIVE_RADIANCE_TOL (a denoiser's
#: rounding may dip just under 0); the check fails when more than NEGATIVE_RADIANCE_MAX_FRACTION of them are.
NEGATIVE_RADIANCE_TOL = 1e-4
NEGATIVE_RADIANCE_MAX_FRACTION = 0.01


def check_values(c: Collector, frame: int, lvl: str, b: dict[str, np.ndarray]) -> np.ndarray | None:
    """Value checks of one frame and level; returns the surface mask (H x W bool) or None when unknown."""
    flags = b.get("flags")
    surface = _check_flags(c, frame, lvl, flags)
    surface = _check_depth(c, frame, lvl, b.get("depth"), surface)
    for name, arr in b.items():
        if name not in ("depth", "flags"):
            _check_finite_and_radiance(c, frame, lvl, name, arr, surface)
    if b.get("normal") is not None:
        _check_normal(c, frame, lvl, b["normal"], surface, flags)
    if b.get("fbeta") is not None:
        _check_fbeta(c, frame, lvl, b["fbeta"], surface)
    _check_material_ranges(c, frame, lvl, b, flags)
    return surface


def _check_flags(c: Collector, frame: int, lvl: str, flags) -> np.ndarray | None:
    """Only known flag bits; the surface mask from the BACKGROUND bit (None without flags)."""
    if flags is None:
        return None
    fl = flags[..., 0]
    unknown = (fl & np.uint32(~_KNOWN_FLAG_BITS & 0xFFFFFFFF)) != 0
    if unknown.any():
        bits = int(np.bitwise_or.reduce(fl[unknown] & np.uint32(~_KNOWN_FLAG_BITS & 0xFFFFFFFF)))
        c.add("flags-range", f"{int(unknown.sum())} pixel(s) carry unknown flag bits 0x{bits:x}",
                 frame=frame, key=f"{lvl}/flags", pixels=int(unknown.sum()), bits=bits)
    surface = (fl & np.uint32(Flag.BACKGROUND)) == 0
    return surface


def _check_depth(c: Collector, frame: int, lvl: str, depth, surface) -> np.ndarray | None:
    """Depth > 0 on surfaces, +inf exactly on background; the surface mask (from depth when flags gave none)."""
    if depth is None:
        return surface
    d = depth[..., 0]
    nan = np.isnan(d) | (d == -np.inf)
    if nan.any():
        c.add("non-finite", f"{int(nan.sum())} pixel(s) of depth are NaN or -inf", frame=frame,
                 key=f"{lvl}/depth", pixels=int(nan.sum()))
    inf = d == np.inf
    fin = np.isfinite(d)
    if surface is not None:
        bad = inf & surface
        if bad.any():
            c.add("depth-inf-on-surface", f"depth is +inf on {int(bad.sum())} pixel(s) that flags mark "
                                             f"as surface (of {int(surface.sum())})", frame=frame,
                     key=f"{lvl}/depth", pixels=int(bad.sum()))
        bad = fin & ~surface
        if bad.any():
            c.add("depth-finite-on-background",
                     f"depth is finite on {int(bad.sum())} background pixel(s) (max {float(d[bad].max()):.4g}"
                     "; background must be +inf)", frame=frame, key=f"{lvl}/depth", pixels=int(bad.sum()))
    else:
        surface = fin
    bad = fin & (d <= 0)
    if bad.any():
        c.add("depth-range", f"depth <= 0 on {int(bad.sum())} pixel(s) (min {float(d[bad].min()):.4g})",
                 frame=frame, key=f"{lvl}/depth", pixels=int(bad.sum()))
    return surface


def _check_finite_and_radiance(c: Collector, frame: int, lvl: str, name: str, arr, surface) -> None:
    """Finite values; radiance not negative on surfaces; radiance and emission below ``RADIANCE_CAP``."""
    nf = ~np.isfinite(arr)
    if nf.any():
        px = nf.any(axis=-1)
        n_nan = int(np.isnan(arr).any(axis=-1).sum())
        n_inf = int(np.isinf(arr).any(axis=-1).sum())
        c.add("non-finite", f"{int(px.sum())} of {px.size} pixel(s) non-finite ({n_nan} NaN, {n_inf} "
                               "Inf)", frame=frame, key=f"{lvl}/{name}", pixels=int(px.sum()),
                 nan=n_nan, inf=n_inf)
    if name == "radiance" and surface is not None and surface.shape == arr.shape[:2] and surface.any():
        with np.errstate(invalid="ignore"):
            neg = (arr < -NEGATIVE_RADIANCE_TOL).any(axis=-1) & surface
        n_neg, n_surf = int(neg.sum()), int(surface.sum())
        if n_neg > NEGATIVE_RADIANCE_MAX_FRACTION * n_surf:
            c.add("negative-radiance", f"radiance is negative on {n_neg} of {n_surf} surface pixel(s) (min "
                                       f"{float(np.nanmin(arr[neg])):.4g}); light is never negative",
                  frame=frame, key=f"{lvl}/{name}", pixels=n_neg)
    if name in ("radiance", "emission"):
        with np.errstate(invalid="ignore"):
            huge = (np.abs(arr) > RADIANCE_CAP).any(axis=-1)
        if huge.any():
            c.add("implausible-value", f"{int(huge.sum())} pixel(s) with |value| > {RADIANCE_CAP:.0e}, "
                                          f"which no scene produces (max {float(np.nanmax(np.abs(arr[huge]))):.4g}"
                                          "; training treats them as non-finite: data.nonfinite)",
                     frame=frame, key=f"{lvl}/{name}", severity=WARNING, pixels=int(huge.sum()))


def _check_normal(c: Collector, frame: int, lvl: str, normal, surface, flags) -> None:
    """Unit normals on surfaces (ALPHA-flagged pixels apart, as a warning), zero on background."""
    o = c.opt
    length = np.linalg.norm(normal.astype(np.float64), axis=-1)
    surf = surface if surface is not None else length > 0.5
    if flags is not None:
        # Alpha-blended or cut-out surfaces: Cycles writes depth and indices from the first sample and
        # accumulates the normal only over samples whose hit passes the alpha threshold, so a flagged
        # pixel's normal may be short or zero. Counted apart, as a warning.
        alpha = surf & ((flags[..., 0] & np.uint32(Flag.ALPHA)) != 0)
        short = alpha & ~(np.abs(length - 1.0) < o.normal_tol)
        if short.any():
            c.add("non-unit-normal", f"{int(short.sum())} of {int(alpha.sum())} ALPHA-flagged pixel(s) "
                                        "have non-unit normals (partial coverage; excluded from the unit-length check)",
                     frame=frame, key=f"{lvl}/normal", severity=WARNING, pixels=int(short.sum()),
                     alpha_pixels=int(alpha.sum()))
        surf = surf & ~alpha
    n_surf = int(surf.sum())
    if n_surf:
        off = ~(np.abs(length[surf] - 1.0) < o.normal_tol)  # NaN counts as off
        frac_ok = 1.0 - float(off.mean())
        if frac_ok < o.normal_min_fraction:
            c.add("non-unit-normal",
                     f"{fmt_frac(1 - frac_ok)} of {n_surf} surface pixels have | |n| - 1 | >= "
                     f"{o.normal_tol:g} (need <= {fmt_frac(1 - o.normal_min_fraction)}; |n| median "
                     f"{float(np.nanmedian(length[surf])):.4g})", frame=frame, key=f"{lvl}/normal",
                     fraction_off=1 - frac_ok, pixels=int(off.sum()))
    if surface is not None:
        bg = ~surface
        bad = bg & ~(length <= o.background_eps)
        if bad.any():
            c.add("normal-on-background", f"normal is not zero on {int(bad.sum())} of {int(bg.sum())} "
                                             "background pixel(s)", frame=frame, key=f"{lvl}/normal",
                     pixels=int(bad.sum()))


def _check_fbeta(c: Collector, frame: int, lvl: str, fbeta, surface) -> None:
    """fbeta in [0, fbeta_max] on surfaces, 1 on background."""
    o = c.opt
    surf = surface if surface is not None else np.ones(fbeta.shape[:2], bool)
    n_surf = int(surf.sum())
    if n_surf:
        v = fbeta[surf]
        outside = ~((v >= 0.0) & (v <= o.fbeta_max)).all(axis=-1)
        frac = float(outside.mean())
        if frac > 0:
            sev = ERROR if frac > o.fbeta_max_outside else WARNING
            c.add("fbeta-range", f"fbeta outside [0, {o.fbeta_max:g}] on {fmt_frac(frac)} of {n_surf} "
                                    f"surface pixels (range {float(np.nanmin(v)):.4g}.."
                                    f"{float(np.nanmax(v)):.4g}; error above "
                                    f"{fmt_frac(o.fbeta_max_outside)})", frame=frame,
                     key=f"{lvl}/fbeta", severity=sev, fraction=frac, pixels=int(outside.sum()))
    if surface is not None:
        bg = ~surface
        bad = bg & ~(np.abs(fbeta - 1.0) <= o.background_eps).all(axis=-1)
        if bad.any():
            c.add("fbeta-background", f"fbeta is not 1 on {int(bad.sum())} of {int(bg.sum())} background "
                                         "pixel(s)", frame=frame, key=f"{lvl}/fbeta", pixels=int(bad.sum()))


def _check_material_ranges(c: Collector, frame: int, lvl: str, b: dict, flags) -> None:
    """Material buffers in [0, 1] and emission >= 0 (warnings where Cycles' accumulation explains it)."""
    eps = c.opt.range_eps
    for name, lo, hi in (("albedo", 0.0, 1.0), ("roughness", 0.0, 1.0), ("metallic", 0.0, 1.0),
                         ("specular", 0.0, 1.0), ("emission", 0.0, None)):
        arr = b.get(name)
        if arr is None:
            continue
        finite = np.isfinite(arr)
        below = (finite & (arr < lo - eps)).any(axis=-1)
        above = (finite & (arr > hi + eps)).any(axis=-1) if hi is not None else np.zeros_like(below)
        if below.any() or above.any():
            rng = f"[{lo:g}, {hi:g}]" if hi is not None else f">= {lo:g}"
            vals = arr[finite]
            # albedo above 1 can come from an HDR texture driving Base Color: suspicious, not impossible.
            # On ALPHA-flagged pixels Cycles accumulates the material passes (albedo, the roughness/metallic/
            # specular AOVs) over the alpha-blended layers a sample passes, so they may leave the range there.
            out = below | above
            on_alpha = flags is not None and not (out & ((flags[..., 0] & np.uint32(Flag.ALPHA)) == 0)).any()
            sev = WARNING if (name == "albedo" and not below.any()) or on_alpha else ERROR
            where = " (all ALPHA-flagged: accumulated over alpha-blended layers)" if on_alpha else ""
            c.add("value-range", f"{name} outside {rng} on {int(out.sum())} pixel(s) (range "
                                    f"{float(vals.min()):.4g}..{float(vals.max()):.4g}){where}", frame=frame,
                     key=f"{lvl}/{name}", severity=sev, pixels=int(out.sum()))


#: ``check_background_emission``: a background pixel disagrees when |radiance - emission| exceeds this fraction of
#: max(1, |radiance|) in some channel; the check fails when more than ``BG_EMISSION_MAX_FRACTION`` of the checked
#: background pixels do (a pixel whose centre sees the sky but some of whose samples hit thin geometry disagrees
#: legitimately). Not checked: background pixels within ``BG_ALPHA_HALO_PX`` pixels of an ALPHA-flagged surface
#: (bpy's ViewLayer.pass_alpha_threshold, 0.5 by default: "Z, Index, normal, UV and vector passes are only
#: affected by surfaces with alpha transparency equal to or higher than this threshold", so the fringe of an
#: alpha-blended leaf is background in the G-buffer while its light is in the radiance: up to 22% of the background
#: pixels of the medium dataset's GlassVaseFlowers clips, all but at most 3 per frame within 2 px of ALPHA-flagged
#: pixels).
#: Fewer than ``BG_EMISSION_MIN_BAD`` disagreeing pixels never fail (a fraction of a handful says nothing: one
#: thin-geometry pixel among the 8 background pixels of a frame is 12.5%).
BG_EMISSION_TOL = 0.01
BG_EMISSION_MAX_FRACTION = 0.1
BG_ALPHA_HALO_PX = 2
BG_EMISSION_MIN_BAD = 4


def check_background_emission(c: Collector, frame: int, lvl: str, b: dict[str, np.ndarray],
                              surface: np.ndarray | None) -> None:
    """On a point-sampled (LR, not denoised) level of a clip whose ``emission`` holds the environment on background
    (``render.gbuffer.emission_background = "environment"``), radiance - emission, the L_D of those pixels, is 0."""
    rad, em = b.get("radiance"), b.get("emission")
    if rad is None or em is None or surface is None or surface.all():
        return
    bg = ~surface
    flags = b.get("flags")
    if flags is not None:
        bits = flags[..., 0].astype(np.uint32)
        alpha = (bits & np.uint32(Flag.ALPHA)) != 0
        if alpha.any():
            bg = bg & ~dilate(alpha, BG_ALPHA_HALO_PX)
        # the sky seen through glass (gbuffer_transmission "behind": BACKGROUND with TRANSMISSION, the reactive
        # mask): its radiance passed the glass, its emission is the environment itself
        bg = bg & ((bits & np.uint32(Flag.TRANSMISSION)) == 0)
    if not bg.any():
        return
    r, e = rad[bg].astype(np.float64), em[bg].astype(np.float64)
    bad = (np.abs(r - e) > BG_EMISSION_TOL * np.maximum(1.0, np.abs(r))).any(axis=-1)
    frac = float(bad.mean())
    if frac > BG_EMISSION_MAX_FRACTION and int(bad.sum()) >= BG_EMISSION_MIN_BAD:
        c.add("emission-background", f"radiance differs from emission (the environment) on {fmt_frac(frac)} of "
              f"the background pixels (at most {fmt_frac(BG_EMISSION_MAX_FRACTION)} allowed)", frame=frame,
              key=f"{lvl}/emission", pixels=int(bad.sum()))


# ------------------------------------------------------------------------- validate's radiance rule, for readers
class _Findings:
    """What ``Collector.add`` records, without a validation run (for ``radiance_problem``)."""

    def __init__(self):
        self.findings = []

    def add(self, code: str, message: str, *, frame=None, key=None, severity: str = ERROR, **details) -> None:
        from .report import Finding
        self.findings.append(Finding(code, severity, message, frame, key, details))


def surface_mask(flags=None, depth=None) -> np.ndarray | None:
    """The surface pixels as validate sees them: flags without BACKGROUND, else finite positive depth; None when
    neither buffer is given (the negative-radiance rule then cannot apply)."""
    if flags is not None:
        return (flags[..., 0] & np.uint32(Flag.BACKGROUND)) == 0
    if depth is not None:
        d = depth[..., 0]
        with np.errstate(invalid="ignore"):
            return np.isfinite(d) & (d > 0)
    return None


def radiance_problem(frame: int, lvl: str, radiance: np.ndarray, flags=None, depth=None) -> str | None:
    """Validate's radiance errors of one frame and level (``non-finite``; ``negative-radiance`` on surfaces), for
    the readers that do not run validate (training's cache, evaluate): the first one as validate words it,
    ``'frame 2 lr/radiance: radiance is negative on ... [negative-radiance]'``, or None."""
    c = _Findings()
    _check_finite_and_radiance(c, frame, lvl, "radiance", radiance, surface_mask(flags, depth))
    errors = [f for f in c.findings if f.severity == ERROR]
    if not errors:
        return None
    return errors[0].line().split(" ", 1)[1]


def check_clip_radiance(clip, frames=None, levels=None) -> None:
    """Raise ClipError (one line: the file, then validate's words) when a finished frame of ``clip`` (an open
    Clip) has radiance that validate refuses, at ``levels`` (default: every level) and ``frames`` (default: all)."""
    from ..clip import ClipError
    for f in (clip.frames if frames is None else frames):
        for lvl in (levels or clip.levels):
            have = clip.buffers
            problem = radiance_problem(f, lvl, clip.read(f, f"{lvl}/radiance"),
                                       clip.read(f, f"{lvl}/flags") if "flags" in have else None,
                                       clip.read(f, f"{lvl}/depth") if "depth" in have else None)
            if problem:
                raise ClipError(f"{clip.path_of(f, f'{lvl}/radiance')}: {problem} (as 'blendsr validate' reports)")
