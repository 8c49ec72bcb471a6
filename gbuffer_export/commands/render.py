"""``blendsr render``: render a clip from a .blend scene (or the built-in default scene)."""
from __future__ import annotations

import argparse
from pathlib import Path

from ..config import (DEVICES, FBETA_SOURCES, HR_FBETA, JITTERS, LIGHTS, ConfigError, RenderConfig, parse_frames,
                      parse_scales, parse_shard, parse_size)
from ..config import check_builtin_frames
from ..conventions import ALL_BUFFERS, DEFAULT_BUFFERS
from ..extras import HelpFormatter as _HelpFormatter, require
from . import flags_named

HELP = """Render a clip: LR and HR radiance, HR and LR G-buffers, the pre-integrated BRDF (fbeta) and motion vectors
as EXR sequences plus a JSON manifest (docs/clip-format.md).

Units: sizes in pixels; motion in pixels of each level (x right, y down, p_prev = p + motion); depth is view-space
z in scene units (+inf on background); normals are unit vectors in camera space (+X right, +Y up, +Z to the
viewer); radiance is linear scene-referred RGB (float32).

Rerunning the same command resumes: finished frames are skipped. --shard K/N renders every N-th frame starting at
the K-th, so N processes can fill one clip; their manifests merge."""


class HelpFormatter(_HelpFormatter):
    """Keeps the description's line breaks and shows each option's default once."""


def add_render_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", type=Path, default=None,
                   help="the scene: .blend, .gltf/.glb or .usd* (kept as it is: world, lights, materials, animation); "
                        "omitted: the built-in default scene")
    p.add_argument("-o", "--output", required=True, type=Path, help="clip directory to create or resume")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="inclusive frame range; omitted: the scene's range (built-in scene: 1:48, at most 1:1000)")
    p.add_argument("--hr-size", default=None, metavar="WxH",
                   help="HR (target) resolution in pixels; None: the scene's resolution (default scene: 640x360)")
    p.add_argument("--scale", type=int, default=4, help="integer upscaling factor; LR = HR / scale")
    p.add_argument("--scales", default=None, metavar="S1,S2,...",
                   help="several LR levels, one LR render each (numbers >= 1 such as 2,2.5,4, where HR width and "
                        "height divided by each are integers): the first is the level 'lr', the others 'lr_x<s>'; "
                        "replaces --scale")
    p.add_argument("--hr-spp", type=int, default=64, help="samples per pixel of the HR ground truth")
    p.add_argument("--lr-spp", type=int, default=4, help="samples per pixel of the LR render")
    p.add_argument("--gbuffer-spp", type=int, default=4,
                   help="samples per pixel of the HR G-buffer pass (all within 0.01 px of the pixel centre)")
    p.add_argument("--hr-denoise", action=argparse.BooleanOptionalAction, default=False,
                   help="denoise the HR ground truth with OpenImageDenoise")
    p.add_argument("--lr-denoise", action=argparse.BooleanOptionalAction, default=False,
                   help="denoise the LR render with OpenImageDenoise (as a real-time denoiser would)")
    p.add_argument("--adaptive", action=argparse.BooleanOptionalAction, default=False,
                   help="adaptive sampling for the HR ground truth (hr-spp becomes the maximum)")
    p.add_argument("--adaptive-threshold", type=float, default=0.01, help="Cycles' adaptive noise threshold")
    p.add_argument("--adaptive-min-samples", type=int, default=0, help="adaptive minimum samples (0 = automatic)")
    p.add_argument("--camera-path", default="scene", metavar="KIND",
                   help="scene: the file's active camera; scene:NAME: the camera NAME; scene:*: the active camera, "
                        "else the first by name; walk: an eye 1.6 m above the floor walking at 1.4 m/s inside the "
                        "level; fly: a free path at 3 m/s inside the level (both keep 0.25 m from every triangle and "
                        "look at content; docs/rendering.md); orbit: an arc around the scene's bounds (the built-in "
                        "scene's walk is a loop framed from its bounds)")
    p.add_argument("--light", choices=LIGHTS, default=RenderConfig.light,
                   help="auto: the file's own lights where they light what the cameras see (measured by a probe "
                        "render), else a sun and sky where the cameras see the sky and lamps under the ceilings "
                        "where they do not; scene: the file's own lights (an unlit scene is refused); sky: add a "
                        "sun lamp and a physical sky, sun direction drawn from --seed (all recorded in the "
                        "manifest)")
    p.add_argument("--world-strength", type=float, default=None, metavar="X",
                   help="multiply the world's background strength by X (recorded in the manifest)")
    p.add_argument("--light-strength", type=float, default=None, metavar="X",
                   help="multiply every lamp's energy by X (recorded in the manifest)")
    p.add_argument("--sun", default=None, metavar="ELEV,AZIM",
                   help="point the sun lamps (and an added sky) from elevation ELEV and azimuth AZIM, in degrees "
                        "(time of day; recorded in the manifest)")
    p.add_argument("--device", choices=DEVICES, default="auto",
                   help="Cycles device: auto uses a GPU when Cycles sees one (OptiX, CUDA, HIP, Metal, oneAPI), "
                        "else the CPU; the device and its name go into the manifest")
    p.add_argument("--seed", type=int, default=0, help="seed of the default scene, camera paths and Cycles noise")
    p.add_argument("--jitter", choices=JITTERS, default="halton",
                   help="sub-pixel jitter of the LR frames (Halton 2,3, period 16), in LR pixels")
    p.add_argument("--buffers", default="default",
                   help=f"comma-separated buffers to write, or 'default' ({','.join(DEFAULT_BUFFERS)}) or 'all' "
                        f"({','.join(ALL_BUFFERS)}); radiance is always written")
    p.add_argument("--for-models", default=None, metavar="M1,M2",
                   help="instead of --buffers: only the buffers these models read, plus radiance and motion for "
                        "evaluation (docs/dataset.md)")
    p.add_argument("--fbeta", choices=FBETA_SOURCES, default="cycles",
                   help="source of the pre-integrated BRDF: Cycles' colour passes, the split-sum table (lut), "
                        "the papers' literal table (lut-paper), or a model of Cycles' Principled BSDF")
    p.add_argument("--hr-fbeta", choices=HR_FBETA, default=RenderConfig.hr_fbeta,
                   help="HR F_beta of --fbeta cycles: the colour passes filtered like the ground truth (footprint: "
                        "no sub-pixel texture in L_D; the shipped weights' data) or point-sampled like the other "
                        "G-buffers (point: every clip before 2026-11-26)")
    p.add_argument("--max-bounces", type=int, default=None, help="override the scene's total light bounces")
    p.add_argument("--shard", default=None, metavar="K/N", help="render every N-th frame starting with the K-th")
    p.add_argument("--threads", type=int, default=0, help="render threads (0 = all cores)")
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


