"""The data-scaling table: one model trained at equal steps on 1, 4, 16, ... and all training clips (or distinct
scenes) of a BlendSR dataset, evaluated on the dataset's test split (assets never seen in training), beside
demod-bilinear and demod-jbu; with several --steps, one run per count and step budget (each its own schedule).

    .venv/bin/python benchmarks/data_scaling.py DATASET -o runs/scaling [--counts 1,4,16,all] [--steps 500]
        [--by clip|scene] [--runs DIR] [--model fusesr] [--config benchmarks/pretrain.toml]

The subsets are nested: the training clips (``--by scene``: the index's scene ids, an asset, a built-in seed or a
level region, with all their clips) ordered by a stable hash of their ids, the first N of them. Each run is a plain
``blendsr train`` run in RUNS (default OUT; resumed when its folder exists, reused when finished) and each score a
plain ``evaluate_model`` on the test split (PSNR/SSIM on the evaluation tonemap, no FLIP), kept in RUNS/scores so
that an interrupted scoring resumes (``score_path``). Writes OUT/scaling.json,
OUT/scaling.md (the table, and per family group the margin's fit ``a + b log10(x)`` with what it predicts at 100x:
``extrapolation_lines``; the fits are also in the JSON: ``fits``) and OUT/scaling.png.

The subsets are taken from the planned train split, so they do not change while a dataset renders: a run trains
once all its clips are rendered (and valid), and the scores wait until every run is trained and the test split is
whole (exit 3 until then; rerun the same command, or pass ``--wait MINUTES`` to look again every MINUTES beside the
render: each run then trains as soon as its clips are). ``blendsr dataset ... --order mixed`` renders in the same
order, so the smallest subsets are ready first; ``--order train-first`` also finishes every subset before the
val and test splits, so that the largest run starts while they render. Processes may share ``--runs``: a run that
another one is training (it holds RUN/.lock) is waited for, not entered, so a second process with the same command
and ``--multiples 10 --train-only`` (no scores: it exits once its runs are trained) trains the largest run beside
the smaller ones, which the first process scores with the rest.

``--multiples 1,3,10`` sizes the nested subsets by HR pixels instead: the smallest prefix of the ordered groups
whose HR pixels (frames x width x height, from the index) reach each multiple of ``--unit-pixels`` (default: the
train split of examples/dataset_wide.toml, 13.9 million, what the shipped weights saw); a multiple the train split
cannot reach is refused (examples/dataset_scale.toml's train split plans 12.4 of them). Every score
is also given per family group of the index (``in-family``, ``held-out``) with its margin over ``demod-jbu``, and
for two sub-groups of ``held-out``: the clips that show an object asset, or a level, that no clip of the whole train
split shows (``held-out asset``, ``held-out level``: ``family_gap.content_groups``; the same clips for every run of
the curve, though a small run trains on fewer families). Added 2026-11-30, before any test score, because the issue's
acceptance is measured on real objects and levels never seen, and on val the unseen assets are where the networks
gain least (FuseSR-l's 1x run +0.53 dB over demod-jbu on 12 clips) and the unseen level where they gain most (+4.26).

The schedule rule of issue 54's scaling curve (written 2026-11-29, before any of its runs; every size the same):
``benchmarks/pretrain.toml`` (batch 8, LR crop 32, lr 5e-4, cosine to 2 %, 50 warm-up steps, seed 0), the same
step budget for 1x, 3x and 10x (``--steps 6000``: equal compute, so the curve measures the data, not the
optimisation), the last checkpoint scored (no choice per size), on the test split of examples/dataset_scale.toml
by family group, at 4x (``--scale 4``: the set also holds a 2x level); FuseSR and FuseSR-l, one thread each, two
runs side by side. Each run is scored twice (added 2026-11-29, before any score): as trained, and with the bound the
shipped weights of its name run with (``--score-options``: an inference option over the same weights, one more
curve), since the shipped networks are what a scaled training would replace. FuseSR-l's runs are also scored with
``lr-guided`` (added 2026-11-29, before any test score, chosen on the val split: on 41 val clips its 3x run gave
+2.13 dB over demod-jbu on the 17 held-out-family clips with ``lr-guided`` against +1.86 with ``lr-range``, smallest
clip +0.36 against +0.45, and +0.31 against +0.22 over all 41: docs/bench/scaling-families/val-bounds-fusesr-l.md),
so that the release can choose either bound by the val rule:

    .venv/bin/python benchmarks/data_scaling.py datasets/scale -o docs/bench/scaling-families/fusesr \
        --multiples 1,3,10 --steps 6000 --model fusesr --threads 1 --score-options residual_clamp=lr-guided --wait 10
    .venv/bin/python benchmarks/data_scaling.py datasets/scale -o docs/bench/scaling-families/fusesr-l \
        --multiples 1,3,10 --steps 6000 --model fusesr-l --threads 1 --wait 10 \
        --score-options 'residual_clamp=lr-range;residual_clamp=lr-guided'

Each family group's margin is given as its mean and its smallest clip; ``--score-options`` is checked before
any training. With ``--multiples`` the plot is the margin over demod-jbu per family group against the data size;
``--combine A/scaling.json B/scaling.json -o OUT`` puts both models' curves in one table and one plot, and writes
OUT/scaling.json with each fit and its 100x prediction (``fits``), the record the results page reads:

    .venv/bin/python benchmarks/data_scaling.py - -o docs/bench/scaling-families --combine \
        docs/bench/scaling-families/fusesr/scaling.json docs/bench/scaling-families/fusesr-l/scaling.json

``--list-clips`` prints the largest subset's clips (no training), so that a render finishes them and then the test
split before the rest of the set (the scores wait for nothing else):

    .venv/bin/python benchmarks/data_scaling.py datasets/scale -o - --multiples 1,3,10 --list-clips subset.txt
    blendsr dataset examples/dataset_scale.toml -o datasets/scale --workers 2 --clips '@subset.txt' --order mixed
    blendsr dataset examples/dataset_scale.toml -o datasets/scale --workers 2 --split test
    blendsr dataset examples/dataset_scale.toml -o datasets/scale --workers 2
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import hashlib
import math
import json
import shlex
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gbuffer_export.dataset.families import HELD_OUT, HELD_OUT_ASSET, HELD_OUT_LEVEL, IN_FAMILY  # noqa: E402

#: HR pixels of the train split of examples/dataset_wide.toml, what the shipped weights were trained on: 47 clips
#: (73 less 11 test and 15 val) of 8 frames at 256x144. One "x" of issue 54's scaling curve.
WIDE_TRAIN_HR_PIXELS = 47 * 8 * 256 * 144


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--counts", default="1,4,16,all",
                   help="numbers of training clips or scenes ('all' = the whole split)")
    p.add_argument("--multiples", default="",
                   help="sizes as multiples of --unit-pixels HR pixels instead of --counts")
    p.add_argument("--unit-pixels", type=float, default=WIDE_TRAIN_HR_PIXELS,
                   help="HR pixels of one multiple (default: the wide set's train split, %(default)d)")
    p.add_argument("--by", choices=("clip", "scene"), default="clip", help="what --counts counts")
    p.add_argument("--steps", default="500",
                   help="optimiser steps of every run; a comma list trains one run per budget")
    p.add_argument("--runs", type=Path, help="folder of the training runs (default: OUT)")
    p.add_argument("--model", default="fusesr")
    p.add_argument("--config", default=str(REPO / "benchmarks" / "pretrain.toml"))
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: the config's)")
    p.add_argument("--score-options", default="",
                   help="inference options each run is also scored with, ';'-separated variants of "
                        "KEY=VALUE[&KEY=VALUE] (e.g. residual_clamp=lr-guided, the shipped FuseSR's bound): one more "
                        "row per run and variant, its own curve")
    p.add_argument("--scale", type=int, default=4,
                   help="the upscaling factor every run trains on and is scored at (a dataset may hold several LR "
                        "levels: examples/dataset_scale.toml renders 4x and 2x)")
    p.add_argument("--wait", type=float, default=0.0, metavar="MINUTES",
                   help="while runs wait for clips or the test split is not whole: look again every MINUTES (a "
                        "run trains as soon as its clips are rendered) instead of exiting 3; 0: exit")
    p.add_argument("--train-only", action="store_true",
                   help="no scores: exit 0 once the runs are trained (with --wait, as their clips are rendered), "
                        "e.g. the largest run in a second process beside the one that trains and scores the curve")
    p.add_argument("--list-clips", nargs="?", const="-", metavar="FILE",
                   help="no training: write the clip ids of the largest subset (nested: it holds the others) to FILE "
                        "(UTF-8, one per line; none or '-': print them), for blendsr dataset ... --clips @FILE")
    p.add_argument("--combine", nargs="+", type=Path, metavar="SCALING_JSON",
                   help="no training: one table, one plot and one scaling.json (the rows with each run's size x, and "
                        "the fits) in OUT from these scaling.json (DATASET is not read)")
    return p


@dataclasses.dataclass
class Curve:
    """One curve's plan and what it has found so far: the arguments, the ordered training groups and the subset
    sizes (groups taken), the step budgets, the score variants (``""``: as trained), each clip's family group, and
    the train clips rendered and the test clips, read again on every pass of the wait."""
    a: argparse.Namespace
    groups: list[tuple[str, list[Path]]]
    counts: list[int]
    budgets: list[int]
    variants: list[str]
    family_of: dict[str, tuple[str, ...]]
    test_planned: int
    test_clips: list[str] = dataclasses.field(default_factory=list)
    done_train: set[Path] = dataclasses.field(default_factory=set)

    @property
    def runs(self) -> Path:
        return self.a.runs or self.a.output


def main(argv=None) -> int:
    a = build_parser().parse_args(argv)
    if a.combine:
        return combine(a.combine, a.output, argv)
    if a.list_clips:
        return list_clips(a)
    if a.wait < 0:
        print(f"data_scaling: --wait {a.wait:g}: minutes must be 0 (exit 3 while waiting) or more", file=sys.stderr)
        return 2
    try:
        curve = plan(a)
    except ValueError as exc:  # BlendSRError among them
        print(f"data_scaling: {exc}", file=sys.stderr)
        return 2
    a.output.mkdir(parents=True, exist_ok=True)
    if a.threads:
        import torch
        torch.set_num_threads(a.threads)
    fitted = wait_for_runs(curve, argv)
    if fitted is None:
        return 3
    if a.train_only:
        return 0
    rows = score_rows(curve, fitted)
    write_records(curve, rows, argv)
    print((a.output / "scaling.md").read_text())
    return 0


def plan(a: argparse.Namespace) -> Curve:
    """The curve ``a`` asks for; ValueError (one line, naming the flag or the file) on what would stop it later: a
    score variant the model does not take, a step budget that is not an integer, a dataset index it cannot read.
    Checked before any training."""
    from gbuffer_export.dataset.build import split_clips
    from training.config import load_config
    trained_as = load_config(a.config, [f'model.name="{a.model}"', f"model.scale={a.scale}"]).to_dict()
    variants = ["", *score_variants(a.score_options, trained_as)]
    try:
        budgets = [int(s) for s in a.steps.split(",")]
    except ValueError:
        raise ValueError(f"--steps {a.steps!r}: expected optimiser steps, comma-separated integers") from None
    groups, counts = subsets(a)
    return Curve(a, groups, counts, budgets, variants, family_groups(a.dataset),
                 len(split_clips(a.dataset, "test", done_only=False)),
                 [str(c) for c in split_clips(a.dataset, "test")])


def score(curve: Curve, spec: str) -> dict:
    """``spec`` (a baseline, or a checkpoint with options) on the test split: PSNR, SSIM, per clip and per family
    group, artifact pixels, and each group's smallest margin over demod-jbu (evaluate's baseline). Kept in
    ``score_path`` once computed, so that a scoring cut short resumes after the scores it finished; another process
    computing the same score (the baselines, shared by the curves of one ``--runs``) is waited for, then read."""
    from gbuffer_export.clip import write_json_atomic
    from gbuffer_export.locks import FolderLock
    path = score_path(curve, spec)
    path.parent.mkdir(parents=True, exist_ok=True)
    with FolderLock(path.parent, "", name=f".{path.stem}.lock", timeout=-1):
        if path.is_file():
            return json.loads(path.read_text())
        result = _score(curve, spec)
        write_json_atomic(path, result)
        return result


def score_path(curve: Curve, spec: str) -> Path:
    """RUNS/scores/DIGEST.json: one score, keyed by the checkpoint's bytes (a run trained again is scored again) or
    the baseline's name, the options, the test clips (each with its family groups, which the index may change
    without a render, and its manifest's bytes: a clip rendered again is scored again) and the scale; shared by the
    processes of one ``--runs``. Delete the folder to score again after a change to the evaluation."""
    from gbuffer_export.clip import MANIFEST
    from training.checkpoint import file_sha256
    weights, _, options = spec.partition("?")
    ident = file_sha256(weights) if Path(weights).is_file() else weights
    clips = sorted((str(Path(c).resolve()), sorted(curve.family_of.get(Path(c).name, ())),
                    file_sha256(Path(c) / MANIFEST)) for c in curve.test_clips)
    key = json.dumps([ident, options, clips, curve.a.scale])
    return curve.runs / "scores" / f"{hashlib.sha256(key.encode()).hexdigest()[:24]}.json"


def _score(curve: Curve, spec: str) -> dict:
    from training.evaluate import EvalOptions, evaluate_model, group_means
    from training.inference.loading import load_model
    a = curve.a
    r = evaluate_model(load_model(spec, a.scale), curve.test_clips, EvalOptions(flip=False, scale=a.scale))
    per_clip = {c: round(v["psnr"], 3) for c, v in group_means(r, metrics=("psnr",)).items()}
    by_family = {}
    for g in sorted({g for gs in curve.family_of.values() for g in gs}):  # a clip may count in several groups
        means = group_means(r, lambda c, g=g: g if g in curve.family_of.get(c, ()) else "", metrics=("psnr",))
        if g in means:
            by_family[g] = means[g]["psnr"]
    margins = {Path(c["clip"]).name: c["margin"] for c in r["per_clip"] if finite(c.get("margin")) is not None}
    return finite({"psnr": r["mean"]["psnr"], "ssim": r["mean"]["ssim"], "per_clip": per_clip,
                   "by_family": by_family, "artifact_pixels": r["mean"].get("artifact_pixels"),
                   "margin_min_by_family": smallest_margins(margins, curve.family_of)})


def finite(value):
    """``value`` with every non-finite float (the PSNR of a diverged run's NaN frames) None, through dicts: a score
    that is kept, tabled as n/a and left out of the margins and fits rather than failing after the test read."""
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    return None if isinstance(value, float) and not math.isfinite(value) else value


def fit(curve: Curve, n: int, steps: int, argv) -> tuple[list[Path], dict | None, Path]:
    """Train (or resume, or reuse) the run of the first ``n`` groups; None while any of its clips is unrendered, or
    while another process trains it (it holds RUN/.lock), so that processes sharing ``--runs`` split one curve."""
    from gbuffer_export.locks import FolderBusyError
    from training.config import load_config
    from training.train import train
    a = curve.a
    clips = [c for g in curve.groups[:n] for c in g[1]]
    run = curve.runs / (f"{a.model}_{n:03d}{a.by}s"
                        + (f"_{steps}steps" if len(curve.budgets) > 1 or a.by != "clip" else ""))
    waiting = [c for c in clips if c not in curve.done_train]
    if waiting:
        print(f"data_scaling: {run.name}: {len(waiting)} of its {len(clips)} clips are not rendered (or not "
              "valid) yet; it trains once they are (blendsr dataset ... --clips @FILE, FILE from this script's "
              "--list-clips, renders them first)")
        return clips, None, run
    overrides = [f'model.name="{a.model}"', f"model.scale={a.scale}", f"run.max_steps={steps}", "run.minutes=0"]
    if a.threads:
        overrides.append(f"run.threads={a.threads}")
    cfg = load_config(a.config, overrides)
    cfg.data.clips = [str(c) for c in clips]
    write_command(run, argv)
    done = run / "summary.json"
    if done.is_file() and json.loads(done.read_text()).get("step") == steps:
        return clips, json.loads(done.read_text()), run  # finished earlier: score it only
    try:
        summary = train(cfg, run, resume=(run / "checkpoints" / "last.pt").is_file())
    except FolderBusyError:  # another process of this curve trains it (say --multiples 10 beside 1,3): wait for it
        print(f"data_scaling: {run.name}: another process is training it; scored once it is finished", flush=True)
        return clips, None, run
    if summary.get("step") != steps:  # stopped early (a signal): not a point of the equal-compute curve
        raise SystemExit(f"data_scaling: {run.name} stopped at step {summary.get('step')} of {steps} "
                         f"({summary.get('stopped_by')}); rerun the same command to resume it")
    return clips, summary, run


def wait_for_runs(curve: Curve, argv) -> list | None:
    """Train each run as soon as its clips are rendered; (n, steps, clips, summary, run) per run once every run is
    trained and the test split is whole; None while not (without --wait) or when a needed clip is marked invalid."""
    from gbuffer_export.dataset.build import split_clips
    a = curve.a
    needed = {c.name for g in curve.groups[:max(curve.counts)] for c in g[1]} | {
        c.name for c in split_clips(a.dataset, "test", done_only=False)}
    while True:
        never = never_ready(a.dataset, needed)
        if never:
            print(f"data_scaling: {a.dataset}: {len(never)} clips the curve needs are marked invalid in the index "
                  f"({', '.join(never[:5])}{', ...' if len(never) > 5 else ''}); they never become ready: render "
                  "them again (blendsr validate says why) or take them out of the spec", file=sys.stderr)
            return None
        curve.done_train.clear()
        curve.done_train.update(split_clips(a.dataset, "train"))
        curve.test_clips[:] = [str(c) for c in split_clips(a.dataset, "test")]
        fitted = [(n, steps, *fit(curve, n, steps, argv)) for steps in curve.budgets for n in curve.counts]
        trained = all(summary is not None for *_, summary, _ in fitted)
        if trained and (a.train_only or len(curve.test_clips) == curve.test_planned):
            return fitted
        until = "--train-only: exits once every run is trained" if a.train_only else (
            "no scores until every run is trained and the test split is whole")
        print(f"data_scaling: {sum(s is not None for *_, s, _ in fitted)} of {len(fitted)} runs trained; test split "
              f"{len(curve.test_clips)} of {curve.test_planned} clips rendered: {until} "
              f"({f'again in {a.wait:g} min' if a.wait else 'rerun the same command'})", flush=True)
        if not a.wait:
            return None
        time.sleep(a.wait * 60)


def score_rows(curve: Curve, fitted: list) -> list[dict]:
    """The baselines' rows, then one row per run and score variant, each with its margin over demod-jbu per family
    group; printed as they come (JSON lines)."""
    a = curve.a
    rows = []
    for name in ("demod-bilinear", "demod-jbu"):
        rows.append({"model": name, "clips": 0, "steps": 0, **score(curve, name)})
        print(json.dumps(rows[-1]), flush=True)
    base = rows[-1]["by_family"]
    for (n, steps, clips, summary, run), opts in ((f, o) for f in fitted for o in curve.variants):
        spec = str(run / "checkpoints" / "last.pt") + (f"?{opts}" if opts else "")
        rows.append({"model": a.model + (f"?{opts}" if opts else ""), "clips": len(clips), a.by + "s": n,
                     "steps": summary["step"], "train_clips": [c.name for c in clips],
                     "elapsed_s": round(summary.get("elapsed_s", 0.0), 1), "hr_pixels": hr_pixels(a.dataset, clips),
                     **score(curve, spec)})
        rows[-1]["margin_by_family"] = {g: v - base[g] for g, v in rows[-1]["by_family"].items()
                                        if v is not None and base.get(g) is not None}
        print(json.dumps(rows[-1]), flush=True)
    return rows


def write_records(curve: Curve, rows: list[dict], argv) -> None:
    """OUT/scaling.json, OUT/scaling.md and OUT/scaling.png."""
    from gbuffer_export.clip import write_bytes_atomic, write_json_atomic
    a, out = curve.a, curve.a.output
    write_json_atomic(out / "scaling.json", {"dataset": str(a.dataset), "test_clips": curve.test_clips,
                                             "rows": sized_rows(rows, a.unit_pixels),
                                             "by": a.by, "scale": a.scale, "steps": curve.budgets,
                                             "config": a.config,
                                             "multiples": a.multiples or None, "unit_pixels": a.unit_pixels,
                                             "score_options": curve.variants[1:], "fits": fits(rows, a.unit_pixels),
                                             "command": command_line(argv)})
    write_bytes_atomic(out / "scaling.md", (report_table(rows, a.by, a.unit_pixels) + "\n"
                                            + "\n".join(extrapolation_lines(rows, a.unit_pixels)) + "\n").encode())
    if a.multiples:  # sized by HR pixels: the margins per family group against the data size
        plot_margins(rows, a.unit_pixels, out / "scaling.png")
    else:
        plot_psnr(rows, curve, out / "scaling.png")


def plot_psnr(rows: list[dict], curve: Curve, path: Path) -> None:
    """Without --multiples: test PSNR against the clips (or scenes, or steps) of each run, the baselines as lines."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    a, counts, budgets = curve.a, curve.counts, curve.budgets
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=120)
    learned = [r for r in rows if r["clips"]]
    x = "steps" if len(counts) == 1 and len(budgets) > 1 else a.by + "s"
    for label in dict.fromkeys(r["model"] for r in learned):
        for steps in (budgets if x != "steps" else [None]):
            pts = [r for r in learned if r["model"] == label and (steps is None or r["steps"] == steps)]
            ax.plot([r[x] for r in pts], [r["psnr"] for r in pts], "o-",
                    label=label + (f" ({steps} steps)" if steps else f" ({counts[0]} {a.by}s)"))
    for r, style in zip([r for r in rows if not r["clips"]], ("--", ":")):
        ax.axhline(r["psnr"], linestyle=style, color="grey", label=r["model"])
    ax.set_xscale("log")
    ax.set_xticks(sorted({r[x] for r in learned}), [str(v) for v in sorted({r[x] for r in learned})])
    ax.minorticks_off()
    ax.set_xlabel({"clips": "training clips", "scenes": "distinct training scenes", "steps": "optimiser steps"}[x])
    ax.set_ylabel("PSNR on unseen test assets (dB)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def subsets(a) -> tuple[list[tuple[str, list[Path]]], list[int]]:
    """The ordered training groups and the sorted subset sizes (groups taken) that ``--multiples`` or ``--counts``
    ask for."""
    try:
        multiples = [float(m) for m in a.multiples.split(",")] if a.multiples else []
        counts = [None if c == "all" else int(c) for c in a.counts.split(",")]
    except ValueError:
        flag, value = ("--multiples", a.multiples) if a.multiples else ("--counts", a.counts)
        raise ValueError(f"{flag} {value!r}: expected comma-separated numbers"
                         + ("" if a.multiples else " or 'all'")) from None
    groups = training_groups(a.dataset, a.by)
    if multiples:
        sized = pixel_prefixes(a.dataset, groups, multiples, a.unit_pixels)
        return groups, sorted({n for _, n, _ in sized})
    return groups, sorted({len(groups) if c is None else min(c, len(groups)) for c in counts})


def list_clips(a) -> int:
    """``--list-clips``: the largest subset's clip ids to FILE (atomically) or stdout; no torch. One line and exit 2
    for a folder that is not a dataset (its index is written by ``blendsr dataset SPEC -o DATASET --limit 0``)."""
    from gbuffer_export.errors import BlendSRError
    try:
        groups, counts = subsets(a)
    except BlendSRError as exc:
        print(f"data_scaling: {exc} (blendsr dataset SPEC -o DATASET --limit 0 writes the index, rendering nothing)",
              file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"data_scaling: {exc}", file=sys.stderr)
        return 2
    text = "".join(f"{c.name}\n" for _, clips in groups[:max(counts, default=0)] for c in clips)
    if a.list_clips == "-":
        sys.stdout.write(text)
        return 0
    from gbuffer_export.clip import write_bytes_atomic
    write_bytes_atomic(a.list_clips, text.encode("utf-8"))
    print(f"data_scaling: {a.list_clips}: {text.count(chr(10))} clips", file=sys.stderr)
    return 0


def margin_series(rows: list[dict], unit: float) -> list[dict]:
    """One curve per model (a scored variant is its own: ``MODEL?OPTIONS``), step budget (``steps``, given when the
    rows hold several) and family group of ``rows`` (those with HR pixels and margins): ``xs``, the data sizes as
    multiples of ``unit``, and ``ys``, the margins over demod-jbu (dB), sorted by size. What the plot draws and
    ``fits`` fits."""
    learned = [r for r in rows if r.get("hr_pixels") and r.get("margin_by_family")]
    budgets = sorted({r.get("steps") for r in learned})
    out = []
    for model, steps, group in ((m, n, g) for m in dict.fromkeys(r["model"] for r in learned) for n in budgets
                                for g in sorted({g for r in learned for g in r["margin_by_family"]})):
        pts = sorted((r["hr_pixels"] / unit, r["margin_by_family"][group]) for r in learned
                     if r["model"] == model and r.get("steps") == steps and group in r["margin_by_family"])
        if pts:
            out.append({"model": model, **({"steps": steps} if len(budgets) > 1 else {}), "group": group,
                        "xs": [x for x, _ in pts], "ys": [y for _, y in pts]})
    return out


def sized_rows(rows: list[dict], unit: float) -> list[dict]:
    """The rows as scaling.json keeps them: each run's with its size ``x`` in multiples of ``unit``."""
    return [{**r, "x": r["hr_pixels"] / unit} if r.get("hr_pixels") else r for r in rows]


def curve_label(series: dict, model: bool = True) -> str:
    """A curve's model (without ``model``: nothing), with its step budget when the rows hold several."""
    return (series["model"] if model else "") + (f" ({series['steps']} steps)" if "steps" in series else "")


#: The plot's line per family group (held-out solid, in-family dashed, its unseen assets dash-dotted, levels dotted).
GROUP_STYLE = {IN_FAMILY: "s--", HELD_OUT: "o-", HELD_OUT_ASSET: "^-.", HELD_OUT_LEVEL: "v:"}


def plot_margins(rows: list[dict], unit: float, path: Path) -> list[dict]:
    """The scaling plot: per model and family group, the mean margin over demod-jbu (dB; demod-jbu is the 0 line)
    against the training data in multiples of ``unit`` HR pixels, log x, one line style per group (``GROUP_STYLE``).
    Returns the series drawn (``margin_series``)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    series = margin_series(rows, unit)
    fig, ax = plt.subplots(figsize=(8.0, 3.8), dpi=120)
    colors = {}
    for c in series:
        color = colors.setdefault(curve_label(c), f"C{len(colors)}")
        ax.plot(c["xs"], c["ys"], GROUP_STYLE.get(c["group"], "o-"), color=color,
                label=f"{curve_label(c)}, {c['group']}")
    ax.axhline(0.0, color="grey", linestyle=":", label="demod-jbu")
    ax.set_xscale("log")
    ticks = sorted({x for c in series for x in c["xs"]})
    ax.set_xticks(ticks, [f"{x:.1f}x" for x in ticks])
    ax.minorticks_off()
    ax.set_xlabel(f"training data (x {unit / 1e6:.1f} M HR pixels)")
    ax.set_ylabel("margin over demod-jbu, test (dB)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the axes: many curves
    ax.grid(alpha=0.3)
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(tmp, bbox_inches="tight")
    plt.close(fig)
    tmp.replace(path)
    return series


def combine(records: list[Path], out: Path, argv=None) -> int:
    """``--combine``: one table, one set of fits and one plot from several scaling.json (FuseSR's and FuseSR-l's
    curves side by side; the baselines' rows once) into OUT/scaling.md, OUT/scaling.png and OUT/scaling.json (the
    rows, each run's size ``x`` in multiples of the unit, and ``fits``: the records the results page reads)."""
    rows, seen, unit, by, first = [], set(), None, "clip", None
    for rec in records:
        try:
            data = json.loads(Path(rec).read_text())
            unit = unit or float(data["unit_pixels"])
            by = data.get("by", by)
            new = [r for r in data["rows"] if r["clips"] or r["model"] not in seen]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            print(f"data_scaling: {rec}: not a scaling.json of data_scaling.py --multiples ({exc})", file=sys.stderr)
            return 2
        same = {k: data.get(k) for k in ("dataset", "test_clips", "unit_pixels", "by", "scale")}
        first = first or (rec, same)
        differ = [k for k in same if same[k] != first[1][k]]
        if differ:
            print(f"data_scaling: {rec}: its {', '.join(differ)} differ from {first[0]}'s: the curves are not "
                  "comparable", file=sys.stderr)
            return 2
        seen |= {r["model"] for r in new if not r["clips"]}
        rows += new
    if any(Path(rec).resolve() == (out / "scaling.json").resolve() for rec in records):
        print(f"data_scaling: {out / 'scaling.json'}: --combine would overwrite one of its inputs; give another -o",
              file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    from gbuffer_export.clip import write_bytes_atomic, write_json_atomic
    write_bytes_atomic(out / "scaling.md", (report_table(rows, by, unit) + "\n"
                                            + "\n".join(extrapolation_lines(rows, unit)) + "\n").encode())
    write_json_atomic(out / "scaling.json", {**first[1], "sources": [str(r) for r in records],
                                             "rows": sized_rows(rows, unit),
                                             "fits": fits(rows, unit), "command": command_line(argv)})
    plot_margins(rows, unit, out / "scaling.png")
    print((out / "scaling.md").read_text())
    return 0


def log_fit(xs: list[float], ys: list[float]) -> tuple[float, float] | None:
    """Least-squares ``y = a + b log10(x)`` through the points: (a, b), or None with fewer than two distinct x. The
    usual form of a data-scaling curve over a decade or two (quality gains a constant amount per tenfold data); what
    it says about 100x is an extrapolation, a guess to be checked, not a measurement."""
    import numpy as np
    if len(set(xs)) < 2:
        return None
    b, a = np.polyfit(np.log10(np.asarray(xs, float)), np.asarray(ys, float), 1)
    return float(a), float(b)


def fits(rows: list[dict], unit: float, at: float = 100.0) -> list[dict]:
    """Per curve of ``margin_series`` with two or more sizes: the fit ``margin = a + b log10(x)`` of the margin over
    demod-jbu (dB) against the data size ``x`` (multiples of ``unit``), the sizes it spans and what it predicts at
    ``at`` x (an extrapolation). The records behind ``extrapolation_lines`` and the results page."""
    out = []
    for c in margin_series(rows, unit):
        line = log_fit(c["xs"], c["ys"])
        if line is None:
            continue
        a, b = (round(v, 6) + 0.0 for v in line)  # no "-0.00"
        out.append({"model": c["model"], **({"steps": c["steps"]} if "steps" in c else {}), "group": c["group"],
                    "a": a, "b": b, "sizes": len(set(c["xs"])), "x_min": c["xs"][0], "x_max": c["xs"][-1],
                    "at": at, "predicted": a + b * math.log10(at)})
    return out


def extrapolation_lines(rows: list[dict], unit: float, at: float = 100.0) -> list[str]:
    """``fits`` in words: per model and family group, the fit, its gain per tenfold data and what it predicts at
    ``at`` x. The lines name the model only when there are several."""
    labels = {r["model"] for r in rows if r.get("hr_pixels") and r.get("margin_by_family")}
    lines = [f"- {f'`{curve_label(c)}` ' if len(labels) > 1 else ''}{c['group']}"
             f"{curve_label(c, model=False) if len(labels) <= 1 else ''}: scored at one size ({c['xs'][0]:.1f}x), "
             "no fit" for c in margin_series(rows, unit) if len(set(c["xs"])) < 2]
    for f in fits(rows, unit, at):
        name = f"`{curve_label(f)}` {f['group']}" if len(labels) > 1 else f["group"] + curve_label(f, model=False)
        lines.append(f"- {name}: margin = {f['a']:+.2f} {f['b']:+.2f} log10(x) dB over {f['sizes']} sizes "
                     f"({f['x_min']:.1f}x to {f['x_max']:.1f}x): {f['b']:+.2f} dB per tenfold data; at {at:g}x it "
                     f"predicts {f['predicted']:+.2f} dB (an extrapolation)")
    return lines


def report_table(rows: list[dict], by: str, unit: float) -> str:
    """scaling.md: per run its size (groups, clips, HR pixels as multiples of ``unit``), steps, test PSNR and SSIM,
    the margin over demod-jbu per family group (mean, and its smallest clip), and the per-clip PSNR."""
    lines = [f"| training data | {by}s | clips | x (HR pixels) | steps | test PSNR (dB) | test SSIM | margin in-family "
             "(smallest) | margin held-out (smallest) | of which unseen assets | of which unseen levels | per test "
             "clip (dB) |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    num = (lambda v, fmt: "n/a" if v is None else format(v, fmt))  # noqa: E731  (a diverged run's NaN: None)
    for r in rows:
        per = ", ".join(f"{k} {num(v, '.2f')}" for k, v in r["per_clip"].items())
        m, lo = r.get("margin_by_family", {}), r.get("margin_min_by_family", {})
        cell = lambda g: (f"{m[g]:+.2f}" + (f" ({lo[g]:+.2f})" if g in lo else "")) if g in m else "-"  # noqa: E731
        x = f"{r['hr_pixels'] / unit:.2f}" if r.get("hr_pixels") else "-"
        lines.append(f"| {r['model']} | {r.get(by + 's', '-')} | {r['clips'] or '-'} | {x} | {r['steps'] or '-'} | "
                     f"{num(r['psnr'], '.2f')} | {num(r['ssim'], '.4f')} | {cell(IN_FAMILY)} | {cell(HELD_OUT)} | "
                     f"{cell(HELD_OUT_ASSET)} | {cell(HELD_OUT_LEVEL)} | {per} |")
    return "\n".join(lines) + "\n"


def never_ready(dataset: Path, needed: set[str]) -> list[str]:
    """The clips of ``needed`` (folder names) that the index marks ``invalid``: ``split_clips`` leaves them out for
    good, so a run or the test split waiting for them would wait forever."""
    from gbuffer_export.dataset.build import read_index
    return sorted(Path(c["path"]).name for c in read_index(dataset)["clips"]
                  if c.get("invalid") and Path(c["path"]).name in needed)


def write_command(run: Path, argv) -> None:
    """RUN/command.txt: the command that trains the run (this script's, which also sizes its subset), for
    benchmarks/release_weights.py (``--run MODEL=RUN --script ''``); kept when the run resumes."""
    from training.run import write_text_atomic
    path = run / "command.txt"
    if not path.is_file():
        run.mkdir(parents=True, exist_ok=True)
        write_text_atomic(path, command_line(argv) + "\n")


def command_line(argv) -> str:
    """This script's command line as a shell would take it (``argv``: its arguments; None: ``sys.argv``'s)."""
    words = list(sys.argv[1:] if argv is None else argv)
    return shlex.join([".venv/bin/python", "benchmarks/data_scaling.py", *words])


def score_variants(text: str, config: dict) -> list[str]:
    """``--score-options``: the ';'-separated variants (KEY=VALUE pairs joined by '&'), each checked before any
    training (a typo must not wait for hours of it) as loading the weights will check it: against ``config``, the
    runs' configuration as a dict (``checked_inference_options``: inference options only, valid values)."""
    from training.inference.loading import checked_inference_options, split_spec
    out = []
    for v in (v.strip() for v in text.split(";") if v.strip()):
        try:
            _, items = split_spec(f"run?{v}")
            checked_inference_options(config, items, f"--score-options {v!r}")
        except ValueError as exc:  # BlendSRError, ConfigError: one line
            raise ValueError(f"--score-options {v!r}: {exc}") from None
        out.append(v)
    return out


def smallest_margins(margins: dict[str, float], family_of: dict[str, tuple[str, ...]]) -> dict:
    """{family group: the smallest of its clips' margins over demod-jbu} (``margins``: clip name -> dB, as
    ``evaluate_model`` gives them; ``family_of``: clip name -> the groups it counts in): the worst case beside each
    group's mean margin."""
    out: dict[str, float] = {}
    for clip, m in margins.items():
        for g in family_of.get(clip, ()):
            out[g] = min(out.get(g, math.inf), m)
    return out


def family_groups(dataset: Path) -> dict[str, tuple[str, ...]]:
    """{clip folder name: the family groups it counts in} from the index: its group (``in-family`` where the index
    has none; ``family_gap.index_groups``), then, for a held-out clip that shows an object asset or a level that no
    clip of the train split shows, ``held-out asset`` or ``held-out level`` (``family_gap.content_groups``)."""
    from gbuffer_export.dataset.family_gap import content_groups, index_families, index_groups, index_trained_families
    groups = index_groups(dataset)
    sub = content_groups(index_families(dataset), groups, index_trained_families(dataset))
    return {c: (g, *sub.get(c, ())) for c, g in groups.items()}


@functools.lru_cache(maxsize=4)
def _pixels_of(dataset: Path) -> dict[str, int]:
    from gbuffer_export.dataset.build import read_index
    return {Path(c["path"]).name: int(c["render"]["frames"]) * c["render"]["hr_size"][0] * c["render"]["hr_size"][1]
            for c in read_index(dataset)["clips"]}


def hr_pixels(dataset: Path, clips) -> int:
    """HR pixels of ``clips`` (folders of ``dataset``): frames planned x width x height, from the index (a subset is
    sized before it is rendered)."""
    pixels = _pixels_of(Path(dataset))
    return sum(pixels.get(Path(c).name, 0) for c in clips)


def pixel_prefixes(dataset: Path, groups, multiples, unit: float) -> list[tuple[float, int, int]]:
    """(multiple, groups taken, HR pixels) per multiple: the smallest prefix of ``groups`` (ordered) whose HR pixels
    reach ``multiple * unit``. SystemExit naming the dataset when the whole train split holds fewer."""
    total, cum = 0, []
    for _, clips in groups:
        total += hr_pixels(dataset, clips)
        cum.append(total)
    out = []
    for m in multiples:
        need = m * unit
        n = next((i + 1 for i, v in enumerate(cum) if v >= need), None)
        if n is None:
            raise SystemExit(f"{dataset}: its train split holds {total:,} HR pixels, fewer than {m:g} x {unit:,.0f}")
        out.append((m, n, cum[n - 1]))
    return out


def training_groups(dataset: Path, by: str) -> list[tuple[str, list[Path]]]:
    """The planned train split (rendered or not) as (id, clips) groups in the mixed order of their ids
    (``spec.mixed_rank``, the order ``blendsr dataset --order mixed`` renders in): one group per clip, or per scene
    id of the index (``by="scene"``)."""
    from gbuffer_export.dataset.build import read_index, split_clips
    from gbuffer_export.dataset.spec import mixed_rank
    clips = split_clips(dataset, "train", done_only=False)
    if by == "clip":
        keyed = {c.name: [c] for c in clips}
    else:
        scene_of = {Path(c["path"]).name: str(c.get("scene_id") or Path(c["path"]).name)
                    for c in read_index(dataset)["clips"]}
        keyed = {}
        for c in clips:
            keyed.setdefault(scene_of.get(c.name, c.name), []).append(c)
    return sorted(keyed.items(), key=lambda kv: mixed_rank(kv[0]))


if __name__ == "__main__":
    sys.exit(main())
