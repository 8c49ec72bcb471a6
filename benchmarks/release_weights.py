"""Score trained runs and the baselines on a dataset's val and test splits and write the shipped float16 weights.

    .venv/bin/python benchmarks/release_weights.py DATASET RUNS [--models fusesr,fusesr-l] [--script S]

Expects RUNS/<model with _ for -> (``benchmarks/pretrain.sh`` makes fusesr and fusesr_l, ``benchmarks/zoo.sh`` the
seed networks, each with RUNS/<run>/command.txt, the training command). Writes training/weights/<PRETRAINED file>
(.safetensors and .json: the file's sha256, dataset spec and index digest, commands, scores of the model and of
bicubic, demod-bilinear and demod-jbu on the same test clips, and on the val clips when the dataset has a val split:
the scenes that choose between trainings, while the test assets only report) and RUNS/release.json.

With a val split, a run replaces the shipped weights of its name only when ``training.selection.choose`` says so
(the worst-case rule: the smallest per-clip margin over demod-jbu does not fall, artifact pixels do not rise, mean
PSNR, SSIM and tPSNR do not fall, all on val); ``--force`` writes them anyway (the JSON records the verdict).
The val clips the rule reads are the held-out-family ones when the index has any (``--val-group auto``, issue 54:
a network is chosen by what it does on families it never trained on), less those whose every family the shipped
weights' recorded lineage, or the candidate's, holds (``unseen_val_clips``: they would favour the network that saw
them), else all of them;
``--val-group all`` or ``held-out`` forces one. The JSON records which (``val_group``, ``val_clips``,
``val_clips_left_out``).

``--options MODEL?KEY=VALUE[&...]`` scores a run with inference options (``INFERENCE_OPTIONS``, e.g.
``fusesr?residual_clamp=lr-guided``: a bound over the same weights) and writes them into the released weights'
configuration, so what the val rule chose is what ships.

``--defer-test`` releases by the val rule without reading the test split: the JSON says so under ``test_split``
(``TEST_DEFERRED``) and has no test scores. A round whose test split is read once, at its end (docs/training.md,
"The scale set's round"), releases that way and later runs ``--record-test``: the shipped weights of ``--models`` and
the baselines scored on the whole test split, written into their JSONs (the weights do not change).
"""
from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import shlex
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from training.pretrained import TEST_DEFERRED, test_deferred as deferred  # noqa: E402  (the weights JSON's keys)


def commands(a, index: dict, name: str, run: Path, steps: int) -> list[str]:
    """The commands that remake the weights of ``name``: the script's (none with ``--script ''``: the run's
    command.txt is the whole command, as benchmarks/data_scaling.py writes it), then the training command (the run's
    command.txt, written by benchmarks/zoo.sh, else benchmarks/pretrain.sh's form)."""
    cmd = run / "command.txt"
    generic = (f"blendsr train --model {name} --data {a.dataset} -o {run} --config benchmarks/pretrain.toml "
               f"--max-steps {steps} --set run.threads=1")
    if not a.script:
        return [*earlier_stages(run), cmd.read_text().strip()] if cmd.is_file() else [generic]
    if a.script == "benchmarks/pretrain.sh":
        spec = "" if "SPEC=" in (a.env or "") else f"SPEC={index['spec']['file']} "  # --env may name it already
        script = f"{spec}{a.env + ' ' if a.env else ''}benchmarks/pretrain.sh {a.dataset} {a.runs}"
    elif a.script == "benchmarks/zoo.sh":
        script = f"MODELS={name} {a.script} {a.dataset} {a.runs}"
    else:
        script = f"{a.env + ' ' if a.env else ''}{a.script} {a.dataset} {a.runs}"
    if cmd.is_file():
        return [script, *earlier_stages(run), cmd.read_text().strip()]
    return [script, generic]


def run_config(run: Path) -> dict:
    """RUN/config.toml (``blendsr train`` writes it in every run) as a dict; {} without one; ValueError (one line)
    when it is not TOML."""
    import tomllib
    cfg = run / "config.toml"
    try:
        return tomllib.loads(cfg.read_text()) if cfg.is_file() else {}
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{cfg}: not TOML ({exc})") from None


def shipped_json(spec: str, weights_dir: Path) -> Path | None:
    """The JSON beside the shipped weights a ``pretrained:NAME[?options]`` spec names, when they are installed; None
    for any other spec."""
    from training.pretrained import PRETRAINED
    name = spec.partition(":")[2].partition("?")[0]
    js = (weights_dir / PRETRAINED.get(name, "-")).with_suffix(".json")
    return js if spec.startswith("pretrained:") and js.is_file() else None


