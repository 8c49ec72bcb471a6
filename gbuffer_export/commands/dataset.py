"""``blendsr dataset SPEC.toml -o DATASET``: render every clip of a dataset spec, resumably, on local worker
processes or a Ray cluster."""
from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import BlendSRError
from ..extras import HelpFormatter as _Formatter

HELP = """Render a dataset: many clips from one spec (built-in scene seeds, folders of glTF/GLB/.blend assets in
generated environments), split by scene or asset into train/val/test, indexed in DATASET/dataset.json with each
clip's split, source, seed, licence, settings and state. Rerunning the same command finishes missing or partial
clips only; a run killed at any moment loses at most the frames in flight. The spec's keys and units:
docs/dataset.md; an example: examples/dataset_small.toml.

Executors: 'local' runs --workers clip processes on this machine (each with --threads Cycles threads; default: the
cores divided by the workers). 'ray' submits one task per clip to a Ray cluster (--threads Cycles threads and as
many CPUs per task; default 1, so the cluster renders as many clips at once as it has CPUs; --address: 'auto'
for the cluster this machine belongs to, ray://HOST:10001 for a remote one; none: a local one is started);
DATASET must be on a filesystem every node sees. The same spec gives the same clips on either executor (per-clip
seeds)."""


def register(subparsers) -> None:
    p = subparsers.add_parser("dataset", help="render a dataset of many clips from a spec (resumable, local or Ray)",
                              description=HELP, formatter_class=_Formatter)
    p.add_argument("spec", type=Path, metavar="SPEC.toml", help="dataset spec (TOML)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="DATASET", help="dataset folder")
    p.add_argument("--executor", default="local", choices=("local", "ray"), help="where the clips render")
    p.add_argument("--workers", type=int, default=1, help="clips rendered at once by the local executor")
    p.add_argument("--threads", type=int, default=0,
                   help="Cycles threads per clip; 0: this machine's cores / --workers locally, 1 on Ray (each task "
                        "asks for --threads CPUs, at least 1; Ray runs as many tasks at once as the cluster has CPUs)")
    p.add_argument("--address", default=None, help="Ray cluster address (auto, ray://HOST:10001); none: start one")
    p.add_argument("--for-models", default=None, metavar="M1,M2",
                   help="render only the buffers these models read, plus radiance and motion for evaluation "
                        "(default: the spec's buffers)")
    from ..format_limits import names_text, needs_text
    p.add_argument("--for-formats", default=None, metavar="F1,F2",
                   help=f"render what these export formats ({names_text()}) need, besides the spec's [dataset] "
                        f"for_formats: {needs_text()}")
    p.add_argument("--limit", type=int, default=None, help="render at most N clips in this run")
    p.add_argument("--clips", default=None, metavar="ID,PATTERN|@FILE",
                   help="render only these clips: comma-separated clip ids or shell patterns ('bt_thin-*'), or "
                        "@FILE with one per line ('#' starts a comment), e.g. benchmarks/data_scaling.py "
                        "--list-clips; an entry that names no clip is refused. The index keeps every clip; a later "
                        "run without --clips renders the rest (default: every clip)")
    p.add_argument("--split", default=None, metavar="S1,S2",
                   help="render only the clips of these splits (train, val, test; with --clips: both must hold) "
                        "(default: every split)")
    from ..dataset.build import ORDERS
    p.add_argument("--order", default=ORDERS[0], choices=ORDERS,
                   help="the order clips render in: the spec's (source by source); mixed: a fixed pseudo-random "
                        "order of the clip ids (the same on every run and machine), so that the clips finished at "
                        "any moment are a sample of every source and split, and benchmarks/data_scaling.py's nested "
                        "training subsets, taken in the same order, are rendered smallest first; train-first: the "
                        "train split in the mixed order, then val and test in it (every training subset is finished "
                        "before the evaluation splits, so the largest run can start while they render)")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda", "optix", "hip", "metal", "oneapi"),
                   help="Cycles device of every clip: auto uses a GPU when Cycles sees one, else the CPU "
                        "(recorded in each clip's manifest)")
    p.add_argument("--dry-run", action="store_true",
                   help="print the clips the spec expands to, import every asset file of the asset clips once (as "
                        "their jobs import it), plan every walk and fly clip's camera in its level (import and plan, "
                        "no render: the path it would take, or why it has none and a fix) and exit; 1 when a file "
                        "does not import or a clip has no path")
    p.add_argument("--no-plan", action="store_true",
                   help="with --dry-run: print the clips only, import and plan nothing")
    p.add_argument("--status", action="store_true",
                   help="render nothing: print, per source and split, the clips and frames done and planned, the "
                        "render hours so far and the median seconds per frame (measured from the finished frames' "
                        "records, clip setup excluded), and the hours left at those rates for one worker")
    p.add_argument("--json", action="store_true", help="with --status: the report as one JSON object on stdout")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..dataset.build import RunOptions, build_dataset, summary
    from ..dataset.spec import expand, load_spec, plan_totals

    if args.json and not args.status:
        raise BlendSRError("--json: only with --status (a render reports on stderr and in DATASET/dataset.json)")
    if (args.clips is not None or args.split is not None) and (args.status or args.dry_run):
        raise BlendSRError("--clips/--split: they choose what a render renders (not with --status or --dry-run)")
    spec = load_spec(args.spec, formats=tuple((args.for_formats or "").split(",")) if args.for_formats else ())
    if args.status:
        return _status(args.output, args.json)
    if args.dry_run:
        from ..format_limits import formats_report
        jobs = expand(spec)
        for j in jobs:
            where = (f"scene={Path(j.asset).name} region={j.region['cell'] if j.region else None} light={j.light}"
                     if j.kind == "scene" else f"hdri={Path(j.hdri).name} strength={j.hdri_strength} "
                     f"clutter={[Path(c).stem for c in j.clutter]}")
            print(f"{j.id:40s} {j.split:5s} {j.kind:7s} camera={j.camera:5s} {where} "
                  f"families={','.join(j.families or ())} ({j.family_group})")
        for key, t in sorted(plan_totals(jobs).items(), key=lambda kv: (kv[0] != "all", kv[0])):
            print(f"total {key}: {t['clips']} clips, {t['frames']} frames, {t['hr_pixels'] / 1e6:.1f} M HR pixels")
        for line in formats_report(j.render for j in jobs):  # what blendsr export-dataset will take
            print(line)
        return _dry_run_plan(jobs, args.no_plan)
    from ..extras import require
    require("blendsr dataset", "render", *(("cluster",) if args.executor == "ray" else ()))
    opts = RunOptions(executor=args.executor, workers=args.workers, threads=args.threads, address=args.address,
                      buffers_for=_names(args.for_models), progress=not args.no_progress, limit=args.limit,
                      device=args.device, order=args.order, clips=_clip_selection(args.clips),
                      splits=_names(args.split, "--split"))
    index = build_dataset(spec, args.output, opts)
    print(f"blendsr: {args.output}: {summary(index)}")
    mine = _selected_ids(spec, opts)  # a selective run reports (and exits 1 for) its own clips only
    failed = [c for c in index["clips"] if c["state"] == "failed" and c["id"] in mine]
    for c in failed:
        print(f"FAILED {c['id']}: {c.get('error', '')} (log: {args.output / 'logs' / (c['id'] + '.log')})")
    invalid = [c for c in index["clips"] if c.get("invalid") and c["id"] in mine]
    for c in invalid:  # rendered to the end, but blendsr validate refuses it (checked as each clip finished)
        print(f"INVALID {c['id']}: {c['invalid']} (blendsr validate {args.output / 'clips' / c['id']})")
    return 1 if failed or invalid else 0


