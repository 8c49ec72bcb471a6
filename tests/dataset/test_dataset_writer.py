"""The spec writer (``gbuffer_export.dataset.writer``) and the parts of ``build_dataset`` the add-on calls before a
run (``planned_jobs``, ``check_folder``, ``job_command`` with a Blender executable). Pure Python, no render."""
from __future__ import annotations

import dataclasses
import json
import os
import tomllib
from pathlib import Path

import pytest

from tests.conftest import REPO
from gbuffer_export.dataset import writer
from gbuffer_export.dataset.build import (INDEX, DatasetError, RunOptions, check_folder, job_command, make_index,
                                          planned_jobs)
from gbuffer_export.dataset.spec import SpecError, expand, load_spec, parse_spec

EXAMPLES = sorted((REPO / "examples").glob("dataset_*.toml"))


def _read_back(text: str, path) -> object:
    return parse_spec(tomllib.loads(text), path)


@pytest.mark.parametrize("dumps", ["tomli_w", "small"])
@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.name)
def test_every_example_spec_round_trips(example, dumps, monkeypatch):
    if dumps == "small":
        monkeypatch.setattr(writer, "dumps_toml", writer.dumps_small)
    else:
        pytest.importorskip("tomli_w")
    spec = load_spec(example)
    text = writer.spec_to_toml(spec, header="a header\nover two lines")
    assert text.startswith("# a header\n# over two lines\n")
    back = _read_back(text, example)
    assert back == spec
    assert writer.spec_to_dict(back) == writer.spec_to_dict(spec)


def test_a_spec_built_in_code_round_trips_with_awkward_text(tmp_path):
    """Quotes, backslashes, newlines, tabs, control and non-ASCII characters, keys that need quoting, per-source
    render overrides and every kind of source and variation key."""
    doc = {
        "dataset": {"name": 'odd "name"\\with\nnewline\tand é', "seed": 7},
        "render": {"frames": 3, "hr_size": "64x36", "scale": 4, "scales": [4, 2], "hr_spp": 2,
                   "buffers": "radiance,depth"},
        "splits": {"val": ["builtin:1"], "test": ["a b.c"], "val_fraction": 0.125, "test_fraction": 1e-05},
        "source": [
            {"name": "b", "kind": "builtin", "seeds": "0:2", "cameras": ["orbit", "scene"], "sun": False,
             "props": ["broken_pane"], "hdri": ["builtin:city"], "hdri_strength": [0.5, 2.0]},
            {"name": "s-1", "kind": "scene", "paths": ["lvl/x y.blend"], "cameras": ["fly", "walk"],
             "clips_per_scene": 3, "light": "sky", "regions": "3x2", "region_val": 1, "region_test": 1,
             "world_strength": [0.5, 1.5], "light_strength": 2.0, "sun_elevation_deg": [10, 80.5],
             "hdri": ["env/a.hdr"], "scale": 2, "scales": [2], "lr_spp": 8,
             "licence": {"x y": {"licence": "CC-BY\u0001", "attribution": "q\"uote\\"}}},
            {"name": "s_2", "kind": "scene", "paths": ["lvl"], "cameras": ["scene:Cam \"A\"", "scene:*"],
             "split": "val"},
        ],
    }
    spec = parse_spec(doc, tmp_path / "spec.toml")
    for text in (writer.dumps_small(writer.spec_to_dict(spec)), writer.spec_to_toml(spec)):
        assert _read_back(text, tmp_path / "spec.toml") == spec
    table = writer.spec_to_dict(spec)["source"][1]
    assert table["scale"] == 2 and table["lr_spp"] == 8 and "hr_spp" not in table  # only what differs
    assert table["scales"] == [2] and spec.sources[1].render.scales is None  # one level where [render] has two
    assert spec.sources[2].render.scales == (4.0, 2.0)
    assert writer.spec_to_dict(spec)["render"]["hr_spp"] == 2


def test_small_writer_refuses_what_toml_cannot_hold():
    for bad in (float("nan"), float("inf"), None, {1, 2}):
        with pytest.raises(ValueError, match="TOML value"):
            writer.dumps_small({"k": bad})
    assert tomllib.loads(writer.dumps_small({"a b": {"c.d": [1, 2.5, True]}})) == {"a b": {"c.d": [1, 2.5, True]}}


def _scene_spec(tmp_path: Path, name: str = "d", frames: int = 2) -> object:
    (tmp_path / "scene").mkdir(exist_ok=True)
    (tmp_path / "scene" / "s.blend").write_bytes(b"BLENDER")
    doc = {"dataset": {"name": name}, "render": {"frames": frames, "hr_size": "64x36"},
           "source": [{"name": "scene", "kind": "scene", "paths": ["scene/s.blend"], "clips_per_scene": 2}]}
    (tmp_path / "spec.toml").write_text(writer.dumps_small(doc))
    return load_spec(tmp_path / "spec.toml")


