"""Issue 42 item 11: the messages a researcher new to BlendSR met, each as it reads now (and two of its findings
about clips: finished clips keep no lock files, the exports' sRGB curve is colour-science's)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import ENV, REPO
from gbuffer_export.cli import main
from gbuffer_export.synthetic import make_synthetic_clip


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)


@pytest.fixture(scope="module")
def dataset(clip, tmp_path_factory):
    from gbuffer_export.dataset.build import INDEX, SCHEMA
    ds = tmp_path_factory.mktemp("ds")
    entries = []
    for cid, split in (("a", "train"), ("b", "test")):
        shutil.copytree(clip, ds / "clips" / cid, ignore=shutil.ignore_patterns(".blendsr_cache"))
        entries.append({"id": cid, "path": f"clips/{cid}", "split": split, "frames_planned": 3, "scene_id": cid,
                        "licence": {"licence": "CC0"}})
    (ds / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": 1, "clips": entries}))
    return ds


def error_line(capsys) -> str:
    err = [ln for ln in capsys.readouterr().err.strip().splitlines() if not ln.startswith("note: ")]
    assert len(err) == 1, err
    return err[0]


@pytest.mark.parametrize("argv", [["upscale", "--model", "bilinear", "--clip", "{ds}", "-o", "{tmp}/up"],
                                  ["bench", "loader", "--data", "{ds}"]])
def test_a_dataset_given_as_a_clip_names_a_clip_inside_it(dataset, tmp_path, capsys, argv):
    pytest.importorskip("torch")
    argv = [a.format(ds=dataset, tmp=tmp_path) for a in argv]
    assert main(argv) == 2
    flag = "--clip" if "upscale" in argv else "--data"
    assert error_line(capsys) == (f"blendsr: error: {flag} {dataset}: this is a dataset (it holds dataset.json), not "
                                  f"a clip: pass {dataset / 'clips' / 'ID'}, one of its clips (e.g. "
                                  f"{dataset / 'clips' / 'a'})")
    assert not (tmp_path / "up").exists()


def test_bench_loader_names_its_own_crop_flag(clip, capsys):
    pytest.importorskip("torch")
    assert main(["bench", "loader", "--data", str(clip), "--crop", "12"]) == 2
    line = error_line(capsys)
    assert line == f"blendsr: error: {clip}: LR size 16x9 is smaller than --crop 12; pass --crop 9 or less"
    assert "--set" not in line


def test_bench_alone_prints_usage_and_exits_2(capsys):
    assert main(["bench"]) == 2
    out = capsys.readouterr()
    assert out.err.startswith("usage: blendsr bench") and "choose a KIND: render, brdf" in out.err
    assert out.out == ""


def test_preview_shows_no_colour_science_warning_without_matplotlib(dataset, tmp_path):
    """A core install has no matplotlib; colour-science warns about it on import, which preview must not show."""
    code = ("import sys\nsys.modules['matplotlib'] = None\nsys.argv = ['blendsr', *sys.argv[1:]]\n"
            "from gbuffer_export.cli import main\nsys.exit(main())\n")
    proc = subprocess.run([sys.executable, "-c", code, "preview", str(dataset), "-o", str(tmp_path / "s.png")],
                          cwd=REPO, env=ENV, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert f"wrote {tmp_path / 's.png'} (2 clips)" in proc.stdout + proc.stderr
    assert "Warning" not in proc.stderr and "colour" not in proc.stderr.lower(), proc.stderr


def test_the_install_hint_works_for_a_checkout_and_for_an_installed_wheel(tmp_path):
    from gbuffer_export.extras import install_hint
    hint = install_hint("render")
    assert hint.startswith("install the [render] extra: pip install '.[render]'")
    assert hint.endswith(f" in {REPO}") or os.getcwd() == str(REPO)
    # a wheel install: the package without the checkout's pyproject.toml beside it
    site = tmp_path / "site"
    shutil.copytree(REPO / "gbuffer_export", site / "gbuffer_export", ignore=shutil.ignore_patterns("__pycache__"))
    env = dict(ENV, PYTHONPATH=str(site))
    proc = subprocess.run([sys.executable, "-c", "from gbuffer_export.extras import require\n"
                           "import sys; sys.modules['torch'] = None\n"
                           "require('blendsr train', 'train')"], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=60)
    last = proc.stderr.strip().splitlines()[-1]
    assert "install the [train] extra: pip install 'blendsr[train]' (adds it to the installed blendsr)" in last, last
    assert "'.[" not in last


def test_a_finished_clip_keeps_no_lock_files_and_shards_remove_them_last(clip, tmp_path):
    from gbuffer_export.clip import ClipBusyError, ClipWriter, load_manifest
    assert not [p.name for p in clip.iterdir() if p.name.startswith(".lock")]
    c = tmp_path / "c"
    shutil.copytree(clip, c, ignore=shutil.ignore_patterns(".blendsr_cache"))
    header = load_manifest(c)
    header.pop("frame_data")
    first, second = ClipWriter(c, {**header, "shard": [1, 2]}), ClipWriter(c, {**header, "shard": [2, 2]})
    with pytest.raises(ClipBusyError):
        ClipWriter(c, header)
    first.close()  # the other shard still writes: the locks stay
    assert sorted(p.name for p in c.iterdir() if p.name.startswith(".lock")) == [
        ".lock", ".lock.manifest", ".lock.shard-1of2", ".lock.shard-2of2"]
    second.close()  # the last writer of the finished clip
    assert not [p.name for p in c.iterdir() if p.name.startswith(".lock")]
    with ClipWriter(c, header):  # and the clip can be opened for writing again (a new lock file)
        assert (c / ".lock").is_file()
    # an unfinished clip keeps its lock file while, and after, a writer holds it: nothing is removed early
    header["frames"] = [1, 2, 3, 4]
    u = tmp_path / "u"
    w = ClipWriter(u, header)
    w.close()
    assert (u / ".lock").is_file()


def test_the_exports_srgb_curve_is_colour_sciences():
    import colour
    from gbuffer_export.formats import conventions as cv
    x = np.linspace(-0.5, 1.5, 2001)
    np.testing.assert_allclose(cv.srgb_encode(x), colour.cctf_encoding(np.clip(x, 0, 1), function="sRGB"), atol=0)
    y = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(cv.srgb_decode(y), colour.cctf_decoding(y, function="sRGB"), atol=0)
    src = (REPO / "gbuffer_export" / "formats" / "conventions.py").read_text()
    assert "0.0031308" not in src and "0.04045" not in src  # the curve is not written out by hand there
