"""Issue 26 (items 6 and 14): the CLI's one error boundary. Bad input (BlendSR's typed errors, missing paths,
filesystem faults) is one line with exit 2; anything else is a bug: its traceback and exit 70."""
from __future__ import annotations

import argparse
import errno
import os
import subprocess
import types

import pytest
from tests.conftest import requires_bpy, run_cli

from gbuffer_export import cli
from gbuffer_export.errors import BlendSRError


def _main_raising(monkeypatch, exc, command="render"):
    def build():
        parser = argparse.ArgumentParser(prog="blendsr")
        sub = parser.add_subparsers(dest="command")
        p = sub.add_parser(command)

        def func(args):
            raise exc
        p.set_defaults(func=func)
        return parser
    monkeypatch.setattr(cli, "build_parser", build)
    return cli.main([command])


@pytest.mark.parametrize("command", ["render", "dataset", "train", "export"])
@pytest.mark.parametrize("code,words", [(errno.EROFS, "read-only file system"),
                                        (errno.ENOSPC, "no space left on device"),
                                        (errno.EACCES, "permission denied")])
def test_filesystem_faults_are_one_line_exit_2(monkeypatch, capsys, command, code, words):
    rc = _main_raising(monkeypatch, OSError(code, os.strerror(code), "/data/out/frames"), command)
    err = capsys.readouterr().err
    assert rc == 2
    assert err.strip() == f"blendsr: error: /data/out/frames: {words}"


def test_a_filesystem_fault_wrapped_by_a_library_is_still_one_line(monkeypatch, capsys):
    try:
        try:
            raise OSError(errno.ENOSPC, "No space left on device", "/ds/dataset.json")
        except OSError as inner:
            raise RuntimeError("save failed") from inner
    except RuntimeError as exc:
        wrapped = exc
    assert _main_raising(monkeypatch, wrapped) == 2
    assert "/ds/dataset.json: no space left on device" in capsys.readouterr().err


def test_typed_bad_input_is_one_line(monkeypatch, capsys):
    from gbuffer_export.clip import ClipError
    from gbuffer_export.config import ConfigError
    from gbuffer_export.dataset.build import DatasetError
    from gbuffer_export.dataset.spec import SpecError
    from gbuffer_export.exr import ExrError
    for cls in (ConfigError, SpecError, ClipError, DatasetError, ExrError, BlendSRError, cli.UsageError):
        assert issubclass(cls, BlendSRError) and issubclass(cls, ValueError)
        assert _main_raising(monkeypatch, cls("spec.toml: bad key\nmore")) == 2
        assert capsys.readouterr().err == "blendsr: error: spec.toml: bad key\n"


def test_an_internal_value_error_is_reported_as_a_bug_with_its_traceback(monkeypatch, capsys):
    rc = _main_raising(monkeypatch, ValueError("operands could not be broadcast together with shapes (3,) (4,)"))
    err = capsys.readouterr().err
    assert rc == cli.EXIT_INTERNAL == 70
    assert "Traceback" in err
    assert "blendsr: internal error (a bug, please report it" in err
    assert "broadcast" in err.splitlines()[-1]


def test_other_exceptions_are_bugs_too(monkeypatch, capsys):
    assert _main_raising(monkeypatch, KeyError("path")) == 70
    assert "internal error" in capsys.readouterr().err


def test_typed_errors_of_the_other_layers_are_bad_input():
    pytest.importorskip("torch")
    from training.checkpoint import CheckpointError
    assert issubclass(CheckpointError, BlendSRError)


@pytest.fixture
def tmpfs(tmp_path):
    """mount(ro: bool, size: str) -> a fresh tmpfs folder, unmounted at teardown."""
    mounted = []

    def mount(ro=False, size="1m"):
        d = tmp_path / f"fs{len(mounted)}"
        d.mkdir()
        opts = f"size={size}" + (",ro" if ro else "")
        proc = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(d)], capture_output=True, text=True)
        if proc.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here (needs root / CAP_SYS_ADMIN): {proc.stderr.strip()}")
        mounted.append(d)
        return d
    yield mount
    for d in mounted:  # lazily when a library still holds a file there (torch after a failed save)
        if subprocess.run(["umount", str(d)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(d)], capture_output=True)


