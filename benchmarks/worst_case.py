"""Issue 40's table: every model against ``demod-jbu`` on one split of one or more datasets, objects and levels apart,
with the mean, the smallest per-clip margin and the artifact pixels (docs/evaluation.md, "The worst case").

    .venv/bin/python benchmarks/worst_case.py DATASET [DATASET ...] [--split test]
        [--models demod-bilinear,demod-jbu,pretrained:fusesr,pretrained:fusesr-l] [-o OUT.json]

A clip is a level when its source is of kind ``scene`` (a level kept as it is, cameras inside it), an object
otherwise (assets in generated environments, built-in scenes). A model whose buffers a clip lacks is left out of
that group with a note (as ``bench models`` does). Writes OUT.json (every model's per-clip rows) and OUT.md (the
table) when ``-o`` is given; prints the table. With ``--record`` (val split only) each shipped network's row
(``pretrained:NAME``, no options) is written into the JSON beside its weights under ``worst_case_val``
(``training.pretrained.WORST_CASE_VAL``, one record per val set, others kept: the frame-weighted margin over
``demod-jbu`` on every group it was scored on, per group too, with the weights' sha256, the datasets and this
command), which ``pretrained.below_baseline`` reads: the README and the add-on's model menu mark a network below
``demod-jbu`` there. ``--scores A.json B.json`` tables (and records) earlier runs' OUT.json instead of scoring:
several runs on the same clips merge, so networks whose weights are final can be scored while others still train,
and one table holds them all.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import shlex
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

def clip_groups(datasets: list[Path], split: str) -> dict[str, list[str]]:
    """The split's clips of every dataset, as paths, by group (``family_gap.KINDS``, by
    ``family_gap.index_kinds``: the one rule of what a level is). DatasetError (one line) unless every clip the
    index plans in the split is finished and valid (``build.whole_split``): part of a split never passes for it."""
    from gbuffer_export.dataset.build import whole_split
    from gbuffer_export.dataset.family_gap import KINDS, index_kinds
    out: dict[str, list[str]] = {g: [] for g in KINDS}
    for ds in datasets:
        kind = index_kinds(ds)
        for clip in whole_split(ds, split):
            out[kind.get(Path(clip).name, "objects")].append(str(clip))
    return out


def weights_sha(label: str) -> str | None:
    """The sha256 of the weights shipped now under a ``pretrained:NAME`` label (with or without options), from the
    JSON beside them; None for any other label."""
    from training import pretrained
    name = label[len(pretrained.PREFIX):].split("?")[0] if label.startswith(pretrained.PREFIX) else None
    return pretrained.info(name).get("sha256") if name in pretrained.PRETRAINED else None


def score(models: list[tuple[str, str]], groups: dict[str, list[str]]) -> dict:
    """``evaluate_model`` of every model on every group (the baseline scored once per group)."""
    from training.bench import _lacking, load_models
    from training.evaluate import Baseline, EvalOptions, evaluate_model
    loaded = load_models(models, 4)  # every model, before any score: a bad spec fails at once
    shas = {label: weights_sha(label) for label, _ in loaded}  # what was loaded (its sha checked on loading)
    result: dict = {}
    for group, clips in groups.items():
        if not clips:
            continue
        base = Baseline("demod-jbu")
        result[group] = {"clips": [Path(c).name for c in clips], "models": {}, "notes": []}
        for label, model in loaded:
            lack = _lacking(label, model, clips)
            if lack:
                result[group]["notes"].append(lack)
                continue
            r = evaluate_model(model, clips, EvalOptions(flip=False, scale=4, baseline=base, label=label))
            result[group]["models"][label] = {"mean": r["mean"], "per_clip": r["per_clip"]}
            if shas[label]:
                result[group]["models"][label]["sha256"] = shas[label]
            print(f"{group} {label}: PSNR {r['mean']['psnr']:.2f} dB", file=sys.stderr)
    return result


def merged(paths: list[Path]) -> dict:
    """The results of earlier runs (their OUT.json) as one: per group, every file's models (a later file's row of
    a model replaces an earlier one's) and notes. ValueError naming the file when a group's clips differ, or when a
    shipped network's row scored other weights than those shipped now (``stale``)."""
    result: dict = {}
    for path in paths:
        try:
            doc = json.loads(path.read_text())
            for group, g in doc.items():
                have = result.setdefault(group, {"clips": g["clips"], "models": {}, "notes": []})
                if have["clips"] != g["clips"]:
                    raise ValueError(f"{path}: its {group} clips differ from those of {paths[0]}; scores of other "
                                     "clips do not merge")
                for label, row in g["models"].items():
                    stale(path, label, row)
                have["models"].update(g["models"])
                have["notes"] += [n for n in g["notes"] if n not in have["notes"]]
        except (json.JSONDecodeError, KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"{path}: not a worst_case.py OUT.json ({type(exc).__name__}: {exc})") from None
    return result