def _names(text: str | None, option: str = "") -> tuple[str, ...]:
    """A comma-separated option as its non-empty entries (None: not given, ()). With ``option``, a value given but
    empty (``--split ''``, an empty shell variable) is a BlendSRError: it would otherwise mean "all"."""
    names = tuple(t.strip() for t in (text or "").split(",") if t.strip())
    if option and text is not None and not names:
        raise BlendSRError(f"{option} {text!r}: names nothing (comma-separated names)")
    return names


def _clip_selection(text: str | None) -> tuple[str, ...]:
    """--clips: its comma-separated entries, or with @FILE the file's lines (UTF-8 or, by its byte-order mark,
    UTF-16 as Windows PowerShell's '>' writes it; blank lines and '#' comments skipped). BlendSRError naming a file
    that cannot be read or a value or file that holds no entry."""
    if text is None or not text.startswith("@"):
        return _names(text, "--clips")
    path = Path(text[1:])
    try:
        raw = path.read_bytes()
        lines = raw.decode("utf-16" if raw[:2] in (b"\xff\xfe", b"\xfe\xff") else "utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise BlendSRError(f"--clips {text}: cannot read {path} ({exc.__class__.__name__}: {exc})") from None
    entries = tuple(e for e in (ln.split("#", 1)[0].strip() for ln in lines) if e)
    if not entries:
        raise BlendSRError(f"--clips {text}: {path} names no clip (one id or shell pattern per line)")
    return entries


def _selected_ids(spec, opts) -> set[str]:
    """The ids of the clips a run with ``opts`` chose (every clip without --clips or --split)."""
    from ..dataset.build import planned_jobs, selected_jobs
    return {j.id for j in selected_jobs(planned_jobs(spec, opts), opts)}


def _status(root: Path, as_json: bool) -> int:
    import json
    from ..dataset.cost import dataset_status, status_lines
    report = dataset_status(root)
    print(json.dumps(report, indent=1) if as_json else "\n".join(status_lines(report)))
    return 0


def _dry_run_assets(files: list[str]) -> int:
    """Import each asset file once (``dry_run.check_assets``, each in a child process), one line each as it is known
    and a total; the number that fail."""
    if not files:
        return 0
    from ..blender.dry_run import check_assets, describe_asset
    checks = check_assets(files, report=lambda rec: print(describe_asset(rec), flush=True))
    bad = sum(not r["ok"] for r in checks)
    print(f"blendsr: imported {len(checks)} asset files: {len(checks) - bad} import, {bad} do not")
    return bad


def _dry_run_plan(jobs, skip: bool) -> int:
    """Import every asset file of ``jobs`` once and plan their walk and fly clips (``gbuffer_export.blender.dry_run``),
    one line each; 1 when a file does not import or a clip has no path."""
    import logging
    from ..blender.dry_run import asset_files, plannable  # no bpy until a function below runs
    files, todo = asset_files(jobs), [j for j in jobs if plannable(j)]
    if skip or not (files or todo):
        return 0
    from ..extras import require
    try:
        require("blendsr dataset --dry-run's planner", "render")
    except BlendSRError as exc:
        logging.getLogger(__name__).warning("blendsr: %s; the %d asset files are not imported and the %d walk/fly "
                                            "clips not planned", exc, len(files), len(todo))
        return 0
    from ..blender.dry_run import describe, plan_jobs
    bad_files = _dry_run_assets(files)
    recs = plan_jobs(todo)
    for rec in recs:
        if not rec["ok"] and "orbit" in rec["fix"]:  # a single object: walk and fly cannot be planned on it
            logging.getLogger(__name__).warning("blendsr: %s: %s", rec["scene"], rec["fix"])
        print(describe(rec))
    bad = sum(not r["ok"] for r in recs)
    if recs:
        print(f"blendsr: planned {len(recs)} walk/fly clips: {len(recs) - bad} have a path, {bad} none")
    return 1 if bad or bad_files else 0
