"""The generalisation gap (pure Python, no bpy, no torch): per-clip margins over ``demod-jbu``
(``benchmarks/worst_case.py -o``, ``blendsr evaluate --json``) of the in-family and the held-out-family clips of a
dataset (each clip's ``family_group`` in its index, ``families.py``) side by side, and their difference::

    python -m gbuffer_export.commands.family_gap MARGINS.json [...] --data DATASET [--data ...]

prints one Markdown row per model: in-family mean (smallest, clips), held-out mean (smallest, clips), gap (dB).

A held-out clip is held out from *this* dataset's train split, not from every network: a network trained elsewhere
(the shipped weights: their JSON's training lineage) may have seen its families, and never seen an in-family one's.
``--seen-from LABEL=WEIGHTS.json`` groups that model's clips by its own lineage (``lineage_families``): in-family
when it trained on every family of the clip, held-out otherwise (``lineage_groups``); its row says so.
``--by-kind`` adds the gap within objects and within levels and the kind-matched gap (``kind_gap``).
"""
from __future__ import annotations

import json
import math
import shlex
from pathlib import Path

from .build import read_index
from .families import HELD_OUT, IN_FAMILY, UNSEEN_CONTENT, unseen_content


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
    dB; ``groups``: clip id -> ``in-family`` / ``held-out`` (the dataset index, or ``lineage_groups``). Clips absent
    from ``groups`` are counted under ``unknown``."""
    by: dict[str, list[float]] = {IN_FAMILY: [], HELD_OUT: [], "unknown": []}
    for clip, m in margins.items():
        by[groups.get(clip, "unknown")].append(m)
    out = {g: {"n": len(v), "mean": sum(v) / len(v) if v else math.nan, "min": min(v) if v else math.nan}
           for g, v in by.items()}
    out["gap"] = out[IN_FAMILY]["mean"] - out[HELD_OUT]["mean"]
    return out


#: The kinds of clip ``kind_gap`` compares within (as ``benchmarks/worst_case.py`` groups them): a level is a clip of a
#: source of kind ``scene`` (a level kept as it is), an object any other.
KINDS = ("objects", "levels")


def kind_gap(margins: dict[str, float], groups: dict[str, str], kinds: dict[str, str]) -> dict:
    """``family_gap`` within each kind of clip (``kinds``: clip id -> one of ``KINDS``) and the kind-matched gap: the
    per-kind gaps weighted by the held-out clips of each kind (kinds with both groups only: ``matched_n`` of the
    ``held_out_n`` held-out clips; ``unknown_n`` clips of no kind are left out). A plain gap mixes kinds:
    where levels score higher margins than objects and the held-out clips are mostly objects, the plain gap grows by
    the mix alone; the matched gap compares each held-out clip with in-family clips of its own kind."""
    out = {k: family_gap({c: m for c, m in margins.items() if kinds.get(c) == k}, groups) for k in KINDS}
    both = [k for k in KINDS if out[k][IN_FAMILY]["n"] and out[k][HELD_OUT]["n"]]
    weight = sum(out[k][HELD_OUT]["n"] for k in both)
    out["matched"] = sum(out[k]["gap"] * out[k][HELD_OUT]["n"] for k in both) / weight if weight else math.nan
    out["matched_n"], out["held_out_n"] = weight, sum(out[k][HELD_OUT]["n"] for k in KINDS)
    out["unknown_n"] = sum(kinds.get(c) not in KINDS for c in margins)
    return out


def index_kinds(dataset: Path) -> dict[str, str]:
    """Clip folder name -> ``levels`` (its source is of kind ``scene``) or ``objects``, from
    ``DATASET/dataset.json``."""
    return {Path(c["path"]).name: "levels" if c.get("kind") == "scene" else "objects"
            for c in read_index(dataset)["clips"]}


def index_groups(dataset: Path) -> dict[str, str]:
    """Clip folder name -> family group, from ``DATASET/dataset.json`` (an index without families: every clip
    ``in-family``)."""
    return {Path(c["path"]).name: c.get("family_group") or IN_FAMILY for c in read_index(dataset)["clips"]}


def index_trained_families(dataset: Path) -> set[str]:
    """Every family that a clip of the train split of ``DATASET/dataset.json`` holds (planned or rendered)."""
    return set().union(*(c.get("families") or () for c in read_index(dataset)["clips"] if c.get("split") == "train"))


def content_groups(families: dict[str, set[str]], groups: dict[str, str], trained: set[str]) -> dict[str, tuple]:
    """Clip -> its ``unseen_content`` sub-groups, for the ``held-out`` clips of ``groups`` that show an object asset or
    a level missing from ``trained`` (the dataset's train split: ``index_trained_families``, the whole split, so that
    every run of a curve is scored on the same clips; or a network's lineage); other clips are left out."""
    out = {}
    for clip, group in groups.items():
        sub = unseen_content(families.get(clip, ()), trained) if group == HELD_OUT else ()
        if sub:
            out[clip] = sub
    return out


def index_families(dataset: Path) -> dict[str, set[str]]:
    """Clip folder name -> its ``families``, from ``DATASET/dataset.json``."""
    return {Path(c["path"]).name: set(c.get("families") or ()) for c in read_index(dataset)["clips"]}


def lineage_stages(doc: dict, name: str) -> tuple[list[tuple[str, set[str] | None]], list[str]]:
    """(every recorded training stage of a weights JSON ``doc``, newest first: (spec file, its train clip ids, or
    None for the spec's whole train split); notes on what is unrecorded). A stage is the JSON's ``dataset``, then each
    nested ``init_from`` that keeps its own ``dataset`` (``release_weights.shipped_origin`` does since issue 54), then,
    for an ``init_from`` without one, the ``SPEC=`` of its commands (the older JSONs)."""
    stages = [(str(doc["dataset"]["spec_file"]), {str(i) for i in doc["dataset"]["train_clips"]})]
    notes, init = unrecorded_start(doc, name, "its last stage"), doc.get("init_from")
    while isinstance(init, dict) and init:
        ds = init.get("dataset")
        if isinstance(ds, dict) and ds.get("spec_file") and ds.get("train_clips") is not None:
            stages.append((str(ds["spec_file"]), {str(i) for i in ds["train_clips"]}))
            notes += unrecorded_start(init, name, repr(init.get("weights", "a stage")))
            init = init.get("init_from")
            continue
        words = command_words(init)
        specs = [(w.split("=", 1)[1], None) for w in words if w.startswith("SPEC=")]
        stages += specs
        if not specs or starts_from_shipped(words):
            notes.append(f"{name}: a stage before {init.get('weights', 'its init_from')!r} is not recorded; the "
                         "families seen there are not counted")
        break
    return stages, notes


def command_words(stage: dict) -> list[str]:
    """The words of a recorded stage's ``commands`` (a string or a list of them)."""
    commands = stage.get("commands") or []
    return [w for c in ([commands] if isinstance(commands, str) else commands) for w in shlex.split(str(c))]


def starts_from_shipped(words: list[str]) -> bool:
    """Whether a stage's command words start its training from shipped weights (``run.init_from`` or a script's
    ``INIT`` naming ``pretrained:``), not merely mention them (an evaluation of ``pretrained:M``)."""
    return any(w.split("=", 1)[0] in ("run.init_from", "INIT") and "pretrained:" in w for w in words)


def unrecorded_start(stage: dict, name: str, what: str) -> list[str]:
    """A note when a recorded stage's commands start from shipped weights (``pretrained:``) but it keeps no
    ``init_from``: the stages before it trained on families that would go uncounted without a word."""
    if stage.get("init_from") or not starts_from_shipped(command_words(stage)):
        return []
    return [f"{name}: {what} started from shipped weights that it does not record (no init_from); the families "
            "seen before it are not counted"]


def lineage_families(weights_json: Path, repo: Path) -> tuple[set[str], list[str]]:
    """(the families a shipped network was trained on, notes on what its JSON leaves unrecorded or unresolved): the
    families of every stage of ``lineage_stages`` (its train clips as their spec expands them today, or the spec's
    whole train split). Specs are paths relative to ``repo``. ValueError (one line naming the file) for a JSON
    without them or a spec that does not load."""
    from .spec import SpecError, expand, load_spec
    try:
        stages, notes = lineage_stages(json.loads(Path(weights_json).read_text()), Path(weights_json).name)
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{weights_json}: no training lineage (dataset.spec_file and train_clips: {exc})") from None
    seen: set[str] = set()
    for spec_file, ids in stages:
        try:
            jobs = expand(load_spec(repo / spec_file))
        except (SpecError, OSError, ValueError) as exc:
            raise ValueError(f"{weights_json}: its spec {spec_file} (under {repo}): {exc}") from None
        found = {j.id for j in jobs}
        if ids is not None and ids - found:
            notes.append(f"{Path(weights_json).name}: {len(ids - found)} train clip(s) not in {spec_file} as it "
                         f"expands today (e.g. {sorted(ids - found)[0]}); their families are not counted")
        seen.update(f for j in jobs if (j.id in ids if ids is not None else j.split == "train")
                    for f in j.families or ())
    return seen, notes


def lineage_groups(families: dict[str, set[str]], trained: set[str]) -> dict[str, str]:
    """Clip -> ``in-family`` when the model trained on every family of the clip, else ``held-out``."""
    return {c: IN_FAMILY if fams <= trained else HELD_OUT for c, fams in families.items()}


def gap_table(models: dict[str, dict[str, float]], groups: dict[str, str],
              own: dict[str, dict[str, str]] | None = None) -> str:
    """A Markdown table: per model, in-family and held-out margins (mean, smallest, clips) and the gap; ``own``:
    per model label, its own groups (``lineage_groups``), used instead of the index's and said in its row."""
    f = lambda x: "n/a" if math.isnan(x) else f"{x:+.2f}"  # noqa: E731
    lines = ["| model | in-family margin (smallest, clips) | held-out-family margin (smallest, clips) | gap (dB) |",
             "|---|---|---|---|"]
    for label, margins in models.items():
        mine = (own or {}).get(label)
        g = family_gap(margins, mine if mine is not None else groups)
        a, b = g[IN_FAMILY], g[HELD_OUT]
        name = f"`{label}`" + (" (by its training lineage)" if mine is not None else "")
        lines.append(f"| {name} | {f(a['mean'])} ({f(a['min'])}, {a['n']}) | {f(b['mean'])} ({f(b['min'])}, "
                     f"{b['n']}) | {f(g['gap'])} |")
        if g["unknown"]["n"]:
            lines.append(f"| `{label}` | {g['unknown']['n']} clips not in the datasets' indexes | | |")
    return "\n".join(lines)


def kind_table(models: dict[str, dict[str, float]], groups: dict[str, str], kinds: dict[str, str],
               own: dict[str, dict[str, str]] | None = None) -> str:
    """A Markdown table: per model, the gap within objects and within levels (in-family mean minus held-out mean,
    clips of each) and the kind-matched gap (``kind_gap``; with the held-out clips it covers); ``own`` as in
    ``gap_table``."""
    f = lambda x: "n/a" if math.isnan(x) else f"{x:+.2f}"  # noqa: E731
    lines = ["| model | objects: in-family / held-out (clips) | gap | levels: in-family / held-out (clips) | gap "
             "| kind-matched gap (dB) |", "|---|---|---|---|---|---|"]
    for label, margins in models.items():
        mine = (own or {}).get(label)
        g = kind_gap(margins, mine if mine is not None else groups, kinds)
        cells = [f"{f(g[k][IN_FAMILY]['mean'])} / {f(g[k][HELD_OUT]['mean'])} ({g[k][IN_FAMILY]['n']} / "
                 f"{g[k][HELD_OUT]['n']}) | {f(g[k]['gap'])}" for k in KINDS]
        name = f"`{label}`" + (" (by its training lineage)" if mine is not None else "")
        lines.append(f"| {name} | {' | '.join(cells)} | {f(g['matched'])} ({g['matched_n']} of {g['held_out_n']} "
                     "held-out) |")
        if g["unknown_n"]:
            lines.append(f"| `{label}` | {g['unknown_n']} clips not in the datasets' indexes | | | | |")
    return "\n".join(lines)


def unseen_by_all(groups: dict[str, str], own: dict[str, dict[str, str]]) -> set[str]:
    """The clips held out of the dataset's train split (``groups``) that every lineage of ``own`` holds out too: the
    clips on which networks of different training can be compared fairly (none trained on every family of one)."""
    return {c for c, g in groups.items() if g == HELD_OUT and all(o.get(c) == HELD_OUT for o in own.values())}


def unseen_table(models: dict[str, dict[str, float]], clips: set[str]) -> str:
    """A Markdown table: per model, its mean and smallest margin on ``clips`` (models that lack one: n/a)."""
    lines = [f"| model | margin on the {len(clips)} clips no network trained on (smallest) |", "|---|---|"]
    for label, margins in models.items():
        v = [margins[c] for c in clips if c in margins]
        cell = f"{sum(v) / len(v):+.2f} ({min(v):+.2f})" if v and len(v) == len(clips) else "n/a (clips missing)"
        lines.append(f"| `{label}` | {cell} |")
    return "\n".join(lines)


def content_table(models: dict[str, dict[str, float]], sub: dict[str, dict[str, tuple]], own=()) -> str:
    """A Markdown table: per model, its mean and smallest margin and the clip count on each ``unseen_content``
    sub-group; ``sub``: per model label, clip -> its sub-groups (``content_groups`` by the dataset's train split, or
    by the model's own lineage for the labels in ``own``, which its row says)."""
    f = lambda v: f"{sum(v) / len(v):+.2f} ({min(v):+.2f}, {len(v)})" if v else "n/a (0)"  # noqa: E731
    lines = ["| model | " + " | ".join(f"{g}s never trained on: margin (smallest, clips)"
                                       for g in UNSEEN_CONTENT.values()) + " |", "|---|---|---|"]
    for label, margins in models.items():
        mine = sub.get(label, {})
        cells = [f([m for c, m in margins.items() if g in mine.get(c, ())]) for g in UNSEEN_CONTENT.values()]
        name = f"`{label}`" + (" (by its training lineage)" if label in own else "")
        lines.append(f"| {name} | {' | '.join(cells)} |")
    return "\n".join(lines)