def stale(path: Path, label: str, row: dict) -> None:
    """ValueError naming ``path`` when the row of a shipped network (``pretrained:NAME``) does not say which weights
    it scored or scored others than those shipped now: its margins would be recorded and tabled for these."""
    now = weights_sha(label)
    if now is not None and row.get("sha256") != now:
        scored = f"weights {row['sha256'][:12]}" if row.get("sha256") else "weights it does not name (no sha256)"
        raise ValueError(f"{path}: its {label} row scored {scored}, not the {now[:12]} shipped now; score it again")


def check_whole(result: dict, groups: dict[str, list[str]], split: str) -> None:
    """ValueError unless every group of ``result`` holds exactly the clips of ``groups`` (the whole split now)."""
    for group in set(result) | {g for g, clips in groups.items() if clips}:
        want = sorted(Path(c).name for c in groups.get(group, []))
        if sorted(result.get(group, {}).get("clips", [])) != want:
            raise ValueError(f"--scores: their {group} clips are not the whole {split} split of the datasets now "
                             f"({len(result.get(group, {}).get('clips', []))} clips, the split has {len(want)}); "
                             "score again")


def without_scores(argv: list[str]) -> list[str]:
    """``argv`` less ``--scores`` and its files: the command that scored, as the record names it."""
    out, skipping = [], False
    for x in argv:
        if x == "--scores" or x.startswith("--scores="):
            skipping = x == "--scores"
            continue
        if skipping and not x.startswith("-"):
            continue
        skipping = False
        out.append(x)
    return out


def table(result: dict) -> str:
    lines = ["| data | model | PSNR (dB) | margin over demod-jbu | smallest per-clip margin (clip) | SSIM | tPSNR | "
             "artifact pixels | artifact pixels, worst clip | worst-1 % share |", "|" + "---|" * 10]
    for group, g in result.items():
        n = len(g["clips"])
        for label, r in g["models"].items():
            m = r["mean"]
            clip = Path(m["margin_min_clip"]).name if m.get("margin_min_clip") else ""
            f = (lambda k, fmt: "n/a" if m.get(k) is None else format(m[k], fmt))  # no baseline: no margin
            lines.append(f"| {group} ({n} clips) | `{label}` | {f('psnr', '.2f')} | {f('margin', '+.2f')} | "
                         f"{f('margin_min', '+.2f')} ({clip}) | {f('ssim', '.4f')} | {f('tpsnr', '.2f')} | "
                         f"{f('artifact_fraction', '.3%')} | {f('artifact_fraction_max', '.3%')} | "
                         f"{f('worst_share', '.0%')} |")
        for note in g["notes"]:
            lines.append(f"| {group} | {note} | | | | | | | | |")
    return "\n".join(lines)


def overall(result: dict, label: str) -> dict | None:
    """A model's margin over ``demod-jbu`` over every group it was scored on (frame-weighted), with each group's."""
    rows = [c for g in result.values() for c in g["models"].get(label, {}).get("per_clip", [])
            if c.get("baseline_psnr") is not None]
    if not rows:
        return None
    frames = sum(c["frames"] for c in rows)
    mean = (lambda k: sum(c[k] * c["frames"] for c in rows) / frames)
    return {"psnr": round(mean("psnr"), 4), "baseline_psnr": round(mean("baseline_psnr"), 4),  # 4: read at 2 as
            "margin": round(mean("psnr") - mean("baseline_psnr"), 4),                         # the tables print them
            "margin_min": round(min(c["margin"] for c in rows), 4), "frames": frames,
            "per_group": {g: round(r["models"][label]["mean"]["margin"], 4) for g, r in result.items()
                          if r["models"].get(label, {}).get("mean", {}).get("margin") is not None},
            "left_out": [n for r in result.values() for n in r["notes"] if f" {label}:" in n]}


