"""Issue 54 item 4: the scaling curve's subsets are sized by HR pixels, as multiples of the wide set's train split,
and every score is split by family group (benchmarks/data_scaling.py; no render: an index written in the test)."""
from __future__ import annotations

import dataclasses
import json
import math
import sys
from pathlib import Path

import pytest

from gbuffer_export.dataset.build import INDEX, SCHEMA, SCHEMA_VERSION
from tests.conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
import data_scaling  # noqa: E402


def _dataset(root: Path, sizes: list[tuple[int, int, int]]) -> list[tuple[str, list[Path]]]:
    """An index of train clips of (frames, width, height) and one held-out test clip; the groups, in order."""
    clips = [{"id": f"c{i}", "path": f"clips/c{i}", "split": "train", "state": "done", "frames_done": f,
              "render": {"frames": f, "hr_size": [w, h]}, "family_group": "in-family"}
             for i, (f, w, h) in enumerate(sizes)]
    clips.append({"id": "t", "path": "clips/t", "split": "test", "state": "done", "frames_done": 2,
                  "render": {"frames": 2, "hr_size": [8, 8]}, "family_group": "held-out"})
    root.mkdir()
    (root / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "clips": clips}))
    return [(c["id"], [root / c["path"]]) for c in clips[:-1]]


def test_multiples_take_the_smallest_prefix_that_reaches_them(tmp_path):
    groups = _dataset(tmp_path / "ds", [(2, 10, 10), (1, 10, 10), (4, 10, 10), (3, 10, 10)])  # 200, 100, 400, 300 px
    got = data_scaling.pixel_prefixes(tmp_path / "ds", groups, [1, 3, 10], 100.0)
    assert got == [(1, 1, 200), (3, 2, 300), (10, 4, 1000)]
    assert data_scaling.hr_pixels(tmp_path / "ds", [tmp_path / "ds/clips/c2"]) == 400
    with pytest.raises(SystemExit, match="fewer than 11 x 100"):
        data_scaling.pixel_prefixes(tmp_path / "ds", groups, [11], 100.0)
    assert data_scaling.family_groups(tmp_path / "ds") == {"c0": ("in-family",), "c1": ("in-family",),
                                                           "c2": ("in-family",), "c3": ("in-family",),
                                                           "t": ("held-out",)}


def test_held_out_clips_of_an_unseen_asset_or_level_are_also_their_own_groups(tmp_path):
    """``held-out asset`` / ``held-out level``: a held-out clip showing an asset or a level that no train clip shows;
    not one whose asset was trained on (held out by its HDRI), nor one holding out a built-in family only, nor an
    in-family clip (a sub-group of held-out), nor a clip whose index entry has no families (an older index)."""
    fams = {"c0": ["asset:A", "hdri:x"], "c1": ["level:L", "material:brick"], "t0": ["asset:B", "hdri:x"],
            "t1": ["asset:A", "hdri:y"], "t2": ["material:voronoi"], "v0": ["level:M"], "v1": ["asset:C"]}
    clips = [{"id": c, "path": f"clips/{c}", "split": {"c": "train", "t": "test", "v": "val"}[c[0]], "families": f,
              "family_group": "in-family" if c[0] == "c" or c == "v1" else "held-out",
              "render": {"frames": 1, "hr_size": [8, 8]}} for c, f in fams.items()]
    clips.append({"id": "bare", "path": "clips/bare", "split": "test", "render": {"frames": 1, "hr_size": [8, 8]}})
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": SCHEMA_VERSION,
                                                      "clips": clips}))
    got = data_scaling.family_groups(tmp_path / "ds")
    assert got == {"c0": ("in-family",), "c1": ("in-family",), "t0": ("held-out", "held-out asset"),
                   "t1": ("held-out",), "t2": ("held-out",), "v0": ("held-out", "held-out level"),
                   "v1": ("in-family",), "bare": ("in-family",)}
    margins = {"c0": 1.0, "t0": 0.4, "t1": 0.2, "t2": 2.0, "v0": 0.7, "v1": -3.0}
    assert data_scaling.smallest_margins(margins, got) == {"in-family": -3.0, "held-out": 0.2,
                                                           "held-out asset": 0.4, "held-out level": 0.7}


