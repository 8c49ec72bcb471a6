"""``blendsr validate``: check that a clip is complete, readable and consistent with the conventions."""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path
from ..errors import BlendSRError

from ..extras import HelpFormatter as _Formatter

HELP = """Check a clip directory: manifest and frame records, every buffer file of every finished frame at both
levels (exists, readable EXR, level size, channels, sample type), values (finite; depth > 0 on surfaces and +inf
on background; unit normals; fbeta in [0, 1.05] on surfaces and 1 on background; material buffers in [0, 1];
known flag bits), usable views (the HR radiance times the clip's exposure neither practically black, log-average
luminance below 0.02 or over 20% of the pixels below 1e-3, nor blown out, log-average above 2; a warning when fewer
than 75% of the frames hold near and far content, HR depth p90/p10 >= 3; docs/clip-format.md "Usable views") and
motion (agreement with reprojection from depth and cameras on static surface pixels, with the camera's
rotation-only motion on background pixels). A half-written clip (planned frames missing, buffer files of
unfinished frames) never passes, nor does a manifest whose identity is not the hash of its header (an exposure
edited, nulled or deleted) or an HR frame whose depth is finite on less than 0.5% of its pixels (nothing in view).
A validation of every frame records its verdict in the clip (CLIP/validation.json: pass/fail, the manifest's
identity, every file's BLAKE2b-128 hash); train, evaluate, upscale, preview and export-dataset trust a passing
verdict while nothing changed, and otherwise validate the clip themselves (docs/clip-format.md, "Identity and the
recorded verdict").

Prints one line per finding ('ERROR frame 12 hr/normal: ... [code]') and a summary line; with --json one JSON
object (ok, errors, warnings, findings, stats) on stdout. Exit code 0: no errors (warnings allowed); 1: errors;
2: CLIP_DIR is not a directory or an option is invalid."""


def register(subparsers) -> None:
    p = subparsers.add_parser("validate", help="check a clip's completeness, files, values and motion vectors",
                              description=HELP, formatter_class=_Formatter)
    p.add_argument("clip", type=Path, metavar="CLIP_DIR",
                   help="the clip directory (holding manifest.json), or a dataset folder (holding dataset.json: "
                        "every clip is validated and the index checked; one summary line)")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object on stdout")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="check only the records and files of frames A..B (inclusive); default: every finished "
                        "frame. Clip-wide checks (missing frames, stale manifest) always cover the whole clip")
    p.add_argument("--quick", action="store_true",
                   help="value and motion checks on the first and last checked frame only; the others get "
                        "existence, size and channel checks from the EXR headers")
    p.add_argument("--tolerance-px", type=float, default=0.05,
                   help="motion tolerance in pixels of the hr level: stored and reprojected motion agree when "
                        "they differ by at most this")
    p.add_argument("--lr-tolerance-px", type=float, default=None,
                   help="motion tolerance in pixels of the lr level (default: the same number as --tolerance-px)")
    p.add_argument("--min-motion-fraction", type=float, default=0.8,
                   help="least fraction of static surface pixels whose motion must agree (edges may disagree, "
                        "as depth is point-sampled)")
    p.add_argument("--min-background-fraction", type=float, default=0.9,
                   help="least fraction of background pixels that must carry the rotation-only motion")
    p.add_argument("--fbeta-max", type=float, default=1.05, help="upper end of the plausible fbeta range on surfaces")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..config import parse_frames
    from . import flags_named
    from ..validate import ValidationOptions, validate_clip

    if not args.clip.is_dir():
        raise NotADirectoryError(f"{args.clip}: not a directory")
    options = ValidationOptions(motion_tol_px=args.tolerance_px, lr_motion_tol_px=args.lr_tolerance_px,
                                motion_min_fraction=args.min_motion_fraction,
                                background_min_fraction=args.min_background_fraction, fbeta_max=args.fbeta_max)
    if (args.clip / "dataset.json").is_file():
        return run_dataset(args, options)
    frames = None
    if args.frames:
        with flags_named(args):
            a, b = parse_frames(args.frames)
        frames = range(a, b + 1)
    with contextlib.redirect_stdout(sys.stderr):  # stdout holds only the report
        report = validate_clip(args.clip, frames=frames, quick=args.quick, options=options,
                               progress=not args.no_progress)
    if args.json:
        print(json.dumps(report.to_dict(), indent=1, allow_nan=False))
    else:
        for f in report.findings:
            print(f.line())
        print(report.summary_line())
    return 0 if report.ok else 1


def run_dataset(args, options) -> int:
    """Validate every clip of a dataset folder and its index; one line per failing clip and one summary."""
    from ..dataset.check import validate_dataset
    if args.frames:
        raise BlendSRError(f"{args.clip}: --frames applies to one clip, not to a dataset")
    with contextlib.redirect_stdout(sys.stderr):
        report = validate_dataset(args.clip, options=options, quick=args.quick, progress=not args.no_progress)
    if args.json:
        print(json.dumps(report.to_dict(), indent=1, allow_nan=False))
    else:
        for line in report.lines():
            print(line)
        print(report.summary_line())
    return 0 if report.ok else 1