def test_planned_jobs_and_check_folder(tmp_path):
    spec = _scene_spec(tmp_path)
    jobs = planned_jobs(spec)
    assert [j.id for j in jobs] == [j.id for j in expand(spec)] == ["scene-s-00", "scene-s-01"]
    assert [j.camera for j in jobs] == ["walk", "fly"]
    nsrr = planned_jobs(spec, RunOptions(buffers_for=("nsrr",)))
    assert all(j.render["buffers"] == ["radiance", "depth", "motion"] for j in nsrr)
    assert check_folder(tmp_path / "new", spec, jobs) is None
    (tmp_path / "file").write_text("x")
    with pytest.raises(DatasetError, match="exists and is not a folder"):
        check_folder(tmp_path / "file", spec, jobs)
    # a folder holding this dataset: its index comes back; another dataset's name, or a changed clip, is refused
    out = tmp_path / "ds"
    (out / "clips" / jobs[0].id).mkdir(parents=True)
    index = make_index(spec, jobs, out, None, RunOptions())
    (out / INDEX).write_text(json.dumps(index))
    assert check_folder(out, spec, jobs)["name"] == "d"
    with pytest.raises(DatasetError, match="holds dataset 'd'"):
        check_folder(out, _scene_spec(tmp_path, name="other"), jobs)
    (out / "clips" / jobs[0].id / "manifest.json").write_text("{}")
    changed = planned_jobs(_scene_spec(tmp_path, frames=3))
    with pytest.raises(DatasetError, match=f"clip {jobs[0].id} was rendered from a different spec"):
        check_folder(out, spec, changed)


def test_an_index_from_before_hr_fbeta_reads_as_point(tmp_path):
    """A dataset indexed before the ``hr_fbeta`` render key was rendered point-sampled: the same spec with
    ``hr_fbeta = "point"`` may extend it; ``footprint``, the default since 2026-11-26, is a changed spec."""
    def spec_with(hr_fbeta):
        (tmp_path / "scene").mkdir(exist_ok=True)
        (tmp_path / "scene" / "s.blend").write_bytes(b"BLENDER")
        render = {"frames": 2, "hr_size": "64x36", **({"hr_fbeta": hr_fbeta} if hr_fbeta else {})}
        doc = {"dataset": {"name": "d"}, "render": render,
               "source": [{"name": "scene", "kind": "scene", "paths": ["scene/s.blend"], "clips_per_scene": 2}]}
        (tmp_path / "spec.toml").write_text(writer.dumps_small(doc))
        return load_spec(tmp_path / "spec.toml")
    point, footprint = spec_with("point"), spec_with(None)
    assert point.sources[0].render.hr_fbeta == "point" and footprint.sources[0].render.hr_fbeta == "footprint"
    out = tmp_path / "ds"
    jobs = planned_jobs(point)
    (out / "clips" / jobs[0].id).mkdir(parents=True)
    (out / "clips" / jobs[0].id / "manifest.json").write_text("{}")
    index = make_index(point, jobs, out, None, RunOptions())
    for c in index["clips"]:
        del c["render"]["hr_fbeta"], c["render"]["scales"]  # as written before the keys
    (out / INDEX).write_text(json.dumps(index))
    assert check_folder(out, point, jobs)["name"] == "d"
    with pytest.raises(DatasetError, match="rendered from a different spec"):
        check_folder(out, footprint, planned_jobs(footprint))
    with pytest.raises(SpecError, match="hr_fbeta"):
        spec_with("box")
    # the job renders what it says, and a job file from before the key renders point-sampled
    from gbuffer_export.blender.dataset_job import render_config
    for spec, want in ((point, "point"), (footprint, "footprint")):
        assert render_config(planned_jobs(spec)[0], tmp_path / "c").hr_fbeta == want
    job = planned_jobs(footprint)[0]
    old_job = dataclasses.replace(job, render={k: v for k, v in job.render.items() if k not in ("hr_fbeta", "scales")})
    old_cfg = render_config(old_job, tmp_path / "c")
    assert old_cfg.hr_fbeta == "point" and old_cfg.scales == (4.0,)


def test_render_scales_give_every_clip_several_lr_levels(tmp_path):
    """``scales`` (a render key): the clip's LR levels, the first being ``scale``; a spec that puts another first is
    refused in one line naming the key."""
    from gbuffer_export.blender.dataset_job import render_config
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "s.blend").write_bytes(b"BLENDER")

    def spec_with(render):
        doc = {"dataset": {"name": "d"}, "render": {"frames": 2, "hr_size": "64x32", **render},
               "source": [{"name": "scene", "kind": "scene", "paths": ["scene/s.blend"], "clips_per_scene": 1}]}
        (tmp_path / "spec.toml").write_text(writer.dumps_small(doc))
        return load_spec(tmp_path / "spec.toml")
    job = planned_jobs(spec_with({"scales": [4, 2]}))[0]
    assert job.render["scales"] == [4.0, 2.0]
    cfg = render_config(job, tmp_path / "c")
    assert cfg.scales == (4.0, 2.0) and cfg.scale == 4
    assert render_config(planned_jobs(spec_with({}))[0], tmp_path / "c").scales == (4.0,)
    with pytest.raises(SpecError, match=r"render\.scales: the first scale is the clip's 'lr' level and must be scale 4"):
        spec_with({"scales": [2, 4]})
    with pytest.raises(SpecError, match="not divisible by scale 3"):
        spec_with({"scales": [4, 3]})