def init_of(run: Path) -> str:
    """The ``run.init_from`` of the run's training command (command.txt), else of its configuration (config.toml),
    else ""."""
    cmd = run / "command.txt"
    words = shlex.split(cmd.read_text()) if cmd.is_file() else []
    init = next((w.partition("=")[2].strip('"') for w in words if w.startswith("run.init_from=")), "")
    return init or str(run_config(run).get("run", {}).get("init_from") or "")


def earlier_stages(run: Path) -> list[str]:
    """The training commands of the runs this one started from, first stage first (``stage_runs``); a stage without
    command.txt is named by its configuration."""
    return [(r / "command.txt").read_text().strip() if (r / "command.txt").is_file() else
            f"blendsr train -o {r} --config {r / 'config.toml'}  # (no command.txt: the stage's configuration)"
            for r in stage_runs(run)[:-1]]


def shipped_origin(runs: list[Path], weights_dir: Path) -> dict | None:
    """What the first stage of ``runs`` (first stage first) started from when that is shipped weights
    (``pretrained:NAME``): their sha256, step and commands, read from the JSON beside them before they are replaced,
    so the chain of fine-tunes stays on record; None otherwise."""
    init = init_of(runs[0])
    js = shipped_json(init, weights_dir)
    if js is None:
        return None
    old = json.loads(js.read_text())
    return {"weights": f"{init} as shipped before this release (sha256 below; git history of {js.name})",
            "sha256": old.get("sha256"), "step": old.get("step"), "commands": old.get("commands"),
            # their own lineage, so that family_gap.lineage_stages reads every stage, not only the last two
            **{k: old[k] for k in ("dataset", "init_from") if k in old}}


def recorded_init(run: Path, loaded: dict) -> dict:
    """What the run's first stage read through ``run.init_from`` (``training.train.init_record``, in every checkpoint
    since 2026-11-29), else RUN/init.json (the same keys, written by hand for a run from before the record, with the
    evidence), else {}."""
    if loaded.get("init"):
        return loaded["init"]
    js = run / "init.json"
    return json.loads(js.read_text()) if js.is_file() else {}


def check_origin(run: Path, loaded: dict, weights_dir: Path) -> None:
    """ValueError (one line) when the run started from ``pretrained:NAME`` weights other than those shipped now
    (``recorded_init``: neither their sha256 nor, the same tensors under another header, their ``param_digest``
    agree): a release made after it started replaced them, so the JSON would name the wrong origin and lineage.
    Nothing recorded: a note (the release assumes the weights shipped now)."""
    from training.checkpoint import load_checkpoint
    first = stage_runs(run)[0]
    spec = init_of(first)
    js = shipped_json(spec, weights_dir)
    if js is None:
        return
    init = recorded_init(first, loaded if first == run else load_checkpoint(first / "checkpoints" / "last.pt"))
    shipped = json.loads(js.read_text())
    if not init.get("sha256"):
        print(f"note: {first}: what its {spec} was is not recorded (no init in its checkpoint, no init.json): the "
              f"release takes it for the {js.name} shipped now", file=sys.stderr)
    elif init["sha256"] != shipped.get("sha256") and (
            not init.get("param_digest") or init["param_digest"] != shipped.get("param_digest")):
        raise ValueError(f"{run}: it started from {spec} with sha256 {init['sha256'][:16]}..., but the shipped "
                         f"{js.name} is now {str(shipped.get('sha256'))[:16]}... (a release after it started, or "
                         "this run's own): fine-tune again from the shipped weights")


def candidate_families(dataset: Path, runs: list[Path], loaded: dict, weights_dir: Path) -> set[str]:
    """The families a candidate trained on: those of the clips of every stage of its own (``runs``, first stage
    first; the last one's clips from its checkpoint ``loaded``; each clip's families from the index of the dataset it
    lies in, else ``dataset``'s), and, when its first stage started from ``pretrained:NAME``, that network's
    recorded lineage (``family_gap.lineage_families``; ``check_origin`` makes sure it is the one shipped now)."""
    from gbuffer_export.dataset.family_gap import index_families, lineage_families
    clips = list((loaded.get("config") or {}).get("data", {}).get("clips") or [])
    for r in runs[:-1]:
        clips += run_config(r).get("data", {}).get("clips", [])
    indexes: dict[Path, dict] = {}
    out: set[str] = set()
    for c in clips:
        root = Path(c).parent.parent if (Path(c).parent.parent / "dataset.json").is_file() else dataset
        families = indexes.setdefault(root, index_families(root))
        out |= families.get(Path(c).name, set())
    js = shipped_json(init_of(runs[0]), weights_dir)
    if js is not None:
        try:
            out |= lineage_families(js, REPO)[0]
        except ValueError as exc:
            print(f"note: {exc}; the candidate's inherited lineage is not counted", file=sys.stderr)
    return out