def test_subsets_are_planned_and_ordered_as_the_mixed_render_order(tmp_path):
    """The subsets come from the planned train split (nothing rendered here), in the order `--order mixed` renders."""
    from gbuffer_export.dataset.build import RunOptions, clips_to_render, selected_jobs
    from gbuffer_export.dataset.spec import SpecError, expand, load_spec
    from gbuffer_export.errors import BlendSRError
    from tests.conftest import builtin_spec
    jobs = expand(load_spec(builtin_spec(tmp_path / "spec.toml", seeds="0:24")))
    jobs = [dataclasses.replace(j, split="test" if k % 5 == 1 else "val" if k % 7 == 3 else j.split)
            for k, j in enumerate(jobs)]  # built-in seeds all hash to train here: some evaluation clips
    root = tmp_path / "ds"
    root.mkdir()
    clips = [{"id": j.id, "path": f"clips/{j.id}", "split": j.split, "state": "partial", "frames_done": 0,
              "render": {"frames": 4, "hr_size": [64, 36]}} for j in jobs]
    (root / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "clips": clips}))
    groups = [g for g, _ in data_scaling.training_groups(root, "clip")]
    assert len(groups) == sum(j.split == "train" for j in jobs) > 5
    index = {"clips": clips}
    mixed = [j.id for j in clips_to_render(jobs, index, RunOptions(order="mixed"))]
    assert [i for i in mixed if i in groups] == groups and mixed != [j.id for j in jobs]
    assert [j.id for j in clips_to_render(jobs, index, RunOptions())] == [j.id for j in jobs]
    assert [j.id for j in clips_to_render(jobs, index, RunOptions(order="mixed", limit=3))] == mixed[:3]
    # train-first: the train split in the mixed order (its subsets first), then val and test, still mixed
    first = [j.id for j in clips_to_render(jobs, index, RunOptions(order="train-first"))]
    split = {j.id: j.split for j in jobs}
    n_train = len(groups)
    assert first[:n_train] == groups and first[n_train:] == [i for i in mixed if split[i] != "train"]
    assert {split[i] for i in first[n_train:]} == {"val", "test"}
    # --clips and --split choose what a run renders; the order still applies to what they keep
    sub = groups[:4]
    picked = clips_to_render(jobs, index, RunOptions(order="mixed", clips=(sub[2], sub[0], sub[1][:-1] + "*")))
    assert [j.id for j in picked] == [i for i in mixed if i in (sub[0], sub[2]) or i.startswith(sub[1][:-1])]
    tests = [j.id for j in clips_to_render(jobs, index, RunOptions(order="mixed", splits=("test",)))]
    assert tests == [i for i in mixed if split[i] == "test"] and tests
    both = clips_to_render(jobs, index, RunOptions(clips=(sub[0], tests[0]), splits=("test",)))
    assert [j.id for j in both] == [tests[0]]
    with pytest.raises(SpecError, match=r"--clips 'nope\*': names no clip of the spec"):
        selected_jobs(jobs, RunOptions(clips=(sub[0], "nope*")))
    with pytest.raises(SpecError, match="--split 'tets': choose from train, val, test"):
        RunOptions(splits=("tets",)).validate()
    # a selection that keeps nothing is refused too (a finished one is not: it is the selection, not what is left)
    with pytest.raises(SpecError, match="--clips and --split: no clip named is in split test"):
        selected_jobs(jobs, RunOptions(clips=(sub[0],), splits=("test",)))
    train_only = [j for j in jobs if j.split == "train"]
    with pytest.raises(SpecError, match="--split: the spec has no clip in split val, test"):
        selected_jobs(train_only, RunOptions(splits=("val", "test")))
    done = {"clips": [{**c, "state": "done"} for c in clips]}
    assert clips_to_render(jobs, done, RunOptions(splits=("test",))) == []
    assert RunOptions(clips=None, splits="test") == RunOptions(splits=("test",))  # a job file's null, one string
    # data_scaling --list-clips: the largest subset's clips (the nested subsets' union), in the mixed order
    listed = tmp_path / "subset.txt"
    import contextlib
    import io
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert data_scaling.main([str(root), "-o", "-", "--counts", "2,5", "--list-clips"]) == 0
    assert buf.getvalue().split() == groups[:5]
    assert data_scaling.main([str(root), "-o", "-", "--counts", "2,5", "--list-clips", str(listed)]) == 0
    assert listed.read_text(encoding="utf-8").split() == groups[:5]
    from gbuffer_export.commands.dataset import _clip_selection
    assert _clip_selection(f"@{listed}") == tuple(groups[:5])
    assert _clip_selection(" a, b*,") == ("a", "b*")
    for encoding in ("utf-8-sig", "utf-16"):  # Notepad's BOM; Windows PowerShell 5.1's '>' (UTF-16 LE with BOM)
        (tmp_path / "win.txt").write_bytes(f"# subset\r\n{groups[0]}\r\n{groups[1]}\r\n".encode(encoding))
        assert _clip_selection(f"@{tmp_path / 'win.txt'}") == tuple(groups[:2]), encoding
    for empty in ("", " , "):  # an empty shell variable would otherwise mean every clip
        with pytest.raises(BlendSRError, match="--clips .*: names nothing"):
            _clip_selection(empty)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert data_scaling.main([str(tmp_path / "new"), "-o", "-", "--list-clips"]) == 2
    line, = err.getvalue().strip().splitlines()
    assert str(tmp_path / "new") in line and "--limit 0 writes the index" in line
    with pytest.raises(BlendSRError, match="cannot read .*missing.txt"):
        _clip_selection(f"@{tmp_path / 'missing.txt'}")
    (tmp_path / "empty.txt").write_text("# nothing\n\n")
    with pytest.raises(BlendSRError, match="empty.txt names no clip"):
        _clip_selection(f"@{tmp_path / 'empty.txt'}")


