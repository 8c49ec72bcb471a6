"""A disk that fills during ``export-dataset --append`` (issue 56): one line naming the file that could not be
written, exit 2, the export as it was and no temporary left. Simulated (an ENOSPC without a file name, as a
``write`` or ``fsync`` raises it) for every format, and for real on a small tmpfs where mounting one is allowed."""
from __future__ import annotations

import errno
import os
import subprocess
from pathlib import Path

import pytest

from gbuffer_export.synthetic import make_synthetic_clip
from tests.core.test_export_rules import one_error, run, tree as _tree


def tree(p: Path) -> dict[str, bytes]:
    """The export's files (its lock file, OUT/.lock, is not part of it)."""
    return {k: v for k, v in _tree(p).items() if k != ".lock"}


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("full") / "c", frames=(1, 2), hr_size=(16, 8), scales=(2,))


@pytest.mark.parametrize("fmt", ["nss", "rdg"])
def test_a_full_disk_during_append_names_the_file(clip, tmp_path, capsys, monkeypatch, fmt):
    out = tmp_path / "out"
    assert run(["export-dataset", clip, "--format", fmt, "-o", out], capsys)[0] == 0
    before = tree(out)

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")  # no file name, as the kernel's write error
    monkeypatch.setattr(os, "fsync", full)
    line = one_error(*run(["export-dataset", clip, "--format", fmt, "-o", out, "--append"], capsys))
    assert line.endswith(": no space left on device") and str(tmp_path) in line, line
    path = line.removeprefix("blendsr: error: ").removesuffix(": no space left on device")
    assert Path(path).name in ("0001.json", "meta_info_train.txt") or path.endswith(".png"), line
    monkeypatch.undo()
    assert tree(out) == before  # nothing of the failed append is in the export
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_real_full_disk_during_append_names_a_file(tmp_path, capsys):
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=600k", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("mounting a tmpfs is not permitted here (needs root); the simulated test covers the logic")
    try:
        src = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(128, 64), scales=(2,))
        out = mnt / "out"
        assert run(["export-dataset", src, "--format", "nss", "-o", out], capsys)[0] == 0
        before = tree(out)
        with open(mnt / "filler", "wb", buffering=0) as f:  # leave about 40 kB: the first EXR or two fit
            f.write(b"\0" * max(os.statvfs(mnt).f_bavail * os.statvfs(mnt).f_frsize - 40_000, 0))
        line = one_error(*run(["export-dataset", src, "--format", "nss", "-o", out, "--append"], capsys))
        assert line.endswith(": no space left on device") and f"{mnt}/" in line, line
        (mnt / "filler").unlink()
        assert tree(out) == before and sorted(p.name for p in mnt.iterdir()) == ["out"]
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)
