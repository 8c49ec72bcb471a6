"""The generalisation gap (pure Python, no bpy, no torch): per-clip margins over ``demod-jbu``
(``benchmarks/worst_case.py -o``, ``blendsr evaluate --json``) of the in-family and the held-out-family clips of a
dataset (each clip's ``family_group`` in its index, ``families.py``) side by side, and their difference::

    python -m gbuffer_export.commands.family_gap MARGINS.json [...] --data DATASET [--data ...]

prints one Markdown row per model: in-family mean (smallest, clips), held-out mean (smallest, clips), gap (dB).

A held-out clip is held out from *this* dataset's train split, not from every network: a network trained elsewhere
(the shipped weights: their JSON's training lineage) may have seen its families. ``--seen-from LABEL=WEIGHTS.json``
counts, for that model, a held-out clip whose held-out families (those no train clip of the index has) were all in
the lineage's training (``lineage_families``) as seen: it leaves the held-out mean and is reported on a line of its
own.
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

from .build import read_index
from .families import HELD_OUT, IN_FAMILY


def read_margins(path: Path) -> dict[str, dict[str, float]]:
    """Per-clip margins over ``demod-jbu`` of each model in a JSON file: ``benchmarks/worst_case.py -o`` (groups ->
    models -> per_clip rows) or ``blendsr evaluate --json`` (per_clip rows of one model, its ``label``). Returns
    model -> clip id (the clip folder's name) -> margin in dB. ValueError (one line naming the file) otherwise."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read margins ({exc})") from None
    out: dict[str, dict[str, float]] = {}

    def add(label: str, rows) -> None:
        for r in rows or []:
            if isinstance(r, dict) and r.get("margin") is not None and r.get("clip"):
                out.setdefault(label, {})[Path(str(r["clip"])).name] = float(r["margin"])
    if isinstance(data, dict) and isinstance(data.get("per_clip"), list):
        add(str(data.get("label") or data.get("model") or Path(path).stem), data["per_clip"])
    elif isinstance(data, dict):
        groups = data.get("groups", data)
        for g in groups.values() if isinstance(groups, dict) else []:
            for label, r in (g.get("models", {}) if isinstance(g, dict) else {}).items():
                add(label, r.get("per_clip") if isinstance(r, dict) else None)
    if not out:
        raise ValueError(f"{path}: no per-clip margins (rows with 'clip' and 'margin'); write it with "
                         "benchmarks/worst_case.py -o or blendsr evaluate --json against demod-jbu")
    return out


SEEN = "seen"  # a held-out clip whose held-out families were all in the model's own training (``--seen-from``)


def family_gap(margins: dict[str, float], groups: dict[str, str], seen: frozenset = frozenset()) -> dict:
    """In-family and held-out-family mean, smallest margin and clip count, and the gap (in-family mean minus
    held-out mean: what training on the families bought that unseen families do not get). ``margins``: clip id ->
    dB; ``groups``: clip id -> ``in-family`` / ``held-out`` (the dataset index); ``seen``: the held-out clips the
    model saw the families of (``seen_clips``), counted under ``seen``, not held-out. Clips absent from ``groups``
    are counted under ``unknown``."""
    by: dict[str, list[float]] = {IN_FAMILY: [], HELD_OUT: [], SEEN: [], "unknown": []}
    for clip, m in margins.items():
        g = groups.get(clip, "unknown")
        by[SEEN if g == HELD_OUT and clip in seen else g].append(m)
    out = {g: {"n": len(v), "mean": sum(v) / len(v) if v else math.nan, "min": min(v) if v else math.nan}
           for g, v in by.items()}
    out["gap"] = out[IN_FAMILY]["mean"] - out[HELD_OUT]["mean"]
    return out


def index_groups(dataset: Path) -> dict[str, str]:
    """Clip folder name -> family group, from ``DATASET/dataset.json`` (an index without families: every clip
    ``in-family``)."""
    return {Path(c["path"]).name: c.get("family_group") or IN_FAMILY for c in read_index(dataset)["clips"]}


def index_families(dataset: Path) -> tuple[dict[str, set[str]], set[str]]:
    """(clip folder name -> its held-out families, the families of the train split) from ``DATASET/dataset.json``:
    a clip's held-out families are those of its ``families`` that no train clip of the index has."""
    clips = read_index(dataset)["clips"]
    train = {f for c in clips if c.get("split") == "train" for f in c.get("families") or ()}
    return {Path(c["path"]).name: set(c.get("families") or ()) - train for c in clips}, train


def lineage_families(weights_json: Path, repo: Path) -> tuple[set[str], list[str]]:
    """(the families a shipped network was trained on, notes on what its JSON leaves unrecorded). Its last stage:
    the families of ``dataset.train_clips`` in ``dataset.spec_file`` (expanded as the spec renders them); the stage
    it was initialised from (``init_from.commands``' ``SPEC=``): that spec's whole train split. Specs are paths
    relative to ``repo``. ValueError (one line naming the file) for a JSON without them."""
    from .spec import expand, load_spec
    try:
        doc = json.loads(Path(weights_json).read_text())
        ds = doc["dataset"]
        stages = [(ds["spec_file"], set(ds["train_clips"]))]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{weights_json}: no training lineage (dataset.spec_file and train_clips: {exc})") from None
    init = doc.get("init_from") or {}
    text = " ".join(init.get("commands") or []) if isinstance(init, dict) else ""
    stages += [(m, None) for m in re.findall(r"\bSPEC=(\S+)", text)]
    notes = [f"{Path(weights_json).name}: the stages before {init.get('weights', '?')!r} are not recorded"
             ] if "pretrained:" in text else []
    seen: set[str] = set()
    for spec_file, ids in stages:
        for job in expand(load_spec(repo / spec_file)):
            if (job.id in ids) if ids is not None else job.split == "train":
                seen.update(job.families or ())
    return seen, notes


def seen_clips(held_out: dict[str, set[str]], trained: set[str]) -> frozenset:
    """The clips (of ``index_families``) whose held-out families the model trained on, every one."""
    return frozenset(c for c, fams in held_out.items() if fams and fams <= trained)


def gap_table(models: dict[str, dict[str, float]], groups: dict[str, str],
              seen: dict[str, frozenset] | None = None) -> str:
    """A Markdown table: per model, in-family and held-out margins (mean, smallest, clips) and the gap; ``seen``:
    per model label, the held-out clips it saw the families of (``seen_clips``), left out of its held-out mean."""
    f = lambda x: "n/a" if math.isnan(x) else f"{x:+.2f}"  # noqa: E731
    lines = ["| model | in-family margin (smallest, clips) | held-out-family margin (smallest, clips) | gap (dB) |",
             "|---|---|---|---|"]
    for label, margins in models.items():
        g = family_gap(margins, groups, (seen or {}).get(label, frozenset()))
        a, b = g[IN_FAMILY], g[HELD_OUT]
        lines.append(f"| `{label}` | {f(a['mean'])} ({f(a['min'])}, {a['n']}) | {f(b['mean'])} ({f(b['min'])}, "
                     f"{b['n']}) | {f(g['gap'])} |")
        if g[SEEN]["n"]:
            lines.append(f"| `{label}` | | {f(g[SEEN]['mean'])} ({f(g[SEEN]['min'])}, {g[SEEN]['n']}): held-out "
                         "clips whose families it trained on, left out above | |")
        if g["unknown"]["n"]:
            lines.append(f"| `{label}` | {g['unknown']['n']} clips not in the datasets' indexes | | |")
    return "\n".join(lines)
