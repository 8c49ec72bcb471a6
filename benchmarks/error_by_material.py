"""Where the error lies by material class, per family group: does an upscaler lack data or inputs (issue 54)?

    .venv/bin/python benchmarks/error_by_material.py DATASET BASELINE.json MODEL.json [MODEL.json ...]
        [--labels LABEL,...] [-o OUT.md]

The JSONs are ``blendsr evaluate`` results on clips of DATASET (``--data DATASET --split val``), the baseline's
(``demod-jbu``) first; each frame's ``materials`` (``gbuffer_export.regions.material_regions``, the classes of
``MATERIALS``) give the squared tonemapped error of every class. For every group of clips (the
kinds objects and levels; the family groups of ``data_scaling.family_groups``: in-family, held-out and its
sub-groups held-out asset and held-out level) and every class: its share of the pixels, the baseline's PSNR and each
model's gain over it, both pooled over the frames (the squared error summed over the class's pixels of every frame
the model and the baseline both scored, at the same scale), and the class's share of the baseline's and of each
model's remaining squared error in the group. A class whose share grows from the baseline's to a model's gains less
than the rest: it may lack inputs (a glossy, coated or transmissive surface shows its surroundings, which no
G-buffer holds; docs/evaluation.md, ``materials``), or capacity or training there. Frames missing from a result are
left out of every result, with a note. Markdown on stdout, and in OUT.md with ``-o``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def pooled(result: dict, where: str) -> dict[tuple[str, float, int], dict[str, tuple[float, float]]]:
    """{(clip folder name, scale, frame): {class: (summed squared error, pixels)}} of an evaluate result's frames
    that have a material breakdown (PSNR on a peak of 1, as evaluate writes it capped: mse = 10^(-PSNR/10)).
    SystemExit naming ``where`` for a result that is not one, or a frame scored twice."""
    rows = result.get("per_frame") if isinstance(result, dict) else None
    if not isinstance(rows, list):
        raise SystemExit(f"{where}: not a blendsr evaluate result (no per_frame list; worst_case.py's JSONs have none)")
    out = {}
    for r in rows:
        if not r.get("materials"):
            continue
        key = (Path(r["clip"]).name, float(r["scale"]), int(r["frame"]))
        if key in out:
            raise SystemExit(f"{where}: frame {key[2]} of {key[0]} at scale {key[1]:g} is scored twice")
        out[key] = {name: (v["fraction"] * r["pixels"] * 10 ** (-v["psnr"] / 10)
                           if v["psnr"] is not None else 0.0, v["fraction"] * r["pixels"])
                    for name, v in r["materials"].items()}
    return out


def common_frames(base: dict, models: list[dict], files: list[Path]) -> set:
    """The frames every result scored with the same classes; a note on stderr for each file that loses frames,
    SystemExit when none is left."""
    keys = set(base).intersection(*models)
    for f, m in zip(files, [base, *models]):
        if len(m) > len(keys):
            print(f"note: {f}: {len(m) - len(keys)} of its {len(m)} frames are not in every result; left out",
                  file=sys.stderr)
    for f, m in zip(files[1:], models):
        odd = next((k for k in keys if set(m[k]) != set(base[k])), None)
        if odd:
            raise SystemExit(f"{f}: frame {odd[2]} of {odd[0]} has classes {sorted(m[odd])}, the baseline's "
                             f"{sorted(base[odd])} (results of different BlendSR versions?)")
    if not keys:
        raise SystemExit(f"{files[1]}: no frame in common with {files[0]} (another split or dataset?)")
    return keys


def clip_groups(dataset: Path, keys) -> dict[str, tuple[str, ...]]:
    """{clip folder name: the groups it counts in}: its kind (objects or levels) and its family groups; SystemExit
    naming the dataset when a scored clip is not in its index."""
    from data_scaling import family_groups
    from gbuffer_export.dataset.family_gap import index_kinds
    kinds = index_kinds(dataset)
    missing = sorted({k[0] for k in keys} - set(kinds))
    if missing:
        raise SystemExit(f"{dataset}: its index has no clip {missing[0]} (and {len(missing) - 1} more): the results "
                         "scored another dataset")
    return {c: (kinds[c], *g) for c, g in family_groups(dataset).items()}


def group_rows(groups: dict, base: dict, models: list[dict], keys: set) -> list[tuple[str, str, list]]:
    """(group, class, [pixel share, baseline PSNR, the baseline's error share, then per model: gain, share of its
    remaining error]) rows over the frames ``keys``."""
    from training.metrics import psnr_from_mse
    names = sorted({g for gs in groups.values() for g in gs}, key=lambda g: (g not in ("objects", "levels"), g))
    rows = []
    for g in names:
        ks = [k for k in keys if g in groups.get(k[0], ())]
        if not ks:
            continue
        classes = list(base[ks[0]])
        tot = [sum(m[k][c][0] for k in ks for c in classes) for m in [base, *models]]
        for c in classes:
            se_b, n = (sum(base[k][c][i] for k in ks) for i in (0, 1))
            if n == 0:
                continue
            cells = [n / sum(base[k][x][1] for k in ks for x in classes), psnr_from_mse(se_b / n),
                     se_b / tot[0] if tot[0] > 0 else math.nan]
            for m, t in zip(models, tot[1:]):
                se = sum(m[k][c][0] for k in ks)
                cells += [psnr_from_mse(se / n) - cells[1], se / t if t > 0 else math.nan]
            rows.append((f"{g} ({len({k[0] for k in ks})} clips)", c, cells))
    return rows


def table(rows, labels: list[str], baseline: str) -> str:
    head = ["group", "class", "pixels", f"`{baseline}` PSNR (dB)", "its error share"]
    for lab in labels:
        head += [f"`{lab}` gain (dB)", "its error share"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for g, c, cells in rows:
        fmt = [f"{cells[0]:.1%}", f"{cells[1]:.2f}", f"{cells[2]:.0%}"]
        for i in range(3, len(cells), 2):
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
    docs = [_load(f) for f in a.results]
    base, *models = [pooled(d, str(f)) for d, f in zip(docs, a.results)]
    missing = [str(f) for f, m in zip(a.results, [base, *models]) if not m]
    if missing:
        raise SystemExit(f"{missing[0]}: no frame has a material breakdown (blendsr evaluate before 2026-11-30, or "
                         "clips without HR flags and roughness)")
    labels = a.labels.split(",") if a.labels else [d["model"] for d in docs[1:]]
    if len(labels) != len(models):
        p.error(f"--labels names {len(labels)} models; {len(models)} results follow the baseline's")
    keys = common_frames(base, models, a.results)
    text = table(group_rows(clip_groups(a.dataset, keys), base, models, keys), labels, docs[0]["model"])
    print(text)
    if a.output:
        from gbuffer_export.clip import write_bytes_atomic
        write_bytes_atomic(a.output, (text + "\n").encode())
    return 0


def _load(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SystemExit(f"{path}: cannot read a JSON result ({type(e).__name__}: {e})") from None


if __name__ == "__main__":
    sys.exit(main())
