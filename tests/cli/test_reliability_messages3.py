"""One-line errors for the bad inputs of the third reliability campaign (issue 43, items 4 and 9): a full disk
while an EXR is written names the file; spec ``scales = []``; a spec error that printed the spec path twice; a
``regions`` value echoed as written; ``--set`` errors not prefixed ``defaults:``; ``preview --splits bogus`` and
``preview --width 100000`` (checked against memory before the allocation)."""
from __future__ import annotations

import errno
import json
import os

import numpy as np
import pytest

from gbuffer_export.cli import main
from gbuffer_export.errors import bad_input_line


def _main(argv, capsys) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


# ---------------------------------------------------------------------------------------------- a full disk
class _FullDisk:
    """Stands for ``OpenEXR`` with a disk that fills up on write (OpenEXR's own message, measured on a full
    tmpfs: 'Failed to write pixel data to image file "...". No space left on device.')."""

    def __init__(self, real):
        self._real = real

    def __getattr__(self, name):
        return getattr(self._real, name)

    def File(self, header, channels):  # noqa: N802 - OpenEXR's name
        class _F:
            def __enter__(self_inner):
                return self_inner

            def __exit__(self_inner, *a):
                return False

            def write(self_inner, path):
                with open(path, "wb") as f:
                    f.write(b"\x76\x2f\x31\x01")  # a torn start, as a full disk leaves
                raise RuntimeError(f'Failed to write pixel data to image file "{path}". No space left on device.')
        return _F()


def test_a_full_disk_while_writing_an_exr_names_the_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    import gbuffer_export.exr as exr
    monkeypatch.setattr(exr, "OpenEXR", _FullDisk(exr.OpenEXR))
    target = tmp_path / "hr" / "radiance" / "000001.exr"
    with pytest.raises(OSError) as info:
        exr.write_exr(target, {"R": np.zeros((4, 4), np.float32)})
    assert info.value.errno == errno.ENOSPC
    assert bad_input_line(info.value) == f"{target}: no space left on device"
    assert list(target.parent.iterdir()) == []


def test_another_openexr_write_error_is_typed_and_names_the_file(tmp_path, monkeypatch):
    import gbuffer_export.exr as exr

    class _Broken(_FullDisk):
        def File(self, header, channels):  # noqa: N802
            raise RuntimeError("Cannot write image file: unsupported compression")
    monkeypatch.setattr(exr, "OpenEXR", _Broken(exr.OpenEXR))
    target = tmp_path / "a.exr"
    with pytest.raises(exr.ExrError, match=f"{target}: could not write the EXR"):
        exr.write_exr(target, {"R": np.zeros((4, 4), np.float32)})


# ---------------------------------------------------------------------------------------------- dataset specs
def _spec(tmp_path, render: str = "", source: str = 'kind = "builtin"\nseeds = "0:0"\n'):
    p = tmp_path / "s.toml"
    p.write_text(f'[dataset]\nname = "x"\n[render]\n{render}\n[[source]]\nname = "b"\n{source}')
    return p


def test_spec_scales_empty_is_one_line(tmp_path, capsys):
    spec = _spec(tmp_path, "scales = []")
    code, err = _main(["dataset", spec, "-o", tmp_path / "o", "--dry-run"], capsys)
    assert code == 2 and f"error: {spec}: render.scales = []: " in err


@pytest.mark.parametrize("render, key", [("hr_size = 5", "render.hr_size"), ("buffers = 5", "render.buffers")])
def test_a_spec_error_names_the_spec_once(tmp_path, capsys, render, key):
    spec = _spec(tmp_path, render)
    code, err = _main(["dataset", spec, "-o", tmp_path / "o", "--dry-run"], capsys)
    line = [ln for ln in err.splitlines() if "error:" in ln][0]
    assert code == 2 and line.count(str(spec)) == 1 and f"{spec}: {key}: expected a string" in line, line


def test_regions_are_echoed_as_written(tmp_path, capsys):
    (tmp_path / "lv").mkdir()
    spec = _spec(tmp_path, source='kind = "scene"\npaths = ["lv"]\nregions = "axb"\n')
    code, err = _main(["dataset", spec, "-o", tmp_path / "o", "--dry-run"], capsys)
    assert code == 2 and "regions = 'axb'" in err and "None" not in err


# ---------------------------------------------------------------------------------------------- --set
def test_set_errors_name_set_not_defaults(tmp_path):
    from training.config import ConfigError, load_config
    with pytest.raises(ConfigError) as info:
        load_config(None, ['data.crop="big"'])
    assert str(info.value).startswith("--set: data.crop") and "defaults" not in str(info.value)
    with pytest.raises(ConfigError) as info:
        load_config(None, ["data.bogus=1"])
    assert str(info.value).startswith("--set: unknown key data.bogus")


# ---------------------------------------------------------------------------------------------- preview
def _index(root, n=3, hr=(64, 32)):
    root.mkdir()
    clips = [{"id": f"c{i}", "path": f"clips/c{i}", "split": "train", "state": "done", "frames_planned": 2,
              "render": {"hr_size": list(hr)}} for i in range(n)]
    (root / "dataset.json").write_text(json.dumps({"schema": "blendsr-dataset", "schema_version": 1, "name": "p",
                                                   "seed": 0, "splits": {}, "clips": clips}))
    return root


def test_preview_unknown_split_names_it_and_the_valid_ones(tmp_path, capsys):
    ds = _index(tmp_path / "ds")
    code, err = _main(["preview", ds, "-o", tmp_path / "s.png", "--splits", "bogus"], capsys)
    assert code == 2 and "unknown split 'bogus'" in err and "train, val, test" in err
    assert "no finished clip" not in err


def test_preview_width_is_checked_against_memory_before_allocating(tmp_path, capsys, monkeypatch):
    ds = _index(tmp_path / "ds")
    monkeypatch.setenv("BLENDSR_MEMORY_AVAILABLE", str(8 * 2**30))
    code, err = _main(["preview", ds, "-o", tmp_path / "s.png", "--width", "100000"], capsys)
    assert code == 2 and "--width 100000: the sheet needs about" in err and "lower --width" in err
    assert not (tmp_path / "s.png").exists()
    # a sane width passes the check (and then finds no finished clip in this hand-written index)
    code, err = _main(["preview", ds, "-o", tmp_path / "s.png", "--width", "256"], capsys)
    assert code == 2 and "memory" not in err
    assert os.environ["BLENDSR_MEMORY_AVAILABLE"] == str(8 * 2**30)