def stage_runs(run: Path) -> list[Path]:
    """The run directories of a fine-tune in stages, first stage first, ending with ``run``."""
    init = init_of(run)
    prev = Path(init).parent.parent
    if not init.endswith(".pt") or not any((prev / f).is_file() for f in ("command.txt", "config.toml")) \
            or prev.resolve() == run.resolve():
        return [run]
    return [*stage_runs(prev), run]


def config_of(run: Path) -> str:
    """The --config of the run's training command (command.txt), else benchmarks/pretrain.toml."""
    cmd = run / "command.txt"
    words = shlex.split(cmd.read_text()) if cmd.is_file() else []
    return words[words.index("--config") + 1] if "--config" in words else "benchmarks/pretrain.toml"


#: What the scores in a weights JSON measure (``evaluate``, ``summary``).
METRIC = "PSNR/SSIM on the evaluation tonemap (docs/training.md), no FLIP"


def evaluate(spec: str, clips: list[str]) -> dict:
    """``evaluate_model`` of ``spec`` (at 4x, no FLIP) on ``clips``, with the demod-jbu baseline the rule reads."""
    from training.evaluate import EvalOptions, evaluate_model
    from training.inference.loading import load_model
    return evaluate_model(load_model(spec, 4), clips, EvalOptions(flip=False, scale=4))


def summary(r: dict) -> dict:
    """The scores of an ``evaluate`` result kept in a weights JSON: means, per-clip PSNR, worst case."""
    from training.evaluate import group_means
    per = {c: round(v["psnr"], 3) for c, v in group_means(r, metrics=("psnr",)).items()}
    m = r["mean"]
    return {"psnr": round(m["psnr"], 3), "ssim": round(m["ssim"], 4), "psnr_hdr": round(m["psnr_hdr"], 3),
            "tpsnr": m.get("tpsnr"), "per_clip": per, "frames": m["frames"], "margin_min": m.get("margin_min"),
            "artifact_pixels": m.get("artifact_pixels")}


def check_round(a, name: str, spec_sha256: str) -> None:
    """ValueError (one line) for a release that would read the test split of a round that defers it: the shipped
    weights of ``name`` came from this dataset's spec with ``--defer-test`` (``--defer-test`` or ``--force`` pass)."""
    from training.pretrained import WEIGHTS_DIR
    js = shipped_json(f"pretrained:{name}", WEIGHTS_DIR)
    doc = json.loads(js.read_text()) if js else {}
    if (not a.defer_test and not a.force and deferred(doc)
            and doc.get("dataset", {}).get("spec_sha256") == spec_sha256):
        raise ValueError(f"{js}: its round defers the test split (released with --defer-test from this dataset's "
                         "spec): pass --defer-test, or --record-test at the round's end")


#: ``--val-group`` choices: ``auto`` = ``held-out`` when the val split has held-out-family clips, else ``all``.
VAL_GROUPS = ("auto", "all", "held-out")


def rule_val_clips(dataset: Path, val: list[str], group: str) -> tuple[list[str], str]:
    """The val clips the val rule reads and the group they are (``all`` or ``held-out``): ``val`` (the finished val
    clips) filtered by each clip's ``family_group`` in the dataset's index. The group follows the planned split, not
    what is finished: ValueError (one line) when a planned held-out-family val clip is not finished (the rule would
    read a part of them, or fall back to in-family clips), or when ``held-out`` is asked and the split plans none."""
    from gbuffer_export.dataset.build import read_index
    from gbuffer_export.dataset.families import HELD_OUT
    if group not in VAL_GROUPS:
        raise ValueError(f"--val-group {group!r}: choose one of {', '.join(VAL_GROUPS)}")
    if group == "all":
        return list(val), "all"
    planned = {Path(c["path"]).name for c in read_index(dataset)["clips"]
               if c.get("split") == "val" and c.get("family_group") == HELD_OUT}
    held = [c for c in val if Path(c).name in planned]
    if planned and len(held) < len(planned):
        raise ValueError(f"{dataset}: {len(planned) - len(held)} of its {len(planned)} held-out-family val clips are "
                         "not finished (or not valid): wait for the render, or pass --val-group all")
    if held:
        return held, HELD_OUT
    if group == HELD_OUT:
        raise ValueError(f"{dataset}: --val-group held-out, but the index plans no held-out-family val clip "
                         "(declare val_families in the spec's [splits])")
    return list(val), "all"


