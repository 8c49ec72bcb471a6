"""One path rule for every reader (issue 43, "What to build" 1): every command that reads a dataset index, a clip's
manifest or an NSS capture is fed ``../``, absolute and linked entries; each refuses with one line (exit 2; validate
reports it and exits 1), writes nothing and opens nothing outside the folder it was given."""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest

from gbuffer_export.dataset.build import INDEX, SCHEMA
from gbuffer_export.synthetic import make_synthetic_clip

OPENED: list[str] | None = None


def _audit(event, args):  # records every file opened while a test sets OPENED (builtins.open, io.open, os.open)
    if event == "open" and OPENED is not None and args and isinstance(args[0], (str, bytes, Path)):
        OPENED.append(str(args[0] if not isinstance(args[0], bytes) else args[0].decode(errors="replace")))


sys.addaudithook(_audit)


def run(argv, capsys) -> tuple[int, str, list[str]]:
    """``blendsr ARGV`` in this process: (exit code, stderr + stdout, every file it opened)."""
    global OPENED
    from gbuffer_export.cli import main
    OPENED = []
    try:
        code = main([str(a) for a in argv])
    finally:
        opened, OPENED = OPENED, None
    out = capsys.readouterr()
    return code, out.err + out.out, opened


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("paths") / "clip", frames=(1, 2, 3), hr_size=(16, 8),
                               scales=(2, 4))


BAD = ["../outside", "ABS", "clips/../../outside", "clips/link", "clips/linked_manifest"]


def make_dataset(tmp_path: Path, base: Path, bad: str) -> tuple[Path, Path]:
    """A dataset whose index lists a good clip and ``bad``; returns (dataset, the outside clip)."""
    outside = tmp_path / "outside"
    shutil.copytree(base, outside)
    ds = tmp_path / "ds"
    (ds / "clips").mkdir(parents=True)
    shutil.copytree(base, ds / "clips" / "good")
    (ds / "clips" / "link").symlink_to(outside, target_is_directory=True)
    lm = ds / "clips" / "linked_manifest"  # a clip folder inside whose manifest.json links to the outside one
    shutil.copytree(base, lm)
    (lm / "manifest.json").unlink()
    (lm / "manifest.json").symlink_to(outside / "manifest.json")
    path = str(outside) if bad == "ABS" else bad
    entries = [{"id": f"c{i}", "path": p, "split": s, "scene_id": f"s{i}", "frames_planned": 3,
                "licence": {"licence": "CC0-1.0"}} for i, (p, s) in enumerate((("clips/good", "train"),
                                                                               (path, "test")))]
    (ds / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": 1, "name": "t", "seed": 0,
                                        "splits": {}, "clips": entries}))
    return ds, outside


def _outside_opened(opened: list[str], outside: Path) -> list[str]:
    o = str(outside.resolve())
    return [p for p in opened if str(Path(p).resolve()).startswith(o)]


READERS = {
    "export-dataset nss": lambda ds, out: ["export-dataset", ds, "--format", "nss", "-o", out],
    "export-dataset rdg": lambda ds, out: ["export-dataset", ds, "--format", "rdg", "-o", out],
    "preview": lambda ds, out: ["preview", ds, "-o", out / "sheet.png"],
    "validate": lambda ds, out: ["validate", ds, "--no-progress"],
}


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("reader", list(READERS))
def test_every_index_reader_refuses_paths_out_of_the_dataset(base, tmp_path, capsys, reader, bad):
    ds, outside = make_dataset(tmp_path, base, bad)
    out = tmp_path / "out"
    code, text, opened = run(READERS[reader](ds, out), capsys)
    assert "Traceback" not in text and "internal error" not in text, text
    assert _outside_opened(opened, outside) == [], (reader, bad)
    assert not out.exists() or not any(out.iterdir()), sorted(out.rglob("*"))
    assert not list(tmp_path.glob(".out.*"))  # no temporary export left beside it
    if reader == "validate":  # validate reports the path among its findings and fails (exit 1)
        assert code == 1 and "FAILED" in text and ("c1" in text or "symbolic link" in text), text
        return
    lines = [ln for ln in text.splitlines() if ln.startswith("blendsr: error:")]
    assert code == 2 and len(lines) == 1, text
    assert ("c1" in lines[0] and "dataset.json" in lines[0]) or "symbolic link" in lines[0], lines[0]


