"""``python -m gbuffer_export.commands.family_gap MARGINS.json ... --data DATASET``: the in-family and held-out-family
margins over ``demod-jbu`` side by side, and their gap; ``--by-kind`` within objects and levels too (the library:
``gbuffer_export.dataset.family_gap``)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..dataset.family_gap import (content_groups, content_table, gap_table, index_families, index_groups, index_kinds,
                                  index_trained_families, kind_table, lineage_families, lineage_groups, read_margins,
                                  unseen_by_all, unseen_table)
from ..errors import BlendSRError


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m gbuffer_export.commands.family_gap",
                                description="in-family vs held-out-family margins over demod-jbu, and the gap")
    p.add_argument("margins", type=Path, nargs="+", help="worst_case.py -o JSON or evaluate --json files")
    p.add_argument("--data", type=Path, action="append", required=True,
                   help="dataset folder(s) whose index names each clip's family group")
    p.add_argument("--seen-from", action="append", default=[], metavar="LABEL=WEIGHTS.json",
                   help="a model trained outside the dataset (e.g. pretrained:fusesr=training/weights/fusesr_x4.json):"
                        " its clips are grouped by its own training lineage (in-family: it trained on every family "
                        "of the clip), not by the dataset's split")
    p.add_argument("--unseen-by-all", action="store_true",
                   help="also a table of every model on the held-out clips that no --seen-from lineage trained on "
                        "every family of: the one set on which all of them compare fairly")
    p.add_argument("--by-kind", action="store_true",
                   help="also the gap within objects and within levels and the kind-matched gap (each held-out clip "
                        "against in-family clips of its own kind: levels score higher margins than objects, and a "
                        "split whose held-out clips are mostly objects has a larger plain gap by the mix alone), and "
                        "every model on the held-out clips that show an object asset, or a level, that it never "
                        "trained on (by the dataset's train split, or by its --seen-from lineage): what 'real objects "
                        "and levels never seen' measures")
    p.add_argument("--repo", type=Path, default=Path(__file__).resolve().parents[2],
                   help="the checkout the weights JSONs' spec paths are relative to (default: this one)")
    p.add_argument("--json", type=Path, metavar="OUT.json",
                   help="also write the tables printed, {name: {columns, rows}} (gap, by_kind, unseen_content, "
                        "unseen_by_all): records the results page's `table` kind reads (with `key`)")
    return p


def table_record(text: str) -> dict:
    """A Markdown table printed here as ``{"columns": [...], "rows": [[...], ...]}`` (cells as printed)."""
    lines = [line for line in text.strip().splitlines() if line.startswith("|")]
    cells = (lambda line: [c.strip() for c in line.strip().strip("|").split("|")])  # noqa: E731
    return {"columns": cells(lines[0]), "rows": [cells(line) for line in lines[2:]]}


def main(argv=None) -> int:
    a = parser().parse_args(argv)
    try:
        groups = {k: v for d in a.data for k, v in index_groups(d).items()}
        families = {k: v for d in a.data for k, v in index_families(d).items()}
        models: dict[str, dict[str, float]] = {}
        for m in a.margins:
            for label, rows in read_margins(m).items():
                models.setdefault(label, {}).update(rows)
        own, lineage = {}, {}
        for item in a.seen_from:
            label, sep, path = item.rpartition("=")  # a label may hold "=" (its options), a path does not
            if not sep or label not in models:
                raise ValueError(f"--seen-from {item!r}: expected LABEL=WEIGHTS.json with LABEL one of the margins' "
                                 f"models ({', '.join(models)})")
            trained, notes = lineage_families(Path(path), a.repo)
            for note in notes:
                print(f"note: {note}", file=sys.stderr)
            own[label] = lineage_groups(families, trained)
            lineage[label] = trained
    except (BlendSRError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    tables = {"gap": gap_table(models, groups, own)}
    if a.by_kind:
        tables["by_kind"] = kind_table(models, groups, {k: v for d in a.data for k, v in index_kinds(d).items()}, own)
        trained = set().union(*(index_trained_families(d) for d in a.data))
        sub = {label: content_groups(families, own.get(label, groups), lineage.get(label, trained))
               for label in models}
        if any(sub.values()):
            tables["unseen_content"] = content_table(models, sub, own)
    if a.unseen_by_all:
        scored = set().union(*models.values())
        clips = unseen_by_all({c: g for c, g in groups.items() if c in scored}, own)
        tables["unseen_by_all"] = unseen_table(models, clips)
    print("\n\n".join(tables.values()))
    if a.json:
        from ..clip import write_json_atomic
        write_json_atomic(a.json, {name: table_record(text) for name, text in tables.items()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