def unseen_val_clips(dataset: Path, val: list[str], group: str, weights_json: Path,
                     candidate: set[str] = frozenset()) -> tuple[list[str], list[str]]:
    """(the rule's val clips that neither network trained on every family of, the others): with the ``held-out``
    group, a clip whose every family the shipped network's recorded training lineage (``family_gap.lineage_families``;
    the wide set trained the shipped networks on the room level and most HDRIs) holds, or the ``candidate``'s
    (``candidate_families``) holds, would favour the network that saw it, so the rule reads only the others. Other
    groups, or no shipped weights: all of ``val``; a JSON without a lineage (said on stderr): only the candidate's
    counts. ValueError (one line) when no clip is left."""
    if group != "held-out" or not weights_json.is_file():
        return list(val), []
    from gbuffer_export.dataset.family_gap import index_families, lineage_families
    try:
        seen, notes = lineage_families(weights_json, REPO)
    except ValueError as exc:
        seen, notes = set(), [f"{exc}; only the candidate's own lineage counts"]
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    families = index_families(dataset)
    known = [c for c in val if families.get(Path(c).name)
             and (families[Path(c).name] <= seen or families[Path(c).name] <= set(candidate))]
    kept = [c for c in val if c not in known]
    if not kept:
        raise ValueError(f"{dataset}: the shipped {weights_json.name} or the candidate trained on every family of "
                         f"all {len(val)} held-out-family val clips; the rule has no unseen clip (--val-group all)")
    return kept, known


def named_runs(items: list[str], models: list[str]) -> dict[str, Path]:
    """``--run MODEL=DIR`` values -> {MODEL: DIR}; ValueError (one line) for another model or a folder without
    checkpoints/last.pt."""
    out = {}
    for item in items:
        name, sep, folder = item.partition("=")
        if not sep or name not in models:
            raise ValueError(f"--run {item!r}: expected MODEL=DIR with MODEL one of --models ({', '.join(models)})")
        if name in out:
            raise ValueError(f"--run {item!r}: {name} is given twice")
        if not (Path(folder) / "checkpoints" / "last.pt").is_file():
            raise ValueError(f"--run {item!r}: {folder} holds no checkpoints/last.pt")
        out[name] = Path(folder)
    return out


def trained_on(ck: dict, split: list[str]) -> list[str]:
    """The clip names a run trained on: its configuration's ``data.clips`` (a subset such as a scaling run's), else
    the dataset's train split ``split``."""
    clips = (ck.get("config") or {}).get("data", {}).get("clips") or []
    return [Path(c).name for c in clips] or split


def option_note(candidate: dict, incumbent: dict, name: str) -> str | None:
    """A line when the candidate's inference options (``INFERENCE_OPTIONS`` of its ``[model.NAME]``, configurations
    as dicts; a key left out is its default) differ from the shipped weights' (say a run released without the bound
    the shipped network runs with: ``--options``); None when they agree."""
    from training.models import MODELS
    from training.models.options import INFERENCE_OPTIONS
    c, i = (((d.get("model") or {}).get(name) or {}) for d in (candidate, incumbent))
    defaults = MODELS[name].options()  # the model's own [model.<name>] table: a key left out has its default
    default = {k: getattr(defaults, k, None) for k in INFERENCE_OPTIONS}
    diff = [f"{k} {c.get(k, default[k])!r} (shipped: {i.get(k, default[k])!r})" for k in INFERENCE_OPTIONS
            if c.get(k, default[k]) != i.get(k, default[k])]
    return f"note: {name}: the candidate runs with {', '.join(diff)}; --options sets them" if diff else None