def test_runs_wait_for_their_clips_and_scores_for_the_whole_test_split(tmp_path, capsys):
    root = tmp_path / "ds"
    _dataset(root, [(2, 10, 10)] * 3)
    rc = data_scaling.main([str(root), "-o", str(tmp_path / "out"), "--multiples", "1", "--unit-pixels", "200",
                            "--steps", "2"])
    out = capsys.readouterr().out
    assert rc == 3 and "are not rendered (or not valid) yet" in out and "0 of 1 runs trained" in out, out
    assert "test split 0 of 1 clips rendered" in out and not (tmp_path / "out" / "scaling.json").exists()


def test_the_curve_is_fitted_per_family_group_and_extrapolated_to_100x():
    unit = 1000.0
    rows = [{"model": "demod-jbu", "clips": 0, "hr_pixels": None},
            *({"model": "fusesr", "hr_pixels": x * unit, "margin_by_family": {"held-out": 1.0 + 0.5 * lg,
                                                                              "in-family": 2.0}}
              for x, lg in ((1, 0.0), (10, 1.0), (3.1622776601683795, 0.5)))]
    a, b = data_scaling.log_fit([1, 10, 100], [1.0, 1.5, 2.0])
    assert abs(a - 1.0) < 1e-9 and abs(b - 0.5) < 1e-9
    assert data_scaling.log_fit([3, 3], [1.0, 2.0]) is None
    lines = data_scaling.extrapolation_lines(rows, unit)
    assert lines[0].startswith("- held-out: margin = +1.00 +0.50 log10(x)") and "predicts +2.00 dB" in lines[0]
    assert lines[1].startswith("- in-family") and "+0.00 dB per tenfold" in lines[1], lines


def test_a_group_at_one_size_says_it_has_no_fit_and_a_diverged_run_is_tabled_not_fatal():
    """A family group scored at one data size gets a line saying so (it used to vanish from the report); a run whose
    frames are NaN keeps its score as None (n/a), out of the margins, instead of failing after the test read."""
    rows = [{"model": "fusesr", "hr_pixels": x, "margin_by_family": {"held-out": y, **extra}}
            for x, y, extra in ((1.0, 1.0, {"held-out level": 2.0}), (10.0, 2.0, {}))]
    lines = data_scaling.extrapolation_lines(rows, 1.0)
    assert lines[0] == "- held-out level: scored at one size (1.0x), no fit" and "held-out: margin" in lines[1], lines
    nan = float("nan")
    assert data_scaling.finite({"psnr": nan, "per_clip": {"a": nan, "b": 30.0}, "n": 3}) == {
        "psnr": None, "per_clip": {"a": None, "b": 30.0}, "n": 3}
    row = {"model": "fusesr", "clips": 2, "hr_pixels": 100, "steps": 10, "psnr": None, "ssim": None,
           "per_clip": {"a": None}, "margin_by_family": {}, "margin_min_by_family": {}}
    assert "| n/a | n/a | - | - | - | - | a n/a |" in data_scaling.report_table([row], "clip", 100.0)