def test_the_library_readers_of_the_index_share_the_rule(base, tmp_path):
    """split_clips (train, evaluate, upscale, bench loader), expand_data_paths and the export's source_clips."""
    from gbuffer_export.clip import ClipError
    from gbuffer_export.dataset.build import expand_data_paths, split_clips
    from gbuffer_export.formats.nss import source_clips
    ds, _ = make_dataset(tmp_path, base, "../outside")
    for call in (lambda: split_clips(ds, "test"), lambda: expand_data_paths([ds], "test"),
                 lambda: source_clips([ds])):
        with pytest.raises(ClipError, match=r"dataset.json: clip 'c1': path '../outside' leads outside"):
            call()


def test_validate_never_opens_an_outside_manifest_for_the_region_check(base, tmp_path, capsys):
    """A scene clip with split regions whose path leads out: the region check skips it (index_errors reports it),
    the outside manifest is never opened."""
    ds, outside = make_dataset(tmp_path, base, "../outside")
    idx = json.loads((ds / INDEX).read_text())
    for c in idx["clips"]:
        c.update(kind="scene", asset="level.glb", region={"grid": [2, 1], "cell": [0, 0] if c["split"] == "train"
                                                          else [1, 0], "cells": {"train": [[0, 0]], "test": [[1, 0]]}})
    (ds / INDEX).write_text(json.dumps(idx))
    code, text, opened = run(["validate", ds, "--no-progress"], capsys)
    assert code == 1 and "leads outside" in text and _outside_opened(opened, outside) == []
    assert any(p.endswith("clips/good/manifest.json") for p in opened)  # the hook sees what validate reads


# ------------------------------------------------------------------------------------------ import-nss


@pytest.fixture(scope="module")
def capture(base, tmp_path_factory):
    from gbuffer_export.formats.nss import export_nss
    out = tmp_path_factory.mktemp("cap") / "nss"
    export_nss([base], out)
    return out


def _copy_capture(capture: Path, tmp_path: Path) -> Path:
    c = tmp_path / "cap"
    shutil.copytree(capture, c)
    return c


@pytest.mark.parametrize("case", ["dotdot sequence", "absolute sequence", "linked json", "linked exr",
                                  "linked folder"])
def test_import_nss_refuses_paths_and_links_out_of_the_capture(capture, tmp_path, capsys, case):
    cap = _copy_capture(capture, tmp_path)
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    seq = "0000"
    if case == "dotdot sequence":
        shutil.copyfile(cap / "0000.json", outside / "0000.json")
        seq = "../elsewhere/0000"
    elif case == "absolute sequence":
        shutil.copyfile(cap / "0000.json", outside / "0000.json")
        seq = str(outside / "0000")
    elif case == "linked json":
        shutil.move(cap / "0000.json", outside / "0000.json")
        (cap / "0000.json").symlink_to(outside / "0000.json")
    elif case == "linked exr":
        p = cap / "x2" / "color" / "0000" / "0001.exr"
        shutil.move(p, outside / "a.exr")
        p.symlink_to(outside / "a.exr")
    else:
        shutil.move(cap / "motion_gt" / "0000", outside / "mgt")
        (cap / "motion_gt" / "0000").symlink_to(outside / "mgt", target_is_directory=True)
    out = tmp_path / "clip"
    code, text, opened = run(["import-nss", cap, "--sequence", seq, "-o", out], capsys)
    lines = [ln for ln in text.splitlines() if ln.startswith("blendsr: error:")]
    assert code == 2 and len(lines) == 1 and "Traceback" not in text, text
    assert ("symbolic link" in lines[0]) == case.startswith("linked"), lines[0]
    assert not out.exists()
    assert _outside_opened(opened, outside) == []