def check_options(options: dict[str, list[str]], runs: dict[str, Path]) -> None:
    """Every model's ``--options`` against its run's configuration, before anything is scored or written: a value or
    a combination the model refuses is a ValueError (one line) now, not after the first model's weights shipped."""
    from training.checkpoint import load_checkpoint
    from training.inference.loading import checked_inference_options
    for name, opts in options.items():
        ck = runs[name] / "checkpoints" / "last.pt"
        if ck.is_file():
            checked_inference_options(load_checkpoint(ck)["config"], opts, f"--options {name}?{'&'.join(opts)}")


def model_options(items: list[str], models: list[str]) -> dict[str, list[str]]:
    """``--options`` values 'MODEL?KEY=VALUE&...' -> {MODEL: ['KEY=VALUE', ...]}; ValueError (one line) for a model
    not in ``models`` (the keys and values: ``check_options``)."""
    from training.inference.loading import split_spec
    out: dict[str, list[str]] = {}
    for item in items:
        try:
            name, opts = split_spec(item)
        except Exception as exc:  # BlendSRError: one line
            raise ValueError(f"--options {item!r}: {exc}") from None
        if name not in models or not opts:
            raise ValueError(f"--options {item!r}: expected MODEL?KEY=VALUE with MODEL one of --models "
                             f"({', '.join(models)})")
        out.setdefault(name, []).extend(opts)
    return out


def check_finished(run: Path, loaded: dict, force: bool) -> None:
    """ValueError (one line) for a run still training or stopped by an interruption (its summary.json, written when
    ``blendsr train`` ends, missing, of another step, or ``stopped_by`` neither max_steps nor minutes): the weights
    scored would not be those shipped. ``--force`` releases it anyway."""
    js = run / "summary.json"
    summary = json.loads(js.read_text()) if js.is_file() else {}
    if force or (summary.get("step") == loaded.get("step") and summary.get("stopped_by") in ("max_steps", "minutes")):
        return
    raise ValueError(f"{run}: its checkpoint is at step {loaded.get('step')}, and the run has not finished there "
                     f"(summary.json: {summary.get('stopped_by', 'none')} at step {summary.get('step', '-')}): "
                     "wait for it, or --force")


def rule_plans(a, run_dirs: dict[str, Path], val: list[str], val_group: str) -> dict[str, tuple[list, list]]:
    """For every model of ``--models`` with a checkpoint, before anything is scored or written: the val clips its
    rule reads and those it leaves out (``unseen_val_clips``). ValueError (one line) for a run without command.txt
    under ``--script ''`` (the JSON would record a command that did not make it), a fine-tune of weights no longer
    shipped (``check_origin``) or no clip left."""
    from gbuffer_export.errors import BlendSRError
    from training.checkpoint import load_checkpoint
    from gbuffer_export.dataset.build import read_index
    from training.pretrained import PRETRAINED, WEIGHTS_DIR
    plans, spec_sha256 = {}, read_index(a.dataset)["spec"]["sha256"]
    if a.defer_test and not val:
        raise ValueError(f"{a.dataset}: no finished val clip: --defer-test releases by the val rule alone, which "
                         "would read nothing")
    for name in a.models.split(","):
        run = run_dirs.get(name, a.runs / name.replace("-", "_"))
        ck = run / "checkpoints" / "last.pt"
        if name not in PRETRAINED:
            raise ValueError(f"--models: {name!r} is not in training.pretrained.PRETRAINED "
                             f"({', '.join(PRETRAINED)})")
        if not ck.is_file():
            continue  # skipped in the loop, with a line
        if not a.script and not (run / "command.txt").is_file():
            raise ValueError(f"{run}: no command.txt, the command that trained it (--script '' records it in the "
                             "JSON): write it there")
        try:
            loaded = load_checkpoint(ck)
            check_origin(run, loaded, WEIGHTS_DIR)
        except (BlendSRError, OSError) as exc:
            raise ValueError(str(exc)) from None
        check_finished(run, loaded, a.force)
        check_round(a, name, spec_sha256)
        mine = candidate_families(a.dataset, stage_runs(run), loaded, WEIGHTS_DIR)
        plans[name] = unseen_val_clips(a.dataset, val, val_group,
                                       (WEIGHTS_DIR / PRETRAINED[name]).with_suffix(".json"), mine)
    return plans


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", type=Path)
    p.add_argument("runs", type=Path)
    p.add_argument("--models", default="fusesr,fusesr-l", help="comma-separated names of PRETRAINED")
    p.add_argument("--script", default="benchmarks/pretrain.sh", help="the script that made RUNS (for the JSON)")
    p.add_argument("--env", default="", help="the variables the script ran with, as written before it in the "
                                             "JSON's command (e.g. \"INIT='pretrained:<M>' LR=2e-4\")")
    p.add_argument("--force", action="store_true",
                   help="write the weights even when the val rule keeps the shipped ones")
    p.add_argument("--attach", action="append", default=[], metavar="KEY=FILE",
                   help="a JSON file put under KEY in every weight file's JSON (e.g. scale curves)")
    p.add_argument("--options", action="append", default=[], metavar="MODEL?KEY=VALUE[&...]",
                   help="inference options a run is scored and released with (e.g. fusesr?residual_clamp=lr-guided)")
    p.add_argument("--run", action="append", default=[], metavar="MODEL=DIR",
                   help="the run of MODEL (default RUNS/<MODEL with _ for ->), e.g. one of "
                        "benchmarks/data_scaling.py")
    p.add_argument("--val-group", choices=VAL_GROUPS, default="auto",
                   help="the val clips the val rule reads: held-out-family ones (auto: when there are any), or all")
    test = p.add_mutually_exclusive_group()
    test.add_argument("--defer-test", action="store_true",
                      help="release by the val rule without reading the test split (the JSON says so)")
    test.add_argument("--record-test", action="store_true",
                      help="release nothing: score the shipped weights of --models and the baselines on the whole "
                           "test split and write the scores into their JSONs")
    return p


