"""Where the error lies by material class, per family group: does an upscaler lack data or inputs (issue 54)?

    .venv/bin/python benchmarks/error_by_material.py DATASET BASELINE.json MODEL.json [MODEL.json ...]
        [--labels LABEL,...] [-o OUT.md]

The JSONs are ``blendsr evaluate`` results on clips of DATASET (``--data DATASET --split val``), the baseline's
(``demod-jbu``) first; each frame's ``materials`` (``gbuffer_export.regions.material_regions``: background,
transmission, coated, glossy, rough) give the squared tonemapped error of every class. For every group of clips (the
kinds objects and levels; the family groups of ``data_scaling.family_groups``: in-family, held-out and its
sub-groups held-out asset and held-out level) and every class: its share of the pixels, the baseline's PSNR and each
model's gain over it, both pooled over the frames (the squared error summed over the class's pixels of every frame
the model and the baseline both scored), and the class's share of the model's remaining squared error in the group.
A class that gains little and holds much of what remains is one whose HR detail no input carries (a glossy,
coated or transmissive surface shows its surroundings; docs/evaluation.md, ``materials``). Markdown on stdout, and
in OUT.md with ``-o``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def pooled(result: dict) -> dict[tuple[str, int], dict[str, tuple[float, float]]]:
    """{(clip folder name, frame): {class: (summed squared error, pixels)}} of an evaluate result's frames that have
    a material breakdown (PSNR on a peak of 1, so mse = 10^(-PSNR/10))."""
    out = {}
    for r in result["per_frame"]:
        if not r.get("materials"):
            continue
        cls = {}
        for name, v in r["materials"].items():
            n = v["fraction"] * r["pixels"]
            cls[name] = (n * 10 ** (-v["psnr"] / 10) if v["psnr"] is not None else 0.0, n)
        out[(Path(r["clip"]).name, int(r["frame"]))] = cls
    return out


def clip_groups(dataset: Path) -> dict[str, tuple[str, ...]]:
    """{clip folder name: the groups it counts in}: its kind (objects or levels) and its family groups."""
    from data_scaling import family_groups
    from gbuffer_export.dataset.family_gap import index_kinds
    kinds = index_kinds(dataset)
    return {c: (kinds.get(c, "objects"), *g) for c, g in family_groups(dataset).items()}


def group_rows(groups: dict, base: dict, models: list[dict]) -> list[tuple[str, str, list]]:
    """(group, class, [pixel share, baseline PSNR, then per model: gain, share of its remaining error]) rows over the
    frames every result scored."""
    keys = set(base).intersection(*models)
    names = sorted({g for gs in groups.values() for g in gs}, key=lambda g: (g not in ("objects", "levels"), g))
    rows = []
    for g in names:
        ks = [k for k in keys if g in groups.get(k[0], ())]
        if not ks:
            continue
        classes = list(base[ks[0]])
        tot = [sum(m[k][c][0] for k in ks for c in classes) for m in models]
        for c in classes:
            se_b, n = (sum(base[k][c][i] for k in ks) for i in (0, 1))
            if n == 0:
                continue
            cells = [n / sum(base[k][x][1] for k in ks for x in classes), _psnr(se_b, n)]
            for m, t in zip(models, tot):
                se = sum(m[k][c][0] for k in ks)
                cells += [_psnr(se, n) - cells[1], se / t if t > 0 else math.nan]
            rows.append((f"{g} ({len({k[0] for k in ks})} clips)", c, cells))
    return rows


def _psnr(se: float, n: float) -> float:
    return 100.0 if se <= 0 else min(100.0, -10 * math.log10(se / n))


def table(rows, labels: list[str], baseline: str) -> str:
    head = ["group", "class", "pixels", f"`{baseline}` PSNR (dB)"]
    for lab in labels:
        head += [f"`{lab}` gain (dB)", "its error share"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for g, c, cells in rows:
        fmt = [f"{cells[0]:.1%}", f"{cells[1]:.2f}"]
        for i in range(2, len(cells), 2):
            fmt += [f"{cells[i]:+.2f}", f"{cells[i + 1]:.0%}"]
        lines.append("| " + " | ".join([g, c] + fmt) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", type=Path, help="the dataset folder the results scored (its index gives the groups)")
    p.add_argument("results", type=Path, nargs="+", help="blendsr evaluate JSONs: the baseline's first")
    p.add_argument("--labels", help="comma-separated names of the models in the table (default: each result's model)")
    p.add_argument("-o", "--output", type=Path, help="also write the table to this Markdown file")
    a = p.parse_args(argv)
    if len(a.results) < 2:
        p.error("give the baseline's result and at least one model's")
    docs = [json.loads(f.read_text()) for f in a.results]
    base, *models = [pooled(d) for d in docs]
    missing = [str(f) for f, m in zip(a.results, [base, *models]) if not m]
    if missing:
        raise SystemExit(f"{missing[0]}: no frame has a material breakdown (blendsr evaluate before 2026-11-30, or "
                         "clips without HR flags and roughness)")
    labels = a.labels.split(",") if a.labels else [d["model"] for d in docs[1:]]
    if len(labels) != len(models):
        p.error(f"--labels names {len(labels)} models; {len(models)} results follow the baseline's")
    text = table(group_rows(clip_groups(a.dataset), base, models), labels, docs[0]["model"])
    print(text)
    if a.output:
        from gbuffer_export.clip import write_bytes_atomic
        write_bytes_atomic(a.output, (text + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
