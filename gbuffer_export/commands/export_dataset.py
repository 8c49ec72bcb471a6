"""``blendsr export-dataset``: write BlendSR clips in another project's dataset layout (Arm's NSS capture layout);
``blendsr import-nss``: read an NSS capture sequence into a BlendSR clip. Conversions: gbuffer_export/formats."""
from __future__ import annotations

import sys
from pathlib import Path

from ..extras import HelpFormatter

FORMATS = ("nss", "rdg")

HELP = """Write BlendSR clips (or every finished clip of a dataset folder) as Arm's NSS capture layout
(neural-graphics-model-gym's docs/nss/nss_dataset_specification.md): one sequence per clip (0000.json, ...),
ground_truth/ and motion_gt/ at HR, x<ratio>/color, depth, motion for every LR level. Colour becomes linear
Rec.709 half RGBA, depth forward-Z device depth with the sequence's near/far planes, motion UV units (current -
previous). --format rdg writes the layout of the RDG authors' loader (basicsr/data/render_dataset.py): GT/ and
LR/<scene>/{Image,Normal,BRDF,Depth,Motion,Emit}/000.{png,exr} and its meta-info files. See docs/formats.md for
every mapping and what is lost."""


def register(subparsers) -> None:
    p = subparsers.add_parser("export-dataset", help="write clips as another trainer's dataset layout (NSS, RDG)",
                              description=HELP, formatter_class=HelpFormatter)
    p.add_argument("sources", nargs="+", type=Path, metavar="DATASET_OR_CLIP",
                   help="clip folders and/or dataset folders (holding dataset.json)")
    p.add_argument("--format", choices=FORMATS, required=True, help="the layout to write")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    p.add_argument("--framerate", type=int, default=24,
                   help="EmulatedFramerate to record (BlendSR clips do not store one; Blender's default is 24)")
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
    from ..formats.rdg import export_rdg
    report = lambda c, j: print(f"blendsr: {c} -> {j}", file=sys.stderr)
    if args.format == "rdg":
        scenes = export_rdg(args.sources, args.output, progress=report)
        print(f"blendsr: wrote {len(scenes)} RDG scene(s) to {args.output}")
        return 0
    paths = export_nss(args.sources, args.output, framerate=args.framerate, progress=report)
    print(f"blendsr: wrote {len(paths)} NSS sequence(s) to {args.output}")
    return 0


def run_import(args) -> int:
    from ..formats.nss import nss_to_clip
    out = nss_to_clip(args.capture, args.sequence, args.output)
    print(f"blendsr: wrote {out}")
    return 0