class Round:
    """One release: the arguments, what was checked before any score (options, runs, each model's val clips), the
    dataset's splits and index, the baselines' scores and the RUNS/release.json being written. (A plain class: the
    tests load this script without registering it as a module, which dataclasses need.)"""

    def __init__(self, a, options: dict[str, list[str]], run_dirs: dict[str, Path],
                 plans: dict[str, tuple[list, list]], val: list[str], val_group: str, splits: dict[str, list],
                 index: dict):
        self.a, self.options, self.run_dirs, self.plans = a, options, run_dirs, plans
        self.val, self.val_group, self.test, self.train, self.index = \
            val, val_group, splits["test"], splits["train"], index
        self.baselines: dict = {}
        self.out: dict = {}
        self._val_baselines: dict = {}

    def score(self, spec: str, clips: list[str] | None = None, full: bool = False) -> dict:
        r = evaluate(spec, self.test if clips is None else clips)
        return r if full else summary(r)

    def val_baselines(self, clips: list[str]) -> dict:
        """demod-bilinear's and demod-jbu's scores on ``clips`` (each model's rule may read its own)."""
        if tuple(clips) not in self._val_baselines:
            self._val_baselines[tuple(clips)] = {m: self.score(m, clips) for m in ("demod-bilinear", "demod-jbu")}
        return self._val_baselines[tuple(clips)]

    def run_of(self, name: str) -> Path:
        return self.run_dirs.get(name, self.a.runs / name.replace("-", "_"))


def release_model(r: Round, name: str) -> dict | None:
    """Score the run of ``name``, apply the val rule against the shipped weights and release it when it passes (or
    with --force); returns the released JSON, None when skipped or kept."""
    from training.checkpoint import load_checkpoint
    from training.pretrained import PRETRAINED, WEIGHTS_DIR
    from training.release import release
    file, run = PRETRAINED[name], r.run_of(name)
    ck = run / "checkpoints" / "last.pt"
    cand = str(ck) + ("?" + "&".join(r.options[name]) if name in r.options else "")  # as scored and shipped
    if not ck.is_file():
        print(f"skip {name}: {ck} not found", file=sys.stderr)
        return None
    loaded = load_checkpoint(ck)
    if name in r.options:  # the options become the shipped configuration's
        from training.inference.loading import with_inference_options
        loaded["config"] = with_inference_options(loaded["config"], r.options[name], cand)
    if (WEIGHTS_DIR / file).is_file():
        note = option_note(loaded["config"], load_checkpoint(WEIGHTS_DIR / file)["config"], name)
        if note:
            print(note, file=sys.stderr)
    val_m, known = r.plans[name]
    if known:
        print(f"{name}: {len(known)} of the {len(r.val)} held-out-family val clips hold only families the shipped "
              f"weights or the candidate trained on (e.g. {Path(known[0]).name}); the rule reads the other "
              f"{len(val_m)}", file=sys.stderr)
    verdict, inc_val, cand_val = None, None, r.score(cand, val_m, full=True) if val_m else None  # scored once
    if val_m and (WEIGHTS_DIR / file).is_file():  # the val rule against the shipped weights of this name
        from training.selection import choose
        inc_val = r.score(f"pretrained:{name}", val_m, full=True)
        verdict = choose(cand_val, inc_val)
        print(verdict.line(name), file=sys.stderr)
        r.out["val_rules"][name] = {**verdict.record(r.a.force), "candidate": summary(cand_val),
                                    "shipped": summary(inc_val)}  # kept in RUNS/release.json either way
        if not verdict.replace and not r.a.force:
            return None
    test_score = None if r.a.defer_test else r.score(cand)
    meta = candidate_meta(r, name, run, loaded, test_score, (val_m, known, cand_val, inc_val), verdict)
    meta = release(loaded, WEIGHTS_DIR / file, meta)
    scored = (f"test PSNR {test_score['psnr']:.2f} dB (demod-jbu {r.baselines['demod-jbu']['psnr']:.2f}, "
              f"{meta['gain_over_demod_jbu_db']:+.2f} dB)" if test_score else "test split not read (--defer-test)")
    print(f"{name}: {scored}, {meta['bytes'] / 1e6:.2f} MB -> {WEIGHTS_DIR / file}")
    return meta