def test_job_command_with_a_blender_executable(tmp_path):
    py = job_command(tmp_path / "j.json", tmp_path / "c", 2, "cpu")
    assert py[1:3] == ["-m", "gbuffer_export.blender.dataset_job"] and py[-4:] == ["--threads", "2", "--device", "cpu"]
    bl = job_command(tmp_path / "j.json", tmp_path / "c", 2, "cpu", blender="/opt/blender/blender")
    script = REPO / "gbuffer_export" / "blender" / "dataset_job_script.py"
    assert bl[:6] == ["/opt/blender/blender", "--background", "--factory-startup", "--python-exit-code", "2",
                      "--python"] and bl[6] == str(script) and script.is_file()
    assert bl[7] == "--" and bl[8:] == py[3:]
    with pytest.raises(SpecError, match="local executor only"):
        RunOptions(executor="ray", blender="/opt/blender/blender").validate()


def test_dataset_job_script_paths(tmp_path):
    from gbuffer_export.blender import dataset_job_script as s
    assert s.script_args(["blender", "--background", "--python", "x.py", "--", "a", "b"]) == ["a", "b"]
    assert s.script_args(["x.py", "a"]) == ["a"]
    paths = s.library_paths({"BLENDSR_SITE_DIRS": os.pathsep.join(["/v/site-packages", "", "/w"])})
    assert paths == ["/v/site-packages", "/w", str(REPO)]
    assert dataclasses.is_dataclass(RunOptions) and RunOptions().blender == ""


def test_a_finished_clip_that_validate_refuses_is_named_invalid(tmp_path):
    """Each clip is checked as it finishes (``quick_check``): a clip rendered to the end but black (the town level's
    test clip under a roof, 2026-11-26) is 'done' yet invalid, and the summary says so."""
    import numpy as np

    from gbuffer_export.dataset.build import quick_check, summary
    from gbuffer_export.exr import read_exr_channels, write_exr
    from gbuffer_export.synthetic import make_synthetic_clip
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4))
    assert quick_check(clip) == ""
    f = clip / "lr" / "radiance" / "000001.exr"
    write_exr(f, {k: np.zeros_like(v) for k, v in read_exr_channels(f).items()})
    problem = quick_check(clip)
    assert problem.startswith("ERROR frame 1 lr/radiance: radiance is 0 on every pixel") and "[black-frame]" in problem
    index = {"clips": [{"id": "c", "state": "done", "invalid": problem}], "splits": {"train": ["c"]}}
    assert summary(index) == "1 clips: 1 done (1 invalid) | splits: train 1"


def test_an_invalid_clip_is_left_out_of_its_split(tmp_path, caplog):
    from gbuffer_export.dataset.build import split_clips
    from gbuffer_export.synthetic import make_synthetic_clip
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "s.blend").write_bytes(b"BLENDER")
    doc = {"dataset": {"name": "d"}, "render": {"frames": 2, "hr_size": "64x36"},
           "source": [{"name": "scene", "kind": "scene", "paths": ["scene/s.blend"], "clips_per_scene": 2,
                       "split": "train"}]}
    (tmp_path / "spec.toml").write_text(writer.dumps_small(doc))
    spec = load_spec(tmp_path / "spec.toml")
    out = tmp_path / "ds"
    jobs = planned_jobs(spec)
    for j in jobs:
        make_synthetic_clip(out / "clips" / j.id, frames=range(1, 3))
    index = make_index(spec, jobs, out, None, RunOptions())
    assert [c["state"] for c in index["clips"]] == ["done", "done"]
    index["clips"][0]["invalid"] = "ERROR frame 1 lr/radiance: radiance is 0 on every pixel [black-frame]"
    (out / INDEX).write_text(json.dumps(index))
    with caplog.at_level("WARNING"):
        assert split_clips(out, "train") == [out / "clips" / jobs[1].id]
    assert f"clip {jobs[0].id} left out of the train split: ERROR frame 1" in caplog.text
    assert len(split_clips(out, "train", done_only=False)) == 2
    # re-indexing keeps the finding while the clip stays as it is
    assert make_index(spec, jobs, out, index, RunOptions())["clips"][0]["invalid"].startswith("ERROR frame 1")
