"""``blendsr validate DATASET``: every clip of a dataset validated, plus the index's own invariants (pure numpy).

Index checks: every clip listed exists and is finished; no scene or asset id lies in two splits; no clip's clutter
comes from an asset of another split (a test asset never appears in a training clip); every clip records a licence;
a level split into regions gives each split its own cells and every clip a cell of its split (each clip's own
validation then checks that its camera stays in that cell), and every clip of one level (a scene file's stem: the
spec gives all of them one layout) lays its grid over the same box, so a cell is one place in every file of the level
(a level exported in other coordinates, such as a GLB turned against its .blend, would put a test cell of one file on
a training place of the other).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..clip import ClipError
from ..errors import BlendSRError
from .build import clip_dir, clip_state, read_index


@dataclass
class DatasetReport:
    path: str
    clips: dict = field(default_factory=dict)      # id -> {"ok", "errors", "warnings", "first_error"}
    index_errors: list = field(default_factory=list)
    sources: dict = field(default_factory=dict)    # source -> {"clips", "usable", "share", "reasons": {id: why}}

    @property
    def ok(self) -> bool:
        return (not self.index_errors and all(c["ok"] for c in self.clips.values())
                and all(s["usable"] for s in self.sources.values()))

    def lines(self) -> list[str]:
        out = [f"ERROR dataset: {e}" for e in self.index_errors]
        for cid, c in self.clips.items():
            if not c["ok"]:
                out.append(f"ERROR {cid}: {c['errors']} errors, first: {c['first_error']}")
        for name, s in self.sources.items():
            out.append(f"source {name}: {s['usable']}/{s['clips']} clips usable ({100 * s['share']:.0f}%)")
        dropped = {n: s for n, s in self.sources.items() if not s["usable"]}
        if dropped:
            out.append(f"ERROR dataset: {len(dropped)} source(s) without a usable clip: "
                       f"{', '.join(dropped)} (each clip's reason below)")
            rows = [(n, cid, why) for n, s in dropped.items() for cid, why in s["reasons"].items()]
            w0, w1 = max(len("source"), *(len(r[0]) for r in rows)), max(len("clip"), *(len(r[1]) for r in rows))
            out.append(f"  {'source':{w0}s}  {'clip':{w1}s}  reason")
            out += [f"  {n:{w0}s}  {cid:{w1}s}  {why}" for n, cid, why in rows]
        return out

    def summary_line(self) -> str:
        n_ok = sum(c["ok"] for c in self.clips.values())
        warn = sum(c["warnings"] for c in self.clips.values())
        verdict = "OK" if self.ok else "FAILED"
        return (f"{verdict}: {self.path}: {n_ok}/{len(self.clips)} clips valid, {warn} warnings, "
                f"{len(self.index_errors)} index errors")

    def to_dict(self) -> dict:
        return {"path": self.path, "ok": self.ok, "clips": self.clips, "index_errors": self.index_errors,
                "sources": self.sources}


def region_errors(index: dict, root: Path | None = None) -> list[str]:
    """Split regions of ``kind = "scene"`` clips: per scene file, the cells of different splits are disjoint, the
    same for every clip, each clip's cell is one of its split's, and the cells its camera was allowed (its
    manifest's ``camera.region``) are its split's."""
    errs = []
    layout: dict[str, dict] = {}
    boxes: dict[str, tuple] = {}
    for c in index["clips"]:
        reg = c.get("region")
        if c.get("kind") != "scene" or not reg:
            continue
        cells = {k: {tuple(x) for x in v} for k, v in (reg.get("cells") or {}).items()}
        key = str(c.get("asset"))
        if layout.setdefault(key, {"grid": reg.get("grid"), "cells": cells}) != {"grid": reg.get("grid"),
                                                                                 "cells": cells}:
            errs.append(f"clip {c['id']}: its scene's split regions differ from another clip's of {Path(key).name}")
        splits = sorted(cells)
        for i, a in enumerate(splits):
            for b in splits[i + 1:]:
                if cells[a] & cells[b]:
                    errs.append(f"clip {c['id']}: regions {sorted(cells[a] & cells[b])} are in both {a} and {b}")
        if tuple(reg.get("cell") or ()) not in cells.get(c["split"], set()):
            errs.append(f"clip {c['id']} ({c['split']}) stands in cell {reg.get('cell')}, not a {c['split']} region")
        region = _manifest_region(root, c) if root is not None else None
        if region is None:
            continue
        used = {tuple(x) for x in region["cells"]}
        if not used <= cells.get(c["split"], set()):
            errs.append(f"clip {c['id']} ({c['split']}): its camera used cells {sorted(used)} outside its split's")
        err = _box_error(c, region, boxes)
        if err:
            errs.append(err)
    return sorted(set(errs))


#: Two clips of one level lay their grid over the same box when its corners agree within this share of its size.
BOX_TOLERANCE = 1e-3


def _box_error(entry: dict, region: dict, boxes: dict) -> str | None:
    """An error when ``entry``'s grid box (its manifest's ``camera.region`` lo/hi) differs from the first box seen
    for its level (the stem of its scene id); None otherwise or when the manifest has no box."""
    import numpy as np
    if region.get("lo") is None or region.get("hi") is None:
        return None
    stem = str(entry.get("scene_id") or Path(str(entry.get("asset"))).stem).split("@")[0]
    lo, hi = np.asarray(region["lo"], float), np.asarray(region["hi"], float)
    first_id, lo0, hi0 = boxes.setdefault(stem, (entry["id"], lo, hi))
    tol = BOX_TOLERANCE * max(float(np.max(hi0 - lo0)), 1e-9)
    if lo.shape == lo0.shape and np.all(np.abs(lo - lo0) <= tol) and np.all(np.abs(hi - hi0) <= tol):
        return None
    fmt = lambda v: "(" + ", ".join(f"{x:.3g}" for x in v) + ")"  # noqa: E731
    return (f"clip {entry['id']}: the regions of level {stem!r} lie over the box {fmt(lo)}..{fmt(hi)}, "
            f"clip {first_id}'s over {fmt(lo0)}..{fmt(hi0)}: its file is in other coordinates, so a cell is another place in it (leave "
            "the file out of the spec, or export it in the coordinates of the level's other files)")


def _manifest_region(root: Path, entry: dict) -> dict | None:
    """The clip manifest's ``camera.region`` (the cells its camera was allowed, the grid's box); None when the
    clip's path breaks the index path rule (``clip_dir``: reported by ``index_errors``, its manifest never opened)
    or its manifest has none."""
    from ..clip import load_manifest
    try:
        reg = load_manifest(clip_dir(root, entry))["camera"]["region"]
        return reg if isinstance(reg, dict) and isinstance(reg.get("cells"), list) else None
    except (OSError, ValueError, KeyError, TypeError):  # ClipError and DatasetError are ValueErrors
        return None


def split_leaks(root: Path, index: dict) -> list[str]:
    """What puts one scene, asset or region into two splits (a split leak): the index checks that ``train`` and
    ``evaluate`` also run on a dataset folder, in the words ``validate`` reports them."""
    errs = region_errors(index, root)
    split_of: dict[str, str] = {}
    asset_split: dict[str, str] = {}
    for c in index["clips"]:
        sid = c.get("scene_id")  # None: no scene recorded (a hand-made index), nothing to compare
        if sid is not None and split_of.setdefault(sid, c["split"]) != c["split"]:
            errs.append(f"scene {sid!r} is in both the {split_of[sid]} and the {c['split']} split")
        if c.get("asset"):
            asset_split.setdefault(Path(c["asset"]).stem, c["split"])
    for c in index["clips"]:
        for cl in c.get("clutter", []):
            s = asset_split.get(Path(cl).stem)
            if s is not None and s != c["split"]:
                errs.append(f"clip {c['id']} ({c['split']}) uses {Path(cl).stem} of the {s} split as clutter")
    return errs


def index_errors(root: Path, index: dict) -> list[str]:
    errs = split_leaks(root, index)
    for c in index["clips"]:
        if not c.get("licence", {}).get("licence"):
            errs.append(f"clip {c['id']}: no licence recorded")
        try:
            path = clip_dir(root, c)
        except ClipError as exc:  # a path outside the dataset: reported, never read
            errs.append(str(exc))
            continue
        state, _ = clip_state(path, int(c.get("frames_planned", 0)))
        if state != "done" and (c.get("state") == "failed" or c.get("error")):
            err = str(c.get("error") or "").strip().splitlines()
            errs.append(f"clip {c['id']} failed{': ' + err[-1] if err else ''} (fix it and rerun 'blendsr dataset')")
        elif state != "done":
            errs.append(f"clip {c['id']} is {state} (rerun 'blendsr dataset' to finish it)")
    if not index["clips"]:
        errs.append("the index lists no clips (nothing to train or evaluate on)")
    return errs


def validate_dataset(root, options=None, quick: bool = False, progress: bool = True) -> DatasetReport:
    """Validate every finished clip of the dataset at ``root`` and the index's invariants."""
    from ..validate import validate_clip
    root = Path(root)
    index = read_index(root)
    rep = DatasetReport(str(root), index_errors=index_errors(root, index))
    clips = []
    for c in index["clips"]:
        try:
            path = clip_dir(root, c)
        except ClipError:
            continue  # an index error (index_errors)
        if (path / "manifest.json").is_file():
            clips.append((c, path))
    it = clips
    if progress:
        from tqdm import tqdm
        import sys
        it = tqdm(clips, desc="validate", unit="clip", file=sys.stderr, dynamic_ncols=True)
    for c, path in it:
        r = validate_clip(path, quick=quick, options=options, progress=False)
        first = r.errors[0].line() if r.errors else ""
        rep.clips[c["id"]] = {"ok": r.ok, "errors": len(r.errors), "warnings": len(r.warnings),
                              "first_error": first}
    rep.sources = source_shares(root, index, rep.clips)
    return rep


