"""Checks that a clip's views are usable data, as its readers see them (docs/clip-format.md, "Usable views"):

- the manifest's ``exposure`` is well formed and, for an auto exposure, the one its frames' metering gives
  (``exposure-invalid``);
- each checked HR frame, exposed (radiance times the clip's exposure, ``conventions.expose``), is neither practically
  black nor blown out (``dark-frame``, ``bright-frame``: errors), and its radiance is still the radiance its record's
  metering was taken from (``metering-mismatch``: radiance changed after rendering);
- enough checked frames hold near and far content: HR depth p90/p10, background counted as infinitely far
  (``flat-view``: a warning for the clip).

The rule is one: the data a reader gets is the stored (physical) radiance times the manifest's exposure, and that is
what is checked. An auto exposure brings a dim render up (up to ``conventions.EXPOSURE_LIMITS``), so a level lit in
other units passes; a clip whose radiance was scaled after rendering keeps the exposure metered for the original and
fails (and its metering no longer matches)."""
from __future__ import annotations

import math

import numpy as np

from ..conventions import exposure_of, frame_luminance, luminance, luminance_stats, metered_exposure
from ..errors import BlendSRError
from .report import WARNING, Collector, fmt_frac

#: ``dark-frame``: an exposed HR frame whose log-average luminance (over its lit pixels) is below DARK_LOG_AVERAGE,
#: or whose pixels are darker than DARK_LUMINANCE on more than DARK_MAX_FRACTION of the frame, is practically black.
DARK_LOG_AVERAGE = 0.02
DARK_LUMINANCE = 1e-3
DARK_MAX_FRACTION = 0.2
#: ``bright-frame``: an exposed HR frame whose log-average luminance is above this is blown out (most of it would
#: show as white).
BRIGHT_LOG_AVERAGE = 2.0
#: ``flat-view``: a frame holds near and far content when its HR depth p90/p10 (background = infinitely far) is at
#: least NEAR_FAR_RATIO; the clip gets a warning when fewer than NEAR_FAR_MIN_FRACTION of its checked frames do.
NEAR_FAR_RATIO = 3.0
NEAR_FAR_MIN_FRACTION = 0.75
#: ``metering-mismatch``: the HR radiance's mean log luminance differs from its record's metering by more than this
#: (float rounding gives < 1e-6; a radiance scaled by k moves it by ln k).
METERING_TOL = 1e-3


def check_exposure(c: Collector, manifest: dict) -> float:
    """The clip's exposure (``conventions.exposure_of``; 1 after an ``exposure-invalid`` finding)."""
    try:
        value = exposure_of(manifest)
    except BlendSRError as exc:
        c.add("exposure-invalid", f"manifest {exc}", key="exposure")
        return 1.0
    block = manifest.get("exposure")
    if isinstance(block, dict) and block.get("mode") == "auto" and isinstance(manifest.get("frame_data"), dict):
        expect = metered_exposure(block, manifest["frame_data"])
        if not math.isclose(expect["value"], value, rel_tol=1e-6):
            c.add("exposure-invalid", f"manifest exposure.value {value:.6g} is not the auto exposure its frames' "
                  f"metering gives ({expect['value']:.6g}; manifest not merged after the last frame?)",
                  key="exposure", expected=expect["value"])
    c.stats["exposure"] = {"value": value, "mode": block.get("mode") if isinstance(block, dict) else None}
    return value


def check_exposed_frame(c: Collector, frame: int, b: dict[str, np.ndarray], exposure: float, manifest: dict,
                        record: dict | None) -> None:
    """``dark-frame``, ``bright-frame`` and ``metering-mismatch`` of one HR frame; its statistics into the stats."""
    rad = b.get("radiance")
    if rad is None or rad.size == 0:
        return
    scene_linear = str(manifest.get("scene_linear", "Linear Rec.709"))
    stats = luminance_stats(rad, scene_linear)
    if not stats["lit_pixels"]:
        return  # no light at all: black-frame says so
    lum = luminance(rad, scene_linear) * exposure
    with np.errstate(invalid="ignore"):
        dark = float(np.mean(~(lum >= DARK_LUMINANCE)))  # NaN counts as dark
    log_avg = math.exp(stats["log_mean"]) * exposure
    per = c.stats.setdefault("exposed_frames", {})
    per[str(frame)] = {"log_average": log_avg, "dark_fraction": dark}
    where = f"exposed HR radiance (exposure {exposure:.4g})"
    if log_avg < DARK_LOG_AVERAGE or dark > DARK_MAX_FRACTION:
        c.add("dark-frame", f"{where} is practically black: log-average luminance {log_avg:.3g} (at least "
              f"{DARK_LOG_AVERAGE:g} needed), {fmt_frac(dark)} of the pixels below {DARK_LUMINANCE:g} (at most "
              f"{fmt_frac(DARK_MAX_FRACTION)} allowed); is the scene lit as the cameras see it?", frame=frame,
              key="hr/radiance", log_average=log_avg, dark_fraction=dark)
    elif log_avg > BRIGHT_LOG_AVERAGE:
        c.add("bright-frame", f"{where} is blown out: log-average luminance {log_avg:.3g} (at most "
              f"{BRIGHT_LOG_AVERAGE:g} allowed)", frame=frame, key="hr/radiance", log_average=log_avg)
    metered = frame_luminance(record) if record is not None else None
    if metered is not None and isinstance(metered.get("log_mean"), (int, float)):
        diff = stats["log_mean"] - float(metered["log_mean"])
        if not abs(diff) <= METERING_TOL:
            c.add("metering-mismatch", f"the HR radiance is {math.exp(diff):.3g} times the radiance its exposure "
                  "was metered on (the record's hr.luminance): changed after rendering", frame=frame,
                  key="hr/radiance", ratio=math.exp(diff))


def depth_ratio(b: dict[str, np.ndarray]) -> float | None:
    """HR depth p90/p10 of one frame, background (non-finite depth) counted as infinitely far; inf when the far
    decile is background, None when the frame has no depth or no surface."""
    depth = b.get("depth")
    if depth is None or depth.size == 0:
        return None
    d = depth[..., 0].astype(np.float64)
    d = np.where(np.isfinite(d) & (d > 0), d, np.inf)
    p10, p90 = np.quantile(d, [0.1, 0.9], method="nearest")
    if not math.isfinite(p10):
        return None  # (almost) all background: camera-view and the light checks speak for it
    return float(p90 / p10)


def check_flat_views(c: Collector, ratios: dict[int, float]) -> None:
    """``flat-view`` (warning) when fewer than NEAR_FAR_MIN_FRACTION of the checked frames hold near and far
    content."""
    if not ratios:
        return
    near_far = sum(r >= NEAR_FAR_RATIO for r in ratios.values())
    share = near_far / len(ratios)
    c.stats["near_far_fraction"] = share
    if share < NEAR_FAR_MIN_FRACTION:
        worst = min(ratios, key=ratios.get)
        c.add("flat-view", f"{len(ratios) - near_far} of {len(ratios)} checked frames show content at about one "
              f"depth (HR depth p90/p10 below {NEAR_FAR_RATIO:g}; lowest {ratios[worst]:.3g} at frame {worst}); at "
              f"least {fmt_frac(NEAR_FAR_MIN_FRACTION)} should show near and far content", key="hr/depth",
              severity=WARNING, near_far_fraction=share)