def config_from_args(args) -> RenderConfig:
    variation = variation_from_args(args)
    if args.scene is None:
        check_builtin_frames(parse_frames(args.frames))
    if getattr(args, "for_models", None):
        from ..dataset.buffers import buffers_for_models
        args.buffers = ",".join(buffers_for_models([m for m in args.for_models.split(",") if m.strip()]))
    return RenderConfig(
        output=args.output, scene=args.scene, frames=parse_frames(args.frames), hr_size=parse_size(args.hr_size),
        scale=args.scale, scales=parse_scales(args.scales), hr_spp=args.hr_spp, lr_spp=args.lr_spp,
        gbuffer_spp=args.gbuffer_spp,
        hr_denoise=args.hr_denoise, lr_denoise=args.lr_denoise, adaptive=args.adaptive,
        adaptive_threshold=args.adaptive_threshold, adaptive_min_samples=args.adaptive_min_samples,
        camera_path=args.camera_path, light=args.light, device=args.device, seed=args.seed, jitter=args.jitter,
        buffers=args.buffers, fbeta=args.fbeta, hr_fbeta=args.hr_fbeta,
        shard=parse_shard(args.shard), max_bounces=args.max_bounces, threads=args.threads,
        progress=not args.no_progress, extra={"variation": variation} if variation else {})


def run(args) -> int:
    require("blendsr render", "render")
    with flags_named(args):  # the library's messages name keys (hr_size); the user typed flags (--hr-size)
        cfg = config_from_args(args)
    if getattr(args, "own_process", False):
        from ..reproducible import prepare_render_process
        prepare_render_process(cfg.threads)  # --threads 1: bit-identical EXRs for the same command
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
