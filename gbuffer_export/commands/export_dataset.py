"""``blendsr export-dataset``: write BlendSR clips in another project's dataset layout (Arm's NSS capture layout);
``blendsr import-nss``: read an NSS capture sequence into a BlendSR clip. Conversions: gbuffer_export/formats."""
from __future__ import annotations

import sys
from pathlib import Path

from ..extras import HelpFormatter
from ..format_limits import FORMATS as FORMATS_NEEDS, NAMES as FORMATS, needs_text

HELP = """Write BlendSR clips (or every finished clip of a dataset folder) as Arm's NSS capture layout
(neural-graphics-model-gym's docs/nss/nss_dataset_specification.md): one sequence per clip (0000.json, ...),
ground_truth/ and motion_gt/ at HR, x<ratio>/color, depth, motion for every LR level. Colour becomes linear
Rec.709 half RGBA, depth forward-Z device depth with the sequence's near/far planes, motion UV units (current -
previous). --format rdg writes the layout of the RDG authors' loader (basicsr/data/render_dataset.py): GT/ and
LR/<scene>/{Image,Normal,BRDF,Depth,Motion,Emit}/000.{png,exr} and its meta-info files. --format nfru writes Arm's
frame-rate upscaling layout (docs/nfru/nfru_dataset_specification.md): ground_truth/, x2/depth, x2/motion_m1 and,
on even frames, x2/motion_m2 (motion two frames back), with the camera basis per frame. See docs/formats.md for
every mapping and what is lost.

The output folder must be new or empty, unless --overwrite (the export replaces it whole: written beside it, then
swapped in) or --append (sequences or scenes are added after the ones it holds). A clip with missing frames becomes
one sequence (or scene) per contiguous run of frames, each starting with a camera cut.

What each format's consumer loads is checked before anything is written (a clip that breaks a limit is refused in
one line naming the fix). What a clip needs for each (render it with --for-formats FORMAT):
""" + "\n".join(f"  {n}: {FORMATS_NEEDS[n].needs()}" for n in FORMATS)


def positive_int(text: str) -> int:
    """argparse type: a whole number in 1..1000 (one line naming the flag on anything else, exit 2)."""
    import argparse
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if not 0 < v <= 1000:
        raise argparse.ArgumentTypeError(f"{v} must be in 1..1000 (frames per second)")
    return v


def register(subparsers) -> None:
    p = subparsers.add_parser("export-dataset", help="write clips as another trainer's dataset layout "
                                                     f"({', '.join(FORMATS)})",
                              description=HELP, formatter_class=HelpFormatter)
    p.add_argument("sources", nargs="+", type=Path, metavar="DATASET_OR_CLIP",
                   help="clip folders and/or dataset folders (holding dataset.json)")
    p.add_argument("--format", choices=FORMATS, required=True,
                   help="the layout to write (" + needs_text() + ")")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    p.add_argument("--framerate", type=positive_int, default=24,
                   help="EmulatedFramerate to record, frames per second in 1..1000 (BlendSR clips do not store "
                        "one; Blender's default is 24)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--overwrite", action="store_true",
                      help="replace a non-empty output folder whole (the new export is written beside it, then "
                           "swapped in)")
    mode.add_argument("--append", action="store_true",
                      help="add to the export in the output folder (sequences or scenes numbered after its own)")
    p.set_defaults(func=run_export)

    q = subparsers.add_parser("import-nss", help="read one NSS capture sequence into a BlendSR clip",
                              description="Write sequence SEQ of an NSS capture folder as a BlendSR clip (buffers "
                                          "radiance, depth, motion; hr/depth is upsampled from the first LR level, "
                                          "NSS has none). See docs/formats.md.",
                              formatter_class=HelpFormatter)
    q.add_argument("capture", type=Path, metavar="NSS_DIR")
    q.add_argument("--sequence", default="0000", help="sequence name (its JSON file's stem)")
    q.add_argument("-o", "--output", type=Path, required=True, help="the clip folder to write")
    q.set_defaults(func=run_import)


def run_export(args) -> int:
    """Bad input (a missing clip, an unfinished one, an output folder in use) raises a BlendSRError: one line, exit
    code 2 at the CLI's error boundary."""
    from ..formats.nss import export_nss
    from ..formats.output import ExportOptions
    from ..formats.rdg import export_rdg
    report = lambda c, j: print(f"blendsr: {c} -> {j}", file=sys.stderr)
    opts = ExportOptions(mode="overwrite" if args.overwrite else "append" if args.append else "new",
                         framerate=args.framerate, progress=report)
    if args.format == "rdg":
        scenes = export_rdg(args.sources, args.output, opts)
        print(f"blendsr: wrote {len(scenes)} RDG scene(s) to {args.output}")
        return 0
    if args.format == "nfru":
        from ..formats.nfru import export_nfru
        paths = export_nfru(args.sources, args.output, opts)
    else:
        paths = export_nss(args.sources, args.output, opts)
    print(f"blendsr: wrote {len(paths)} {args.format.upper()} sequence(s) to {args.output}")
    return 0


def run_import(args) -> int:
    from ..formats.nss import nss_to_clip
    out = nss_to_clip(args.capture, args.sequence, args.output)
    print(f"blendsr: wrote {out}")
    return 0