@requires_bpy
def test_render_into_a_read_only_folder_is_one_line(tmpfs):
    ro = tmpfs(ro=True)
    proc = run_cli("render", "-o", ro / "c", "--hr-size", "64x36", "--frames", "1:1", "--hr-spp", "2",
                   "--lr-spp", "1", "--threads", "1")
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1] == f"blendsr: error: {ro / 'c'}: read-only file system"
    assert "Traceback" not in proc.stderr


def test_dataset_into_a_read_only_folder_is_one_line(tmpfs, tmp_path):
    ro = tmpfs(ro=True)
    spec = tmp_path / "spec.toml"
    spec.write_text('[dataset]\nname = "ro"\n[render]\nhr_size = "64x36"\nframes = 2\nhr_spp = 2\nlr_spp = 1\n'
                    '[[source]]\nname = "b"\nkind = "builtin"\nseeds = "0:1"\n')
    proc = run_cli("dataset", spec, "-o", ro / "ds", "--threads", "1")
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "read-only file system" in proc.stderr.strip().splitlines()[-1]
    assert "Traceback" not in proc.stderr


@requires_bpy
def test_a_full_disk_under_cycles_is_not_blamed_on_the_exr(tmpfs):
    """Cycles' temporary EXR cannot be written: the error is ENOSPC naming the folder, not 'not a readable EXR'."""
    from gbuffer_export.blender.render import _check_disk_after_write
    full = tmpfs(size="64k")
    (full / "filler").write_bytes(b"\0" * 60_000)
    scene = types.SimpleNamespace(render=types.SimpleNamespace(resolution_x=64, resolution_y=36,
                                                               resolution_percentage=100))
    with pytest.raises(OSError) as info:
        _check_disk_after_write(full / "hr_radiance.exr", scene)
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(full)
    assert cli.bad_input_line(info.value) == f"{full}: no space left on device"


def test_a_checkpoint_saved_to_a_full_disk_is_enospc_naming_the_file(tmpfs):
    """torch.save reports a full disk as a RuntimeError ('unexpected pos'); save_checkpoint says what it was."""
    torch = pytest.importorskip("torch")
    from training.checkpoint import save_checkpoint
    full = tmpfs(size="64k")
    with pytest.raises(OSError) as info:
        save_checkpoint(full / "checkpoints" / "last.pt", {"w": torch.zeros(100_000)})
    assert info.value.errno == errno.ENOSPC
    assert cli.bad_input_line(info.value) == f"{full / 'checkpoints' / 'last.pt'}: no space left on device"
    assert not list((full / "checkpoints").iterdir())  # no temporary left behind


def test_train_into_a_read_only_folder_is_one_line(tmpfs, tmp_path, capsys):
    pytest.importorskip("torch")
    from gbuffer_export.synthetic import make_synthetic_clip
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 5), hr_size=(64, 36), scale=4)
    ro = tmpfs(ro=True)
    rc = cli.main(["train", "--model", "fusesr", "--data", str(clip), "-o",
                   str(ro / "run"), "--max-steps", "1", "--set", "run.progress=false"])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert err.splitlines()[-1] == f"blendsr: error: {ro / 'run'}: read-only file system"


def test_export_into_a_read_only_folder_is_one_line(tmpfs, capsys):
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    ro = tmpfs(ro=True)
    rc = cli.main(["export", "--model", "bicubic", "--onnx", str(ro / "x.onnx"), "--hr-size", "64x36"])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert err.splitlines()[-1] == f"blendsr: error: {ro / 'x.onnx'}: read-only file system"
