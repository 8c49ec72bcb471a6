"""``python -m gbuffer_export.commands.family_gap MARGINS.json ... --data DATASET``: the in-family and held-out-family
margins over ``demod-jbu`` side by side, and their gap (the library: ``gbuffer_export.dataset.family_gap``)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..dataset.family_gap import gap_table, index_groups, read_margins
from ..errors import BlendSRError


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m gbuffer_export.commands.family_gap",
                                description="in-family vs held-out-family margins over demod-jbu, and the gap")
    p.add_argument("margins", type=Path, nargs="+", help="worst_case.py -o JSON or evaluate --json files")
    p.add_argument("--data", type=Path, action="append", required=True,
                   help="dataset folder(s) whose index names each clip's family group")
    a = p.parse_args(argv)
    try:
        groups = {k: v for d in a.data for k, v in index_groups(d).items()}
        models: dict[str, dict[str, float]] = {}
        for m in a.margins:
            for label, rows in read_margins(m).items():
                models.setdefault(label, {}).update(rows)
    except (BlendSRError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(gap_table(models, groups))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