def candidate_meta(r: Round, name: str, run: Path, loaded: dict, test_score: dict | None, val_part: tuple,
                   verdict) -> dict:
    """The JSON beside released weights: dataset and clips, commands, scores on test (``TEST_DEFERRED`` instead when
    ``test_score`` is None) and val, the verdict with the replaced weights' val scores, the shipped weights it started
    from, attachments and inference options."""
    from training.pretrained import WEIGHTS_DIR
    val_m, known, cand_val, inc_val = val_part
    index = r.index
    meta = {
        "model": name, "scale": 4, "date": r.out["date"],
        "dataset": {"spec_file": index["spec"]["file"], "spec_sha256": index["spec"]["sha256"],
                    "name": index["name"], "train_clips": trained_on(loaded, r.train),
                    "val_clips": [Path(c).name for c in val_m], "val_clips_left_out": [Path(c).name for c in known],
                    "test_clips": r.out["test_clips"]},
        "commands": commands(r.a, index, name, run, int(loaded["step"])),
        "config": config_of(run),
    }
    if test_score is None:
        meta["test_split"] = TEST_DEFERRED
    else:
        meta.update(test_scores(name, {**test_score, "steps": int(loaded["step"])}, r.baselines))
    if val_m:
        meta["scores_on_val_split"] = {"metric": METRIC, "val_group": r.val_group, name: summary(cand_val),
                                       **r.val_baselines(val_m)}
    if verdict is not None:
        meta["val_rule"] = {**verdict.record(r.a.force), "shipped_before": summary(inc_val)}
    origin = shipped_origin(stage_runs(run), WEIGHTS_DIR)
    if origin is not None:
        meta["init_from"] = origin
    for item in r.a.attach:
        key, _, path = item.partition("=")
        meta[key] = json.loads(Path(path).read_text())
    if name in r.options:
        meta["inference_options"] = r.options[name]
    return meta


def test_scores(name: str, score: dict, baselines: dict) -> dict:
    """The test-split keys of a weights JSON: the network's scores beside the baselines' and its gain."""
    return {"scores_on_test_split": {"metric": METRIC, name: score, **baselines},
            "gain_over_demod_jbu_db": round(score["psnr"] - baselines["demod-jbu"]["psnr"], 3)}


def whole_test_split(dataset: Path) -> list[str]:
    """Every planned test clip of ``dataset``, finished and valid (``build.whole_split``); ValueError (one line) when
    any is not, or when the index plans none."""
    from gbuffer_export.dataset import build
    try:
        return [str(c) for c in build.whole_split(dataset, "test")]
    except build.DatasetError as exc:
        raise ValueError(f"{exc}: --record-test reads the whole test split") from None


def shipped_docs(models: list[str], spec_sha256: str) -> dict[str, dict]:
    """{name: its shipped weights JSON} of the names of ``models`` released from this dataset's spec with their test
    split deferred; a note on stderr for each other name (weights of another spec: their test split is another;
    already recorded: the test split is read once); ValueError (one line) for a name without shipped weights, or
    when no name is left."""
    from training.pretrained import WEIGHTS_DIR
    docs = {}
    for name in models:
        js = shipped_json(f"pretrained:{name}", WEIGHTS_DIR)
        if js is None:
            raise ValueError(f"--models: no shipped weights named {name!r}")
        doc = json.loads(js.read_text())
        if doc.get("dataset", {}).get("spec_sha256") != spec_sha256:
            print(f"note: {js}: released from another dataset spec; its test split is not this one", file=sys.stderr)
        elif not deferred(doc):
            print(f"note: {js}: its test split is recorded already ({doc.get('test_split', 'at its release')})",
                  file=sys.stderr)
        else:
            docs[name] = doc
    if not docs:
        raise ValueError(f"--models {','.join(models)}: no shipped weights of this dataset's spec with a deferred "
                         "test split")
    return docs


