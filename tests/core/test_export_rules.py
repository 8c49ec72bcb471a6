"""``blendsr export-dataset`` writes by rules (issue 43, "What to build" 3): a non-empty output is refused unless
--overwrite (replaced whole) or --append (numbered after what is there); a clip, a file or a source as output is
refused; a clip with missing frames becomes one sequence per contiguous run; RDG scene names are sanitised and
unique; numeric options are checked; what a killed export left is cleaned by the next run."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from tests.conftest import edit_manifest
from gbuffer_export.synthetic import make_synthetic_clip

DEAD_PID = 2**22 + 12345  # above Linux's pid_max default range: no such process


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    root = tmp_path_factory.mktemp("exp")
    a = make_synthetic_clip(root / "a", frames=(1, 2, 3), hr_size=(16, 8), scales=(2, 4))
    b = make_synthetic_clip(root / "b", frames=(1, 2), hr_size=(16, 8), scales=(2,))
    return a, b


def run(argv, capsys) -> tuple[int, str]:
    from gbuffer_export.cli import main
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.err + out.out


def one_error(code: int, text: str) -> str:
    lines = [ln for ln in text.splitlines() if ln.startswith("blendsr: error:")]
    assert code == 2 and len(lines) == 1 and "Traceback" not in text, text
    return lines[0]


def tree(p: Path) -> dict[str, bytes]:
    return {str(f.relative_to(p)): f.read_bytes() for f in sorted(p.rglob("*")) if f.is_file()}


@pytest.mark.parametrize("fmt", ["nss", "rdg"])
def test_a_non_empty_output_is_refused_then_overwritten_whole_or_appended(clips, tmp_path, capsys, fmt):
    a, b = clips
    out = tmp_path / "out"
    assert run(["export-dataset", a, "--format", fmt, "-o", out], capsys)[0] == 0
    first = tree(out)
    line = one_error(*run(["export-dataset", b, "--format", fmt, "-o", out], capsys))
    assert str(out) in line and "--overwrite" in line and "--append" in line
    assert tree(out) == first  # nothing touched
    (out / "stray.txt").write_text("old")
    assert run(["export-dataset", b, "--format", fmt, "-o", out, "--overwrite"], capsys)[0] == 0
    assert not (out / "stray.txt").exists()  # replaced whole
    if fmt == "nss":
        assert sorted(p.name for p in out.glob("*.json")) == ["0000.json"]
        assert json.loads((out / "0000.json").read_text())["BlendSR"]["clip"] == str(b)
    else:
        assert (out / "meta_info_train.txt").read_text().split() == ["b", "2", "0", "0"]
    assert run(["export-dataset", a, "--format", fmt, "-o", out, "--append"], capsys)[0] == 0
    if fmt == "nss":
        assert sorted(p.name for p in out.glob("*.json")) == ["0000.json", "0001.json"]
        assert json.loads((out / "0001.json").read_text())["BlendSR"]["clip"] == str(a)
        assert sorted(p.name for p in (out / "ground_truth").iterdir()) == ["0000", "0001"]
        assert len(list((out / "ground_truth" / "0001").iterdir())) == 3
    else:
        assert (out / "meta_info_train.txt").read_text().splitlines() == ["b 2 0 0", "a 3 0 0"]
        assert (out / "meta_info_test.txt").read_text().splitlines() == ["b 2 0", "a 3 0"]
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no temporary sibling left


def test_append_needs_an_export_of_the_same_format(clips, tmp_path, capsys):
    a, _ = clips
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    line = one_error(*run(["export-dataset", a, "--format", "nss", "-o", out, "--append"], capsys))
    assert "holds no NSS export" in line and (out / "notes.txt").read_text() == "mine"
    assert run(["export-dataset", a, "--format", "rdg", "-o", tmp_path / "r"], capsys)[0] == 0
    line = one_error(*run(["export-dataset", a, "--format", "nss", "-o", tmp_path / "r", "--append"], capsys))
    assert "holds no NSS export" in line


def test_overwrite_and_append_together_are_refused(clips, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        run(["export-dataset", clips[0], "--format", "nss", "-o", tmp_path / "o", "--overwrite", "--append"],
            capsys)
    assert e.value.code == 2


@pytest.mark.parametrize("where", ["the clip", "inside the clip", "a file", "a link to a file",
                                   "a link to a folder", "holding the source", "a dataset"])
def test_an_output_that_is_a_clip_a_file_or_a_source_is_refused(clips, tmp_path, capsys, where):
    a, _ = clips
    src = tmp_path / "src" / "a"
    shutil.copytree(a, src)
    before = tree(src.parent)
    out = {"the clip": src, "inside the clip": src / "nss", "a file": tmp_path / "f.txt",
           "a link to a file": tmp_path / "l", "a link to a folder": tmp_path / "ld",
           "holding the source": src.parent,
           "a dataset": tmp_path / "ds"}[where]
    if where == "a file":
        out.write_text("x")
    if where == "a link to a file":
        (tmp_path / "t.txt").write_text("x")
        out.symlink_to(tmp_path / "t.txt")
    if where == "a link to a folder":
        (tmp_path / "elsewhere").mkdir()
        out.symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    if where == "a dataset":
        out.mkdir()
        (out / "dataset.json").write_text("{}")
    for extra in ([], ["--overwrite"]):
        line = one_error(*run(["export-dataset", src, "--format", "nss", "-o", out, *extra], capsys))
        assert str(out) in line
    assert tree(src.parent) == before
    if where == "a link to a folder":
        assert not any((tmp_path / "elsewhere").iterdir())
    if where == "a file":
        assert out.read_text() == "x"


def test_a_clip_with_missing_frames_becomes_one_sequence_per_run(tmp_path, capsys):
    """Frames 1 and 3 of 1:4 (an interrupted shard run): two sequences, each starting with a camera cut; RDG: two
    scenes."""
    clip = make_synthetic_clip(tmp_path / "c", frames=(1, 2, 3, 4), hr_size=(16, 8), scales=(2,))

    def drop(m):
        for f in ("2", "4"):
            del m["frame_data"][f]
    edit_manifest(clip, drop)
    for f in (2, 4):
        (clip / "frames" / f"{f:06d}.json").unlink()
    code, text = run(["export-dataset", clip, "--format", "nss", "-o", tmp_path / "nss"], capsys)
    assert code == 0 and "exported as 2 sequences" in text
    metas = [json.loads((tmp_path / "nss" / f"000{i}.json").read_text()) for i in (0, 1)]
    assert [[fr["BlendSRFrame"] for fr in m["Frames"]] for m in metas] == [[1], [3]]
    assert all(m["Frames"][0]["CameraCut"] for m in metas)
    assert run(["export-dataset", clip, "--format", "rdg", "-o", tmp_path / "rdg"], capsys)[0] == 0
    assert (tmp_path / "rdg" / "meta_info_train.txt").read_text().split("\n")[:2] == ["c_f1 1 0 0", "c_f3 1 0 0"]


def test_rdg_scene_names_are_sanitised_and_unique(clips, tmp_path, capsys, monkeypatch):
    from gbuffer_export.formats.rdg import scene_name
    assert scene_name("my clip", set()) == "my_clip" and scene_name(".", set()) == "clip"
    assert scene_name("a", {"a", "a_2"}) == "a_3" and scene_name("..x y..", set()) == "x_y"
    a, _ = clips
    for name in ("my clip", "x/a", "y/a"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copytree(a, tmp_path / name)
    monkeypatch.chdir(tmp_path / "my clip")
    code, _ = run(["export-dataset", ".", tmp_path / "x" / "a", tmp_path / "y" / "a", "--format", "rdg",
                   "-o", tmp_path / "rdg"], capsys)
    assert code == 0
    meta = (tmp_path / "rdg" / "meta_info_train.txt").read_text().splitlines()
    assert [ln.split()[0] for ln in meta] == ["my_clip", "a", "a_2"]
    assert all(len(ln.split()) == 4 for ln in meta)
    assert sorted(p.name for p in (tmp_path / "rdg" / "GT").iterdir()) == ["a", "a_2", "my_clip"]


@pytest.mark.parametrize("value", ["-5", "0", "2.5", "1e9"])
def test_the_framerate_is_checked(clips, tmp_path, capsys, value):
    with pytest.raises(SystemExit) as e:
        run(["export-dataset", clips[0], "--format", "nss", "-o", tmp_path / "o", "--framerate", value], capsys)
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--framerate" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
    from gbuffer_export.formats.nss import export_nss
    from gbuffer_export.formats.output import ExportError, ExportOptions
    with pytest.raises(ExportError, match="framerate"):
        export_nss([clips[0]], tmp_path / "o", ExportOptions(framerate=-5))


def test_what_a_killed_export_left_is_cleaned_by_the_next_run(clips, tmp_path, capsys):
    a, b = clips
    out = tmp_path / "out"
    # a killed export: its sibling holds a half-written sequence and an EXR temporary
    dead = tmp_path / f".out.export{DEAD_PID}"
    (dead / "ground_truth" / "0000").mkdir(parents=True)
    (dead / "ground_truth" / "0000" / f".0000.tmp{DEAD_PID}.exr").write_bytes(b"half")
    assert run(["export-dataset", a, "--format", "nss", "-o", out], capsys)[0] == 0
    assert not dead.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    # an overwrite killed between its two renames: the previous export is put back, then replaced as asked
    prev = tree(out)
    os.rename(out, tmp_path / f".out.old{DEAD_PID}")
    assert run(["export-dataset", b, "--format", "nss", "-o", out], capsys)[0] == 2  # restored: not empty
    assert tree(out) == prev
    # an append killed while moving files in: sequence 0001's folders without 0001.json, an old temporary
    (out / "ground_truth" / "0001").mkdir()
    (out / "ground_truth" / "0001" / "0000.exr").write_bytes(b"partial")
    (out / "x2" / "color" / "0000" / f".0005.tmp{DEAD_PID}.exr").write_bytes(b"tmp")
    code, text = run(["export-dataset", b, "--format", "nss", "-o", out, "--append"], capsys)
    assert code == 0 and "interrupted append" in text
    assert not (out / "x2" / "color" / "0000" / f".0005.tmp{DEAD_PID}.exr").exists()
    assert len(list((out / "ground_truth" / "0001").iterdir())) == 2  # b's two frames, not the partial one
    assert sorted(p.name for p in out.glob("*.json")) == ["0000.json", "0001.json"]


def test_nss_needs_a_2x_level_and_names_the_fix(tmp_path, capsys):
    clip = make_synthetic_clip(tmp_path / "c4", frames=(1, 2), hr_size=(16, 8), scale=4)
    line = one_error(*run(["export-dataset", clip, "--format", "nss", "-o", tmp_path / "o"], capsys))
    assert "2x level" in line and "--scales 2,4" in line and str(clip) in line
    assert not (tmp_path / "o").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["c4"]


def test_rdg_warns_in_one_line_about_buffers_its_configs_read(tmp_path, capsys):
    clip = make_synthetic_clip(tmp_path / "c", frames=(1, 2), hr_size=(16, 8), scales=(2,),
                               buffers=("radiance", "depth", "motion"))
    code, text = run(["export-dataset", clip, "--format", "rdg", "-o", tmp_path / "rdg"], capsys)
    warn = [ln for ln in text.splitlines() if "RDG's shipped configs" in ln]
    assert code == 0 and len(warn) == 1, text
    assert "Normal (normal)" in warn[0] and "BRDF (fbeta)" in warn[0] and "Depth" not in warn[0]
    full = make_synthetic_clip(tmp_path / "full", frames=(1, 2), hr_size=(16, 8), scales=(2,))
    code, text = run(["export-dataset", full, "--format", "rdg", "-o", tmp_path / "rdg2"], capsys)
    assert code == 0 and "RDG's shipped configs" not in text


@pytest.mark.parametrize("fmt", ["nss", "nfru"])
def test_a_missing_2x_level_is_refused_in_the_formats_own_name(tmp_path, capsys, fmt):
    clip = make_synthetic_clip(tmp_path / "c4", frames=(1, 2), hr_size=(16, 8), scale=4)
    line = one_error(*run(["export-dataset", clip, "--format", fmt, "-o", tmp_path / "o"], capsys))
    assert f"{fmt.upper()} needs a 2x level" in line and f"--for-formats {fmt}" in line
    assert ("NSS" in line) == (fmt == "nss")  # the NFRU refusal never speaks of NSS
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c4"]


def test_nfru_refuses_a_size_its_reader_cannot_load_before_writing(clips, tmp_path, capsys):
    """Arm's NFRU reader loads 1920x1080 captures only (docs/formats.md): a 16x8 clip with a 2x level is refused in
    one line naming the size and the fix, and nothing is written (not even the sibling), whatever the mode."""
    a, _ = clips
    out = tmp_path / "out"
    for mode in ([], ["--append"], ["--overwrite"]):
        line = one_error(*run(["export-dataset", a, "--format", "nfru", "-o", out, *mode], capsys))
        assert "NFRU needs HR 1920x1080" in line and "is 16x8" in line and "--hr-size 1920x1080" in line, line
        assert str(a) in line
        assert sorted(p.name for p in tmp_path.iterdir()) == [], list(tmp_path.iterdir())


def test_export_dataset_help_lists_the_format_table(capsys):
    from gbuffer_export.cli import build_parser
    from gbuffer_export.format_limits import FORMATS
    text = " ".join(build_parser().format_help().split())
    assert "(NSS, RDG)" not in text and f"dataset layout ({', '.join(FORMATS)})" in text, text