def test_each_family_group_reports_its_worst_clip_beside_its_mean():
    per = {"a": 30.0, "b": 25.0, "c": 28.0, "d": 20.0}
    base = {"a": 29.0, "b": 26.0, "c": 27.5, "d": 19.0}
    family = {"a": ("in-family",), "b": ("in-family",), "c": ("held-out",), "d": ("held-out",)}
    margins = {c: per[c] - base[c] for c in per}  # as evaluate_model gives them, over demod-jbu
    assert data_scaling.smallest_margins(margins, family) == {"in-family": -1.0, "held-out": 0.5}
    row = {"model": "fusesr", "clips": 2, "hr_pixels": 100, "steps": 10, "psnr": 25.75, "ssim": 0.9,
           "per_clip": per, "margin_by_family": {"in-family": 0.0, "held-out": 0.75},
           "margin_min_by_family": {"in-family": -1.0, "held-out": 0.5}}
    table = data_scaling.report_table([row], "clip", 100.0)
    assert "| +0.00 (-1.00) | +0.75 (+0.50) | - | - |" in table
    row["margin_by_family"]["held-out asset"], row["margin_min_by_family"]["held-out asset"] = 1.0, 1.0  # clip d
    assert "| +0.75 (+0.50) | +1.00 (+1.00) | - |" in data_scaling.report_table([row], "clip", 100.0)


def test_score_variants_are_checked_before_training_and_each_is_its_own_curve(tmp_path):
    from training.config import load_config
    fusesr = load_config(str(REPO / "benchmarks/pretrain.toml"), ['model.name="fusesr"']).to_dict()
    assert data_scaling.score_variants("residual_clamp=lr-guided; ;residual_clamp=lr-range&residual_clamp_margin=0.5",
                                       fusesr) == ["residual_clamp=lr-guided",
                                                   "residual_clamp=lr-range&residual_clamp_margin=0.5"]
    with pytest.raises(ValueError, match="configuration is fixed except its inference options"):
        data_scaling.score_variants("width=3", fusesr)
    with pytest.raises(ValueError, match="expected MODEL"):
        data_scaling.score_variants("residual_clamp", fusesr)
    with pytest.raises(ValueError, match="'lr-guidd': choose one of none, lr-range, lr-guided"):
        data_scaling.score_variants("residual_clamp=lr-guidd", fusesr)
    root = tmp_path / "ds"
    _dataset(root, [(2, 10, 10)])
    assert data_scaling.main([str(root), "-o", str(tmp_path / "out"), "--score-options", "lr=1"]) == 2
    unit = 1.0
    rows = [{"model": m, "hr_pixels": x, "margin_by_family": {"held-out": y}}
            for m, pts in (("fusesr", ((1, 1.0), (10, 2.0))),
                           ("fusesr?residual_clamp=lr-guided", ((1, 1.5), (10, 1.5))))
            for x, y in pts]
    lines = data_scaling.extrapolation_lines(rows, unit)
    assert lines[0].startswith("- `fusesr` held-out: margin = +1.00 +1.00 log10(x)"), lines
    assert lines[1].startswith("- `fusesr?residual_clamp=lr-guided` held-out: margin = +1.50 +0.00"), lines


