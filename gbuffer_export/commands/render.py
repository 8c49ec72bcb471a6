"""``blendsr render``: render a clip from a .blend scene (or the built-in default scene)."""
from __future__ import annotations

import argparse
from pathlib import Path

from ..config import (CLI, ConfigError, RenderConfig, check_builtin_frames, parse_frames, parse_scales, parse_shard,
                      parse_size)
from ..table_shells import add_arguments, values_from_args
from ..typed_table import fields_of
from ..conventions import ALL_BUFFERS, DEFAULT_BUFFERS
from ..extras import HelpFormatter as _HelpFormatter, require
from . import flags_named

HELP = """Render a clip: LR and HR radiance, HR and LR G-buffers, the pre-integrated BRDF (fbeta) and motion vectors
as EXR sequences plus a JSON manifest (docs/clip-format.md).

Units: sizes in pixels; motion in pixels of each level (x right, y down, p_prev = p + motion); depth is view-space
z in scene units (+inf on background); normals are unit vectors in camera space (+X right, +Y up, +Z to the
viewer); radiance is linear scene-referred RGB (float32).

Rerunning the same command resumes: finished frames are skipped. --shard K/N renders every N-th frame starting at
the K-th, so N processes can fill one clip; their manifests merge.

Exports (blendsr export-dataset) check what their consumer loads before writing: a default render (one level at
--scale 4) cannot be exported as NSS or NFRU, which need a 2x level. --for-formats nss (or nfru, rdg) adds what each
format needs (levels, size, buffers)."""


class HelpFormatter(_HelpFormatter):
    """Keeps the description's line breaks and shows each option's default once."""


