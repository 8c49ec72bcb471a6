"""Compare two speed tables of ``blendsr bench models`` (bench_speed.json, e.g. two ``CHECK=graph`` calls on two lent
machines): per (model, variant) both medians, their ratio and whether they agree within ``--within`` (10 %: a timing
that cannot be repeated within 10 % is not a result), plus each row's own spread where the graph timer gave one.

Usage: python3 benchmarks/gpu/compare.py A/speed_graph.json B/speed_graph.json [--within 0.10] [-o OUT.md]
Exit 0 when every row common to both agrees, 1 otherwise.
"""
from __future__ import annotations

import argparse
import json
import sys


def compare(a: dict, b: dict, within: float) -> tuple[list[str], bool]:
    rows_b = {(r["model"], r["variant"]): r for r in b["rows"]}
    lines = [f"A: {a.get('device')}; B: {b.get('device')}", "",
             "| model | variant | A ms | B ms | B / A | A spread | B spread | within |",
             "|---|---|---|---|---|---|---|---|"]
    ok = True
    for r in a["rows"]:
        other = rows_b.get((r["model"], r["variant"]))
        if other is None:
            continue
        ratio = other["ms"] / r["ms"] if r["ms"] else float("inf")
        agree = abs(ratio - 1.0) <= within
        ok &= agree
        spread = (lambda x: f"{x['spread']:.1%}" if "spread" in x else "-")
        lines.append(f"| {r['model']} | {r['variant']} | {r['ms']:.4g} | {other['ms']:.4g} | {ratio:.3f} | "
                     f"{spread(r)} | {spread(other)} | {'yes' if agree else 'NO'} |")
    return lines, ok


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("--within", type=float, default=0.10)
    p.add_argument("-o", dest="out")
    args = p.parse_args()
    with open(args.a) as fa, open(args.b) as fb:
        lines, ok = compare(json.load(fa), json.load(fb), args.within)
    text = "\n".join(lines)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