def test_the_plot_and_the_combined_table_show_every_model_and_family_group(tmp_path):
    base = [{"model": "demod-bilinear", "clips": 0, "steps": 0, "psnr": 20.0, "ssim": 0.5, "per_clip": {}},
            {"model": "demod-jbu", "clips": 0, "steps": 0, "psnr": 21.0, "ssim": 0.6, "per_clip": {}}]

    def run(model, x, held, fam):
        return {"model": model, "clips": 3, "steps": 10, "psnr": 22.0, "ssim": 0.7, "per_clip": {},
                "hr_pixels": x * 100, "margin_by_family": {"held-out": held, "in-family": fam}}
    for name, rows in (("a", [run("fusesr", 10, 2.0, 3.0), run("fusesr", 1, 1.0, 2.5)]),
                       ("b", [run("fusesr-l", 1, 0.5, 1.0), run("fusesr-l", 10, 0.7, 1.5)])):
        (tmp_path / name).mkdir()
        (tmp_path / name / "scaling.json").write_text(json.dumps({"rows": base + rows, "unit_pixels": 100.0}))
    out = tmp_path / "both"
    assert data_scaling.main(["-", "-o", str(out), "--combine", str(tmp_path / "a/scaling.json"),
                              str(tmp_path / "b/scaling.json")]) == 0
    table = (out / "scaling.md").read_text()
    assert table.count("| demod-jbu |") == 1 and table.count("| fusesr |") == 2 and table.count("| fusesr-l |") == 2
    assert "`fusesr-l` held-out: margin = +0.50 +0.20 log10(x)" in table, table
    assert (out / "scaling.png").stat().st_size > 1000
    record = json.loads((out / "scaling.json").read_text())  # what the results page reads
    assert [r["model"] for r in record["rows"]] == ["demod-bilinear", "demod-jbu"] + ["fusesr"] * 2 + ["fusesr-l"] * 2
    assert [r.get("x") for r in record["rows"]] == [None, None, 10.0, 1.0, 1.0, 10.0]
    fit = {(f["model"], f["group"]): f for f in record["fits"]}
    # two sizes a decade apart: the line through them, b = the gain per decade, a = the margin at 1x
    for key, (at1, at10) in {("fusesr", "held-out"): (1.0, 2.0), ("fusesr-l", "in-family"): (1.0, 1.5)}.items():
        f = fit[key]
        assert abs(f["a"] - at1) < 1e-6 and abs(f["b"] - (at10 - at1)) < 1e-6 and f["at"] == 100.0
        assert abs(f["predicted"] - (at1 + 2 * (at10 - at1))) < 1e-6 and (f["x_min"], f["x_max"], f["sizes"]) == (
            1.0, 10.0, 2)
    assert len(fit) == 4 and record["sources"] == [str(tmp_path / "a/scaling.json"), str(tmp_path / "b/scaling.json")]
    assert record["command"].startswith(".venv/bin/python benchmarks/data_scaling.py - -o ")
    series = data_scaling.margin_series(json.loads((tmp_path / "a/scaling.json").read_text())["rows"], 100.0)
    assert series == [{"model": "fusesr", "group": "held-out", "xs": [1.0, 10.0], "ys": [1.0, 2.0]},
                      {"model": "fusesr", "group": "in-family", "xs": [1.0, 10.0], "ys": [2.5, 3.0]}]
    (tmp_path / "bad.json").write_text("{}")
    assert data_scaling.main(["-", "-o", str(out), "--combine", str(tmp_path / "bad.json")]) == 2
    # OUT holding one of its inputs: refused, the input kept
    before = (tmp_path / "a/scaling.json").read_text()
    assert data_scaling.main(["-", "-o", str(tmp_path / "a"), "--combine", str(tmp_path / "a/scaling.json"),
                              str(tmp_path / "b/scaling.json")]) == 2
    assert (tmp_path / "a/scaling.json").read_text() == before


def test_fits_keep_step_budgets_apart_and_bad_flags_are_one_line(tmp_path, capsys):
    rows = [{"model": "fusesr", "steps": n, "hr_pixels": x, "margin_by_family": {"held-out": y}}
            for n, pts in ((500, ((1, 1.0), (10, 2.0))), (2000, ((1, 2.0), (10, 2.5))))
            for x, y in pts]
    fits = data_scaling.fits(rows, 1.0)
    assert [(f["steps"], f["a"], f["b"], f["sizes"]) for f in fits] == [(500, 1.0, 1.0, 2), (2000, 2.0, 0.5, 2)]
    assert [data_scaling.curve_label(c) for c in data_scaling.margin_series(rows, 1.0)] == [
        "fusesr (500 steps)", "fusesr (2000 steps)"]  # the plot keeps the budgets apart too
    assert data_scaling.extrapolation_lines(rows, 1.0)[1].startswith("- held-out (2000 steps): margin = +2.00 +0.50")
    root = tmp_path / "ds"
    _dataset(root, [(2, 10, 10)])
    for flag, value in (("--steps", "500,x"), ("--counts", "1,two"), ("--multiples", "1,3x")):
        assert data_scaling.main([str(root), "-o", str(tmp_path / "out"), flag, value]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"data_scaling: {flag} {value!r}: expected") and err.count("\n") == 1, err


