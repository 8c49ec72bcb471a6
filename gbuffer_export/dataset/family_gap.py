"""The generalisation gap (pure Python, no bpy, no torch): per-clip margins over ``demod-jbu``
(``benchmarks/worst_case.py -o``, ``blendsr evaluate --json``) of the in-family and the held-out-family clips of a
dataset (each clip's ``family_group`` in its index, ``families.py``) side by side, and their difference::

    python -m gbuffer_export.commands.family_gap MARGINS.json [...] --data DATASET [--data ...]

prints one Markdown row per model: in-family mean (smallest, clips), held-out mean (smallest, clips), gap (dB).
"""
from __future__ import annotations

import json
import math
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


def family_gap(margins: dict[str, float], groups: dict[str, str]) -> dict:
    """In-family and held-out-family mean, smallest margin and clip count, and the gap (in-family mean minus
    held-out mean: what training on the families bought that unseen families do not get). ``margins``: clip id ->
    dB; ``groups``: clip id -> ``in-family`` / ``held-out`` (the dataset index). Clips absent from ``groups`` are
    counted under ``unknown``."""
    by: dict[str, list[float]] = {IN_FAMILY: [], HELD_OUT: [], "unknown": []}
    for clip, m in margins.items():
        by[groups.get(clip, "unknown")].append(m)
    out = {g: {"n": len(v), "mean": sum(v) / len(v) if v else math.nan, "min": min(v) if v else math.nan}
           for g, v in by.items()}
    out["gap"] = out[IN_FAMILY]["mean"] - out[HELD_OUT]["mean"]
    return out


def index_groups(dataset: Path) -> dict[str, str]:
    """Clip folder name -> family group, from ``DATASET/dataset.json`` (an index without families: every clip
    ``in-family``)."""
    return {Path(c["path"]).name: c.get("family_group") or IN_FAMILY for c in read_index(dataset)["clips"]}


def gap_table(models: dict[str, dict[str, float]], groups: dict[str, str]) -> str:
    """A Markdown table: per model, in-family and held-out margins (mean, smallest, clips) and the gap."""
    f = lambda x: "n/a" if math.isnan(x) else f"{x:+.2f}"  # noqa: E731
    lines = ["| model | in-family margin (smallest, clips) | held-out-family margin (smallest, clips) | gap (dB) |",
             "|---|---|---|---|"]
    for label, margins in models.items():
        g = family_gap(margins, groups)
        a, b = g[IN_FAMILY], g[HELD_OUT]
        lines.append(f"| `{label}` | {f(a['mean'])} ({f(a['min'])}, {a['n']}) | {f(b['mean'])} ({f(b['min'])}, "
                     f"{b['n']}) | {f(g['gap'])} |")
        if g["unknown"]["n"]:
            lines.append(f"| `{label}` | {g['unknown']['n']} clips not in the datasets' indexes | | |")
    return "\n".join(lines)