def add_render_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of ``blendsr render``: one per ``RenderConfig`` key the CLI derives (``table_shells``: type,
    default, choices and help from the field), then those written here (parsed values, light variation)."""
    field = {name: rule for name, (_, rule) in fields_of(RenderConfig).items()}
    p.add_argument("scene", nargs="?", type=Path, default=None,
                   help=field["scene"].help.replace("None:", "omitted:"))
    p.add_argument("-o", "--output", required=True, type=Path, help=field["output"].help)
    p.add_argument("--frames", default=None, metavar="A:B", help=field["frames"].help.replace("None:", "omitted:"))
    p.add_argument("--hr-size", default=None, metavar="WxH", help=field["hr_size"].help.replace("None:", "omitted:"))
    p.add_argument("--scale", type=int, default=4, help="integer upscaling factor; LR = HR / scale")
    p.add_argument("--scales", default=None, metavar="S1,S2,...",
                   help=field["scales"].help.replace("replaces scale", "replaces --scale"))
    add_arguments(p, RenderConfig, CLI)
    p.add_argument("--buffers", default="default",
                   help=f"comma-separated buffers to write, or 'default' ({','.join(DEFAULT_BUFFERS)}) or 'all' "
                        f"({','.join(ALL_BUFFERS)}); radiance is always written")
    p.add_argument("--for-models", default=None, metavar="M1,M2",
                   help="instead of --buffers: only the buffers these models read, plus radiance and motion for "
                        "evaluation (docs/dataset.md)")
    from ..format_limits import names_text, needs_text
    p.add_argument("--for-formats", default=None, metavar="F1,F2",
                   help=f"also render what these export formats ({names_text()}; blendsr export-dataset --format) "
                        f"need, added to --scales, --hr-size and --buffers: {needs_text()}")
    p.add_argument("--world-strength", type=float, default=None, metavar="X",
                   help="multiply the world's background strength by X (recorded in the manifest)")
    p.add_argument("--light-strength", type=float, default=None, metavar="X",
                   help="multiply every lamp's energy by X (recorded in the manifest)")
    p.add_argument("--sun", default=None, metavar="ELEV,AZIM",
                   help="point the sun lamps (and an added sky) from elevation ELEV and azimuth AZIM, in degrees "
                        "(time of day; recorded in the manifest)")
    p.add_argument("--shard", default=None, metavar="K/N", help=field["shard"].help)
    p.add_argument("--allow-read", action="append", default=[], metavar="DIR", help=field["allow_read"].help
                   + "; repeat for more folders")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def variation_from_args(args) -> dict | None:
    """The light variation of ``--world-strength``, ``--light-strength`` and ``--sun`` (the keys of a dataset's
    drawn variation, docs/dataset.md); ConfigError on a bad value."""
    import math
    out = {}
    for key in ("world_strength", "light_strength"):
        v = getattr(args, key, None)
        if v is not None:
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"--{key.replace('_', '-')} {v}: must be a finite number >= 0")
            out[key] = v
    if getattr(args, "sun", None):
        try:
            elev, azim = (float(x) for x in args.sun.split(","))
        except ValueError:
            raise ConfigError(f"--sun {args.sun!r}: expected ELEV,AZIM in degrees, e.g. 35,120") from None
        if not (0 < elev <= 90 and math.isfinite(azim)):
            raise ConfigError(f"--sun {args.sun!r}: elevation must be in (0, 90] degrees")
        out.update(sun_elevation_deg=elev, sun_azimuth_deg=azim % 360.0)
    return out or None


def formats_from_args(args) -> None:
    """``--for-formats``: ``args.scales``, ``args.hr_size`` and ``args.buffers`` with what the formats need
    (``format_limits.render_for_formats``, the derivation the spec key ``for_formats`` uses too)."""
    from ..conventions import parse_buffer_list
    from ..format_limits import render_for_formats
    r = render_for_formats(args.for_formats, scales=parse_scales(args.scales) or (args.scale,),
                           hr_size=parse_size(args.hr_size), buffers=parse_buffer_list(args.buffers))
    args.scales = ",".join(f"{s:g}" for s in r["scales"])
    args.buffers = ",".join(r["buffers"])
    if r["hr_size"] is not None:
        args.hr_size = f"{r['hr_size'][0]}x{r['hr_size'][1]}"


def config_from_args(args) -> RenderConfig:
    variation = variation_from_args(args)
    if args.scene is None:
        check_builtin_frames(parse_frames(args.frames))
    if getattr(args, "for_models", None):
        from ..dataset.buffers import buffers_for_models
        args.buffers = ",".join(buffers_for_models([m for m in args.for_models.split(",") if m.strip()]))
    if getattr(args, "for_formats", None):
        formats_from_args(args)
    return RenderConfig(
        output=args.output, scene=args.scene, frames=parse_frames(args.frames), hr_size=parse_size(args.hr_size),
        scale=args.scale, scales=parse_scales(args.scales), buffers=args.buffers, shard=parse_shard(args.shard),
        progress=not args.no_progress, extra={"variation": variation} if variation else {},
        allow_read=tuple(getattr(args, "allow_read", None) or ()),
        **values_from_args(args, RenderConfig, CLI))


def run(args) -> int:
    require("blendsr render", "render")
    with flags_named(args):  # the library's messages name keys (hr_size); the user typed flags (--hr-size)
        cfg = config_from_args(args)
    if getattr(args, "own_process", False):
        from ..reproducible import prepare_render_process
        prepare_render_process(cfg.threads)  # --threads 1: bit-identical EXRs for the same command
    if cfg.scene is not None:  # refuse what the scene may not read at once, before bpy starts (the import re-checks)
        from ..scene_refs import check_scene_refs
        check_scene_refs(cfg.scene, cfg.allow_read)
    from ..interrupt import check_interrupt, stop_on_sigint
    with stop_on_sigint(), flags_named(args):  # Ctrl-C while bpy starts or Cycles renders: exit 130, not a crash
        from ..blender.render import render_clip  # imports bpy
        check_interrupt()
        out = render_clip(cfg)
    print(f"blendsr: wrote {out}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("render", help="render a training clip from a .blend scene", description=HELP,
                       formatter_class=HelpFormatter)
    add_render_arguments(p)
    p.set_defaults(func=run)