def record(result: dict, datasets: list[Path], argv: list[str]) -> None:
    """Write each ``pretrained:NAME`` row's ``overall`` into the JSON beside its weights (``WORST_CASE_VAL``), with
    the sha256 of the weights it scored; a row of weights no longer shipped is left out with a line."""
    from gbuffer_export.clip import write_json_atomic
    from gbuffer_export.dataset.build import read_index
    from training import pretrained
    where = " + ".join(f"{read_index(d)['spec']['file']} val" for d in datasets)
    for label in {m for g in result.values() for m in g["models"]}:
        name = label[len(pretrained.PREFIX):] if label.startswith(pretrained.PREFIX) else None
        got = overall(result, label)
        if name not in pretrained.PRETRAINED or got is None:
            continue
        if not all(math.isfinite(v) for v in (got["margin"], got["margin_min"], *got["per_group"].values())):
            print(f"{label}: not recorded: a margin is not finite (a diverged network's frames)", file=sys.stderr)
            continue
        path = (pretrained.WEIGHTS_DIR / pretrained.PRETRAINED[name]).with_suffix(".json")
        doc = json.loads(path.read_text())
        scored = {g["models"][label].get("sha256") for g in result.values() if label in g["models"]}
        if scored != {doc.get("sha256")}:
            print(f"{path.name}: not recorded: {label} was scored on other weights than those shipped now",
                  file=sys.stderr)
            continue
        doc[pretrained.WORST_CASE_VAL] = pretrained.all_val_records(doc)  # other val sets' records stay
        doc[pretrained.WORST_CASE_VAL][where] = {
            "dataset": where, "sha256": doc.get("sha256"),
            "date": datetime.date.today().isoformat(),
            "command": "benchmarks/worst_case.py " + " ".join(shlex.quote(a) for a in argv), **got}
        write_json_atomic(path, doc)
        print(f"{path.name}: {pretrained.WORST_CASE_VAL} on {where}: margin {got['margin']:+.2f} dB", file=sys.stderr)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("datasets", type=Path, nargs="+")
    p.add_argument("--split", default="test")
    p.add_argument("--models", default="demod-bilinear,demod-jbu,pretrained:fusesr,pretrained:fusesr-l")
    p.add_argument("-o", dest="out", type=Path, help="OUT.json and OUT.md")
    p.add_argument("--scores", type=Path, nargs="+", metavar="OUT_JSON",
                   help="OUT.json of earlier runs on the same split (each group's clips the same in every file): "
                        "their models' scores, merged, are tabled (and recorded) instead of scoring again")
    p.add_argument("--record", action="store_true",
                   help="write each shipped network's val margin beside its weights (val split only)")
    argv = sys.argv[1:] if argv is None else list(argv)
    a = p.parse_args(argv)
    if a.record and a.split != "val":
        p.error("--record takes the val split only (the test split never chooses or marks)")
    from gbuffer_export.errors import BlendSRError
    from training.bench import parse_models
    try:
        if a.scores:
            result = merged(a.scores)
            check_whole(result, clip_groups(a.datasets, a.split), a.split)
        else:
            models = parse_models(a.models)  # a bad spec first: it costs nothing
            result = score(models, clip_groups(a.datasets, a.split))
    except (BlendSRError, OSError, ValueError) as exc:  # bad models, datasets or files: one line, exit 2
        print(f"blendsr: error: {exc}", file=sys.stderr)
        return 2
    text = table(result)
    print(text)
    if a.out:
        from gbuffer_export.clip import write_bytes_atomic  # a file cut short never passes for a score
        write_bytes_atomic(a.out.with_suffix(".json"), json.dumps(result, indent=1).encode())
        write_bytes_atomic(a.out.with_suffix(".md"), (text + "\n").encode())
    if a.record:
        record(result, a.datasets, without_scores(argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