#: Flags ``--record-test`` would ignore: it scores the shipped weights as they are.
NOT_RECORDED = ("options", "run", "attach", "force", "env")


def record_test(a) -> int:
    """``--record-test``: each shipped network of ``--models`` whose test split its release deferred, and the
    baselines, on the whole test split, written into its JSON; the weights and their sha256 do not change."""
    from gbuffer_export.clip import write_json_atomic
    from gbuffer_export.dataset.build import read_index
    from training.pretrained import PRETRAINED, WEIGHTS_DIR
    extra = [f"--{k}" for k in NOT_RECORDED if getattr(a, k)]
    try:
        if extra:
            raise ValueError(f"--record-test scores the shipped weights as they are: {', '.join(extra)} would be "
                             "ignored")
        test = whole_test_split(a.dataset)
        docs = shipped_docs(a.models.split(","), read_index(a.dataset)["spec"]["sha256"])
    except ValueError as exc:
        print(f"blendsr: {exc}", file=sys.stderr)
        return 2
    baselines = {m: summary(evaluate(m, test)) for m in ("bicubic", "demod-bilinear", "demod-jbu")}
    command = f"benchmarks/release_weights.py {a.dataset} {a.runs} --models {a.models} --record-test"
    rc = 0
    for name, doc in docs.items():
        score = {**summary(evaluate(f"pretrained:{name}", test)), "steps": doc.get("step")}
        path = (WEIGHTS_DIR / PRETRAINED[name]).with_suffix(".json")
        fresh = json.loads(path.read_text())  # as it is now: scoring took hours, and only the test keys are ours
        if fresh.get("sha256") != doc.get("sha256") or not deferred(fresh):
            print(f"blendsr: {path}: the weights were released again or their test split recorded while they were "
                  "scored; nothing written for them (run --record-test again)", file=sys.stderr)
            rc = 2
            continue
        fresh.update(test_scores(name, score, baselines))
        fresh["dataset"]["test_clips"] = [Path(c).name for c in test]
        fresh["test_split"] = f"recorded {datetime.date.today().isoformat()}: {command}"
        write_json_atomic(path, fresh)
        print(f"{name}: test margin {fresh['gain_over_demod_jbu_db']:+.2f} dB over demod-jbu", file=sys.stderr)
    return rc


def main(argv=None) -> int:
    a = parser().parse_args(argv)
    from gbuffer_export.clip import write_json_atomic
    from gbuffer_export.dataset.build import read_index, split_clips
    if a.record_test:
        return record_test(a)
    test = [] if a.defer_test else [str(c) for c in split_clips(a.dataset, "test")]
    try:
        options = model_options(a.options, a.models.split(","))
        run_dirs = named_runs(a.run, a.models.split(","))
        check_options(options, {m: run_dirs.get(m, a.runs / m.replace("-", "_")) for m in options})
        val, val_group = rule_val_clips(a.dataset, [str(c) for c in split_clips(a.dataset, "val")], a.val_group)
        plans = rule_plans(a, run_dirs, val, val_group)
    except ValueError as exc:
        print(f"blendsr: {exc}", file=sys.stderr)
        return 2
    r = Round(a, options, run_dirs, plans, val, val_group,
              {"test": test, "train": [c.name for c in split_clips(a.dataset, "train")]}, read_index(a.dataset))
    r.baselines = {} if a.defer_test else {m: r.score(m) for m in ("bicubic", "demod-bilinear", "demod-jbu")}
    r.out = {"date": datetime.date.today().isoformat(), "dataset": str(a.dataset),
             "test_clips": [Path(c).name for c in test], "val_clips": [Path(c).name for c in val],
             "val_group": val_group, "baselines": r.baselines, "val_rules": {}, "models": {}}
    for name in a.models.split(","):
        meta = release_model(r, name)
        if meta is not None:
            r.out["models"][name] = meta
    write_json_atomic(a.runs / "release.json", r.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