def source_of(entry: dict) -> str:
    """The source an index entry is counted under: its spec source, and for a scene file its level
    (``SOURCE/STEM``), so that one level of a source that lists several is never dropped unseen."""
    src = str(entry.get("source") or "?")
    if entry.get("kind") == "scene" and entry.get("asset"):
        return f"{src}/{Path(str(entry['asset'])).stem}"
    return src


def unusable_reason(root: Path, entry: dict, checked: dict | None) -> str | None:
    """Why a clip gives no training data (None: it is usable): failed, unfinished, refused when it finished
    (``invalid``) or failing validation (its first error)."""
    if entry.get("state") == "failed" or entry.get("error"):
        err = str(entry.get("error") or "").strip().splitlines()
        return f"failed: {err[-1] if err else 'no error recorded'}"
    if checked is None:
        try:
            state, _ = clip_state(clip_dir(root, entry), int(entry.get("frames_planned", 0)))
        except BlendSRError as exc:  # a path outside the dataset (an index error too)
            return str(exc)
        return f"not rendered ({state})"
    if not checked["ok"]:
        return f"invalid: {checked['first_error'] or str(checked['errors']) + ' errors'}"
    if entry.get("invalid"):
        return f"invalid: {entry['invalid']}"
    return None


def source_shares(root: Path, index: dict, checked: dict) -> dict:
    """Per source (``source_of``): its clips, how many are usable, their share and each unusable clip's reason
    (``unusable_reason``); ``checked``: the validated clips by id."""
    out: dict[str, dict] = {}
    for c in index["clips"]:
        s = out.setdefault(source_of(c), {"clips": 0, "usable": 0, "share": 0.0, "reasons": {}})
        why = unusable_reason(root, c, checked.get(c["id"]))
        s["clips"] += 1
        if why is None:
            s["usable"] += 1
        else:
            s["reasons"][c["id"]] = why
    for s in out.values():
        s["share"] = s["usable"] / s["clips"]
    return out
