"""blendsr dataset --status: done and planned work and the render cost, read from the dataset's own clips."""
from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from gbuffer_export.dataset.build import INDEX, SCHEMA, SCHEMA_VERSION
from gbuffer_export.dataset.cost import dataset_status, status_lines
from gbuffer_export.errors import BlendSRError
from gbuffer_export.synthetic import make_synthetic_clip
from tests.conftest import builtin_spec, edit_manifest, edit_record, run_cli

HR = (16, 8)


def _clip(root: Path, cid: str, source: str, split: str, seconds: list[float], planned: int = 4) -> dict:
    """An index entry; with ``seconds``, a real clip of that many frames whose records carry those wall timings and
    half of each in CPU seconds."""
    if seconds:
        clip = make_synthetic_clip(root / "clips" / cid, frames=range(1, len(seconds) + 1), hr_size=HR,
                                   buffers=("radiance", "depth"))
        for f, s in enumerate(seconds, 1):
            edit_record(clip, f, lambda r, s=s: r.update(seconds_total=s, cpu_seconds_total=s / 2))
        # the manifest plans what the index plans: a shorter clip is a partial one
        edit_manifest(clip, lambda m: m.update(frames=list(range(1, planned + 1))))
    return {"id": cid, "source": source, "split": split, "path": f"clips/{cid}", "frames_planned": planned,
            "frames_done": 0, "state": "pending", "render": {"hr_size": list(HR)}}


def _index(root: Path, clips: list[dict]) -> None:
    (root / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "name": "t",
                                          "clips": clips}))


@pytest.fixture
def dataset(tmp_path) -> Path:
    _index(tmp_path, [_clip(tmp_path, "a0", "levels", "train", [10, 20, 30, 40]),
                      _clip(tmp_path, "a1", "levels", "test", [50]),
                      _clip(tmp_path, "b0", "builtin", "train", [])])
    return tmp_path


def test_the_cost_is_the_finished_frames_own_times_and_the_rest_is_estimated_at_their_median(dataset):
    # the index's stale "pending" states are not believed: each clip's folder says what is done
    r = dataset_status(dataset)
    lv, bt, every = r["by_source"]["levels"], r["by_source"]["builtin"], r["all"]
    assert (lv["clips"], lv["clips_done"], lv["frames_done"], lv["frames_planned"]) == (2, 1, 5, 8)
    assert lv["render_s"] == 150 and lv["median_s_per_frame"] == 30 and lv["hr_pixels_done"] == 5 * 16 * 8
    assert lv["p90_s_per_frame"] == pytest.approx(46.0)  # numpy's linear quantile of 10..50
    assert lv["estimate_left_s"] == 3 * 30 and lv["estimate_from"] == "own"
    # a source with nothing finished is estimated at the median of every finished frame, and says so
    assert bt["median_s_per_frame"] is None and bt["estimate_left_s"] == 4 * 30 and bt["estimate_from"] == "all"
    assert every["estimate_left_s"] == 7 * 30 and every["frames_done"] == 5
    assert r["by_split"]["train"]["clips"] == 2 and r["by_split"]["test"]["frames_done"] == 1
    # the CPU seconds are summed and estimated the same way, apart from the wall times
    assert lv["cpu_s"] == 75 and lv["median_cpu_s_per_frame"] == 15 and lv["estimate_left_cpu_s"] == 3 * 15
    assert bt["estimate_left_cpu_s"] == 4 * 15 and bt["estimate_cpu_from"] == "all"
    assert every["estimate_left_cpu_s"] == 7 * 15 and every["frames_cpu_timed"] == 5
    lines = status_lines(r)
    assert any(line.startswith("builtin") and line.rstrip().endswith("*") for line in lines), lines