def test_wait_trains_each_run_as_soon_as_its_clips_are_rendered(tmp_path, capsys, monkeypatch):
    """--wait: the clips are read again on every pass; a run trains on the pass its clips are ready, and the loop goes
    on while the test split is not whole."""
    from gbuffer_export.dataset import build
    root = tmp_path / "ds"
    _dataset(root, [(2, 10, 10)] * 3)
    naps, trained = [], []

    class Stop(Exception):
        pass

    def nap(seconds):
        naps.append(seconds)
        if len(naps) == 3:
            raise Stop
    real = build.split_clips
    # the train clips are rendered after the first pass; the test clip never is
    monkeypatch.setattr(build, "split_clips", lambda root, split, done_only=True: real(
        root, split, done_only=done_only and not (split == "train" and naps)))
    def train(cfg, run, resume=False):  # as train() ends a run: its summary.json
        trained.append(run)
        run.mkdir(parents=True, exist_ok=True)
        (run / "summary.json").write_text('{"step": 2}')
        return {"step": 2}
    monkeypatch.setattr("training.train.train", train)
    monkeypatch.setattr(data_scaling.time, "sleep", nap)
    with pytest.raises(Stop):
        data_scaling.main([str(root), "-o", str(tmp_path / "out"), "--multiples", "1", "--unit-pixels", "200",
                           "--steps", "2", "--wait", "0.5"])
    out = capsys.readouterr().out
    assert naps == [30.0] * 3 and "0 of 1 runs trained" in out and "again in 0.5 min" in out, out
    assert out.count("1 of 1 runs trained") == 2 and len(trained) == 1, out  # trained once, then reused
    assert (trained[0] / "command.txt").read_text().startswith(".venv/bin/python benchmarks/data_scaling.py")


def test_a_run_another_process_trains_is_waited_for_and_train_only_ends_without_the_test_split(
        tmp_path, capsys, monkeypatch):
    """Two processes share --runs: the run whose RUN/.lock the other holds is not entered (the pass goes on, the
    wait looks again); --train-only exits 0 once its runs are trained, though the test split never renders."""
    from gbuffer_export.dataset import build
    from gbuffer_export.locks import FolderLock
    from training.train import lock_run
    root = tmp_path / "ds"
    _dataset(root, [(2, 10, 10)] * 3)
    run = tmp_path / "out" / "fusesr_001clips"
    run.mkdir(parents=True)
    other = FolderLock(run, "held by the test")  # the other process, training this run
    real = build.split_clips
    monkeypatch.setattr(build, "split_clips", lambda root, split, done_only=True: real(
        root, split, done_only=done_only and split != "train"))  # train clips rendered, the test clip never
    naps = []
    monkeypatch.setattr(data_scaling.time, "sleep", lambda s: (naps.append(s), other.close()))

    def train(cfg, run, resume=False):  # as train() starts a run: RUN/.lock first
        with lock_run(run, create=True):
            (run / "summary.json").write_text('{"step": 2}')
        return {"step": 2}
    monkeypatch.setattr("training.train.train", train)
    assert data_scaling.main([str(root), "-o", str(tmp_path / "out"), "--multiples", "1", "--unit-pixels", "200",
                              "--steps", "2", "--wait", "1", "--train-only"]) == 0
    out = capsys.readouterr().out
    assert "fusesr_001clips: another process is training it" in out and naps == [60.0], out
    assert "--train-only: exits once every run is trained (again in 1 min)" in out, out
    assert json.loads((run / "summary.json").read_text()) == {"step": 2}
    assert not (tmp_path / "out" / "scaling.json").exists()  # no scores


def test_the_wait_ends_on_clips_that_never_come_and_a_run_stopped_early_stops_the_script(tmp_path, capsys,
                                                                                         monkeypatch):
    from gbuffer_export.dataset import build
    root = tmp_path / "ds"
    _dataset(root, [(2, 10, 10)] * 3)
    index = json.loads((root / INDEX).read_text())
    index["clips"][-1]["invalid"] = "black frames"  # the test clip: split_clips leaves it out for good
    (root / INDEX).write_text(json.dumps(index))
    argv = [str(root), "-o", str(tmp_path / "out"), "--multiples", "1", "--unit-pixels", "200", "--steps", "2"]
    assert data_scaling.main(argv + ["--wait", "5"]) == 3
    assert "1 clips the curve needs are marked invalid in the index (t)" in capsys.readouterr().err
    assert data_scaling.main(argv + ["--wait", "-1"]) == 2
    # a run cut short (SIGTERM: train() saves and returns early) is not a point of the curve: the script stops
    other = tmp_path / "ds2"
    _dataset(other, [(2, 10, 10)] * 3)
    real = build.split_clips
    monkeypatch.setattr(build, "split_clips", lambda root, split, done_only=True: real(root, split, done_only=False))
    monkeypatch.setattr("training.train.train", lambda cfg, run, resume=False: {"step": 1, "stopped_by": "signal"})
    with pytest.raises(SystemExit, match="stopped at step 1 of 2 \\(signal\\); rerun the same command"):
        data_scaling.main([str(other)] + argv[1:])


