"""``blendsr preview DATASET -o SHEET.png``: a contact sheet of a dataset, to see it at a glance."""
from __future__ import annotations

from pathlib import Path
from ..errors import BlendSRError

from ..extras import HelpFormatter

HELP = """Write a contact sheet of a dataset: the HR radiance of every finished clip's first and last frame
(exposed, tonemapped: Reinhard, then sRGB), as many clips side by side as fit 1600 px, each labelled with the
clip's id, camera kind (walk, fly, orbit, scene...), split, frame, HR size and exposure."""

#: Bytes the sheet holds per pixel of its tiles while it is composed: float64 RGB tiles, the 8-bit canvas and its
#: float64 copy (``preview.dataset_sheet``, ``labelled_grid``).
SHEET_BYTES_PER_PIXEL = 3 * 8 + 3 + 3 * 8


def register(subparsers) -> None:
    p = subparsers.add_parser("preview", help="contact sheet of a dataset's clips (first and last frames)",
                              description=HELP, formatter_class=HelpFormatter)
    p.add_argument("dataset", type=Path, metavar="DATASET", help="dataset folder (holding dataset.json)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="SHEET.png", help="PNG to write")
    p.add_argument("--width", type=int, default=256, help="width of each frame on the sheet, in pixels")
    p.add_argument("--splits", default=None, metavar="S1,S2", help="only these splits (train, val, test)")
    p.set_defaults(func=run)


def parse_splits(text: str | None) -> list[str] | None:
    """``--splits`` as a list of known split names (None: every split); BlendSRError naming an unknown one."""
    from ..dataset.spec import SPLITS
    if text is None:
        return None
    splits = [s.strip() for s in text.split(",") if s.strip()]
    unknown = [s for s in splits if s not in SPLITS]
    if unknown or not splits:
        raise BlendSRError(f"--splits {text}: {'unknown split ' + repr(unknown[0]) if unknown else 'no split'}; "
                           f"choose among {', '.join(SPLITS)}")
    return splits


def sheet_bytes(index: dict, width: int, splits: list[str] | None) -> int:
    """Memory the sheet of ``index``'s clips (of ``splits``) takes at ``width`` pixels a frame: two frames a clip,
    each as tall as its HR aspect makes it (square when the index does not say)."""
    total = 0
    for c in index["clips"]:
        if splits and c.get("split") not in splits:
            continue
        size = (c.get("render") or {}).get("hr_size") if isinstance(c.get("render"), dict) else None
        ok = isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)
        h = max(1, round(width * size[1] / size[0])) if ok else width
        total += 2 * width * h
    return total * SHEET_BYTES_PER_PIXEL


def run(args) -> int:
    from ..dataset.build import read_index
    from ..preview import dataset_sheet
    from ..resources import check_memory
    if args.width < 16:
        raise BlendSRError(f"--width {args.width}: must be at least 16 pixels")
    splits = parse_splits(args.splits)
    check_memory(sheet_bytes(read_index(args.dataset), args.width, splits), f"--width {args.width}: the sheet",
                 "lower --width or choose fewer --splits")
    path, n = dataset_sheet(args.dataset, args.output, args.width, splits)
    print(f"blendsr: wrote {path} ({n} clips)")
    return 0