def test_the_frames_are_counted_by_the_commit_that_rendered_them(dataset):
    """A dataset resumed across code changes says so: each frame record's ``commit`` (gbuffer_export.provenance); a
    render of a commit with local changes is its own entry."""
    old, new = "a" * 40, "b" * 40 + "-dirty"
    for f in (1, 2, 3):
        edit_record(dataset / "clips" / "a0", f, lambda rec: rec.update(commit=old))
    edit_record(dataset / "clips" / "a1", 1, lambda rec: rec.update(commit=new))
    r = dataset_status(dataset)
    assert r["all"]["frames_by_commit"] == {old: 3, new: 1, "unrecorded": 1}
    assert r["by_split"]["test"]["frames_by_commit"] == {new: 1}
    assert ("frames by the commit that rendered them: aaaaaaaaaaaa 3, unrecorded 1, bbbbbbbbbbbb-dirty 1") in status_lines(r)


def test_a_frame_without_a_timing_counts_as_done_but_not_timed(dataset):
    edit_record(dataset / "clips" / "a1", 1, lambda rec: rec.pop("seconds_total"))
    t = dataset_status(dataset)["by_split"]["test"]
    assert (t["frames_done"], t["frames_timed"], t["render_s"]) == (1, 0, 0)
    assert (t["frames_cpu_timed"], t["cpu_s"]) == (1, 25)  # its CPU time still counts


def test_frames_from_before_cpu_timings_leave_the_cpu_figures_empty_not_zero(dataset):
    for cid, frames in (("a0", 4), ("a1", 1)):
        for f in range(1, frames + 1):
            edit_record(dataset / "clips" / cid, f, lambda rec: rec.pop("cpu_seconds_total"))
    r = dataset_status(dataset)
    assert r["all"]["median_cpu_s_per_frame"] is None and r["all"]["estimate_left_cpu_s"] is None
    assert r["all"]["estimate_left_s"] == 7 * 30  # the wall estimate is unchanged
    assert any(line.startswith("all") and line.rstrip().endswith("-") for line in status_lines(r))


def test_a_missing_or_broken_index_is_one_line_naming_the_file(tmp_path):
    with pytest.raises(BlendSRError, match="no dataset.json"):
        dataset_status(tmp_path)
    (tmp_path / INDEX).write_text("[]")
    with pytest.raises(BlendSRError, match="dataset.json: not a BlendSR dataset index"):
        dataset_status(tmp_path)


def test_paths_from_the_index_stay_inside_the_dataset(tmp_path):
    """The index is read through build.clip_dir: no path outside the dataset folder, none through a link."""
    outside = tmp_path / "elsewhere"
    make_synthetic_clip(outside / "x", frames=range(1, 2), hr_size=HR, buffers=("radiance", "depth"))
    root = tmp_path / "ds"
    root.mkdir()
    _index(root, [{**_clip(root, "x", "levels", "train", []), "path": "../elsewhere/x"}])
    with pytest.raises(BlendSRError, match=r"dataset.json: clip 'x'"):
        dataset_status(root)
    (root / "clips").mkdir()
    os.symlink(outside / "x", root / "clips" / "x")
    _index(root, [_clip(root, "x", "levels", "train", [])])
    with pytest.raises(BlendSRError, match=r"dataset.json: clip 'x'"):
        dataset_status(root)


def test_the_cli_prints_the_report_and_renders_nothing(dataset, tmp_path):
    spec = builtin_spec(tmp_path / "spec.toml", seeds="0:1")
    proc = run_cli("dataset", str(spec), "-o", str(dataset), "--status", "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["all"]["render_s"] == 150
    assert sorted(p.name for p in (dataset / "clips").iterdir()) == ["a0", "a1"]  # nothing rendered
    proc = run_cli("dataset", str(spec), "-o", str(tmp_path / "none"), "--status")
    assert proc.returncode == 2 and "no dataset.json" in proc.stderr and proc.stderr.count("\n") == 1, proc.stderr
    proc = run_cli("dataset", str(spec), "-o", str(dataset), "--json")
    assert proc.returncode == 2 and "--json: only with --status" in proc.stderr, proc.stderr