def test_combine_refuses_curves_scored_on_different_test_clips(tmp_path, capsys):
    for name, clips in (("a", ["t1", "t2"]), ("b", ["t1"])):
        (tmp_path / name).mkdir()
        (tmp_path / name / "scaling.json").write_text(json.dumps({"rows": [], "unit_pixels": 1.0, "test_clips": clips}))
    assert data_scaling.main(["-", "-o", str(tmp_path / "o"), "--combine", str(tmp_path / "a/scaling.json"),
                              str(tmp_path / "b/scaling.json")]) == 2
    assert "its test_clips differ from" in capsys.readouterr().err
    for name, scale in (("a", 4), ("b", 2)):  # the same clips scored at other scales
        (tmp_path / name / "scaling.json").write_text(json.dumps({"rows": [], "unit_pixels": 1.0, "test_clips": [],
                                                                  "scale": scale}))
    assert data_scaling.main(["-", "-o", str(tmp_path / "o"), "--combine", str(tmp_path / "a/scaling.json"),
                              str(tmp_path / "b/scaling.json")]) == 2
    assert "its scale differ from" in capsys.readouterr().err


def test_a_score_another_process_is_computing_is_waited_for_and_read_not_computed_twice(tmp_path, monkeypatch):
    """Both curves of one --runs score the baselines: the second waits on the score's lock, then reads the file."""
    import threading
    import time

    from gbuffer_export.locks import FolderLock
    path = tmp_path / "scores" / "abc.json"
    path.parent.mkdir()
    monkeypatch.setattr(data_scaling, "score_path", lambda curve, spec: path)

    def computed(curve, spec):
        raise AssertionError("scored twice")
    monkeypatch.setattr(data_scaling, "_score", computed)
    held = threading.Event()

    def other():  # the other process, scoring it now
        with FolderLock(path.parent, "", name=".abc.lock"):
            held.set()
            time.sleep(0.5)
            path.write_text(json.dumps({"psnr": 30.0}))
    thread = threading.Thread(target=other)
    thread.start()
    held.wait(10)
    try:
        assert data_scaling.score(None, "demod-jbu") == {"psnr": 30.0}
    finally:
        thread.join()


