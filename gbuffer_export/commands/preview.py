"""``blendsr preview DATASET -o SHEET.png``: a contact sheet of a dataset, to see it at a glance."""
from __future__ import annotations

from pathlib import Path
from ..errors import BlendSRError

from ..extras import HelpFormatter

HELP = """Write a contact sheet of a dataset: the HR radiance of every finished clip's first and last frame
(exposed, tonemapped: Reinhard, then sRGB), as many clips side by side as fit 1600 px, each labelled with the
clip's id, camera kind (walk, fly, orbit, scene...), split, frame, HR size and exposure."""


def register(subparsers) -> None:
    p = subparsers.add_parser("preview", help="contact sheet of a dataset's clips (first and last frames)",
                              description=HELP, formatter_class=HelpFormatter)
    p.add_argument("dataset", type=Path, metavar="DATASET", help="dataset folder (holding dataset.json)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="SHEET.png", help="PNG to write")
    p.add_argument("--width", type=int, default=256, help="width of each frame on the sheet, in pixels")
    p.add_argument("--splits", default=None, metavar="S1,S2", help="only these splits (train, val, test)")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..preview import dataset_sheet
    if args.width < 16:
        raise BlendSRError(f"--width {args.width}: must be at least 16 pixels")
    splits = [s.strip() for s in args.splits.split(",")] if args.splits else None
    path, n = dataset_sheet(args.dataset, args.output, args.width, splits)
    print(f"blendsr: wrote {path} ({n} clips)")
    return 0
