"""blendsr dataset --status: done and planned work and the render cost, read from the dataset's own records."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from gbuffer_export.dataset.cost import dataset_status, frame_seconds, status_lines
from gbuffer_export.errors import BlendSRError
from tests.conftest import builtin_spec, run_cli


def _clip(root: Path, cid: str, source: str, split: str, seconds: list[float], planned: int = 4) -> dict:
    frames = root / "clips" / cid / "frames"
    frames.mkdir(parents=True)
    for i, s in enumerate(seconds, 1):
        (frames / f"{i:06d}.json").write_text(json.dumps({"hr": {}, "seconds_total": s}))
    return {"id": cid, "source": source, "split": split, "path": f"clips/{cid}", "frames_planned": planned,
            "frames_done": len(seconds), "state": "done" if len(seconds) == planned else "partial",
            "render": {"hr_size": [16, 8]}}


@pytest.fixture
def dataset(tmp_path) -> Path:
    clips = [_clip(tmp_path, "a0", "levels", "train", [10, 20, 30, 40]),
             _clip(tmp_path, "a1", "levels", "test", [50]),
             _clip(tmp_path, "b0", "builtin", "train", [])]
    (tmp_path / "clips" / "a1" / "frames" / "000002.json").write_text("{not json")  # a torn record is skipped
    (tmp_path / "dataset.json").write_text(json.dumps({"name": "t", "clips": clips}))
    return tmp_path


def test_the_cost_is_the_finished_frames_own_times_and_the_rest_is_estimated_at_their_median(dataset):
    r = dataset_status(dataset)
    lv, bt, every = r["by_source"]["levels"], r["by_source"]["builtin"], r["all"]
    assert frame_seconds(dataset / "clips" / "a1") == [50.0]
    assert (lv["clips"], lv["clips_done"], lv["frames_done"], lv["frames_planned"]) == (2, 1, 5, 8)
    assert lv["render_s"] == 150 and lv["median_s_per_frame"] == 30 and lv["hr_pixels_done"] == 5 * 16 * 8
    assert lv["estimate_left_s"] == 3 * 30 and lv["estimate_from"] == "own"
    # a source with nothing finished is estimated at the median of every finished frame, and says so
    assert bt["median_s_per_frame"] is None and bt["estimate_left_s"] == 4 * 30 and bt["estimate_from"] == "all"
    assert every["estimate_left_s"] == 7 * 30 and every["frames_done"] == 5
    assert r["by_split"]["train"]["clips"] == 2 and r["by_split"]["test"]["frames_done"] == 1
    lines = status_lines(r)
    assert any(line.startswith("builtin") and line.rstrip().endswith("*") for line in lines), lines


def test_a_missing_or_broken_index_is_one_line_naming_the_file(tmp_path):
    with pytest.raises(BlendSRError, match="dataset.json: no dataset index"):
        dataset_status(tmp_path)
    (tmp_path / "dataset.json").write_text("[]")
    with pytest.raises(BlendSRError, match="dataset.json: not a dataset index"):
        dataset_status(tmp_path)


def test_the_cli_prints_the_report_and_renders_nothing(dataset, tmp_path):
    spec = builtin_spec(tmp_path / "spec.toml", seeds="0:1")
    proc = run_cli("dataset", str(spec), "-o", str(dataset), "--status", "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["all"]["render_s"] == 150
    assert sorted(p.name for p in (dataset / "clips").iterdir()) == ["a0", "a1", "b0"]  # nothing rendered
    proc = run_cli("dataset", str(spec), "-o", str(tmp_path / "none"), "--status")
    assert proc.returncode == 2 and "no dataset index" in proc.stderr and proc.stderr.count("\n") == 1, proc.stderr
    proc = run_cli("dataset", str(spec), "-o", str(dataset), "--json")
    assert proc.returncode == 2 and "--json: only with --status" in proc.stderr, proc.stderr