def test_the_curve_trains_scores_and_writes_its_records_end_to_end(tmp_path, monkeypatch):
    """The script's last stage, as the round's end runs it: every run trained (2 steps here), the baselines and each
    run scored as trained and with --score-options on the test split by family group (of the two held-out clips one
    shows an asset no train clip shows: it alone is also ``held-out asset``), the records written."""
    from gbuffer_export.synthetic import SyntheticLook, make_synthetic_clip
    root = tmp_path / "ds"
    clips = []
    for i, (split, group) in enumerate([("train", "in-family")] * 3 + [("test", "in-family"), ("test", "held-out"),
                                                                        ("test", "held-out")]):
        cid = f"{split}{i}"
        make_synthetic_clip(root / "clips" / cid, frames=range(1, 4), hr_size=(128, 72),
                            look=SyntheticLook(light=0.5 + 0.2 * i))
        clips.append({"id": cid, "path": f"clips/{cid}", "split": split, "state": "done", "frames_done": 3,
                      "render": {"frames": 3, "hr_size": [128, 72]}, "family_group": group,
                      "families": ["asset:B"] if i == 4 else ["asset:A", "hdri:z"] if i == 5 else ["asset:A"]})
    (root / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "clips": clips}))
    out = tmp_path / "out"
    argv = [str(root), "-o", str(out), "--runs", str(tmp_path / "runs"), "--multiples", "1,2", "--unit-pixels",
            str(3 * 128 * 72), "--steps", "2", "--model", "fusesr-l", "--threads", "1",
            "--score-options", "residual_clamp=lr-guided"]
    import torch
    threads = torch.get_num_threads()
    try:
        assert data_scaling.main(argv) == 0
    finally:
        torch.set_num_threads(threads)  # --threads 1 sets this process's
    record = json.loads((out / "scaling.json").read_text())
    assert [(r["model"], r["clips"]) for r in record["rows"]] == [
        ("demod-bilinear", 0), ("demod-jbu", 0), ("fusesr-l", 1), ("fusesr-l?residual_clamp=lr-guided", 1),
        ("fusesr-l", 2), ("fusesr-l?residual_clamp=lr-guided", 2)]
    jbu = record["rows"][1]["by_family"]
    groups = ("in-family", "held-out", "held-out asset")
    assert set(jbu) == set(groups) and len({jbu[g] for g in groups}) == 3
    for r in record["rows"][2:]:
        assert r["steps"] == 2 and set(r["margin_by_family"]) == set(groups)
        assert all(abs(r["margin_by_family"][g] - (r["by_family"][g] - jbu[g])) < 1e-9 for g in jbu)
        assert set(r["margin_min_by_family"]) == set(groups) and len(r["per_clip"]) == 3
        assert abs(r["by_family"]["held-out asset"] - r["per_clip"]["test4"]) < 1e-3  # its one clip
    assert {(f["model"], f["group"]) for f in record["fits"]} == {
        (m, g) for m in ("fusesr-l", "fusesr-l?residual_clamp=lr-guided") for g in groups}
    one, two = record["rows"][2], record["rows"][4]  # fusesr-l at 1x and 2x: the line through the two margins
    x1, x2 = one["hr_pixels"] / (3 * 128 * 72), two["hr_pixels"] / (3 * 128 * 72)
    assert (one["x"], two["x"]) == (x1, x2)
    slope = (two["margin_by_family"]["held-out"] - one["margin_by_family"]["held-out"]) / math.log10(x2 / x1)
    f = next(f for f in record["fits"] if (f["model"], f["group"]) == ("fusesr-l", "held-out"))
    assert (x1, x2) == (1.0, 2.0) and abs(f["b"] - slope) < 1e-5 and "steps" not in f
    assert record["test_clips"] == [str(root / f"clips/test{i}") for i in (3, 4, 5)]
    assert "predicts" in (out / "scaling.md").read_text() and (out / "scaling.png").stat().st_size > 1000
    # by clip count (the PSNR plot): the same runs, finished, are neither trained nor scored again (RUNS/scores)
    ckpt = tmp_path / "runs/fusesr-l_001clips/checkpoints/last.pt"
    mtime = ckpt.stat().st_mtime_ns
    assert len(list((tmp_path / "runs/scores").glob("*.json"))) == 6
    def scored_again(*a, **k):
        raise RuntimeError("scored again")
    monkeypatch.setattr("training.evaluate.evaluate_model", scored_again)
    assert data_scaling.main(argv[:5] + ["--counts", "1,2", "--steps", "2", "--model", "fusesr-l"]) == 0
    again = json.loads((out / "scaling.json").read_text())
    assert [r["model"] for r in again["rows"]] == ["demod-bilinear", "demod-jbu", "fusesr-l", "fusesr-l"]
    assert again["rows"][2]["per_clip"] == record["rows"][2]["per_clip"] and ckpt.stat().st_mtime_ns == mtime
    assert (out / "scaling.png").stat().st_size > 1000
    # a test clip rendered again (its manifest's bytes differ) is scored again, the baselines first
    manifest = root / "clips/test3/manifest.json"
    kept = manifest.read_bytes()
    manifest.write_bytes(kept + b"\n")
    with pytest.raises(RuntimeError, match="scored again"):
        data_scaling.main(argv[:5] + ["--counts", "1,2", "--steps", "2", "--model", "fusesr-l"])
    manifest.write_bytes(kept)
    # a run trained again (other bytes) is scored again
    torch.save({**torch.load(ckpt, weights_only=False), "again": 1}, ckpt)
    with pytest.raises(RuntimeError, match="scored again"):
        data_scaling.main(argv[:5] + ["--counts", "1,2", "--steps", "2", "--model", "fusesr-l"])
