"""Two ``blendsr export-dataset --append`` at once onto one export (issue 56, item 4): the second waits for the
export's lock, then numbers its sequences (or RDG scenes) after the first's; no sequence is lost or mixed, for
every format. The test holds the lock itself while both start, so that they surely run side by side, then lets
them go; each must report that it waits."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gbuffer_export.synthetic import SyntheticLook, make_synthetic_clip

REPO = Path(__file__).resolve().parents[2]
ENV = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))


@pytest.fixture(scope="module")
def small_clips(tmp_path_factory):
    root = tmp_path_factory.mktemp("race")
    return {n: make_synthetic_clip(root / n, frames=range(1, k + 1), hr_size=(16, 8), scales=(2, 4))
            for n, k in (("base", 1), ("a", 3), ("b", 2))}


@pytest.fixture(scope="module")
def hd_clips(tmp_path_factory):
    root = tmp_path_factory.mktemp("race_hd")
    # NFRU's reader loads 1920x1080 only: one such clip, and two copies of it (the race is about sequences, not
    # pictures; a copy is a clip of its own name, which the export lists as its source)
    hd = make_synthetic_clip(root / "base_hd", frames=(1,), hr_size=(1920, 1080), scales=(2,),
                             buffers=("radiance", "depth", "motion"), look=SyntheticLook(hr_supersample=1))
    return {"base": hd, **{n: Path(shutil.copytree(hd, root / f"{n}_hd")) for n in ("a", "b")}}


def _start(src: Path, fmt: str, out: Path, log: Path) -> subprocess.Popen:
    with open(log, "w") as f:
        return subprocess.Popen([sys.executable, "-m", "gbuffer_export.cli", "export-dataset", str(src), "--format",
                                 fmt, "-o", str(out), "--append"], cwd=REPO, env=ENV, stdout=f, stderr=f)


def _frames_of(out: Path, fmt: str) -> dict[str, tuple[str, int]]:
    """{sequence or scene: (source clip, frames)} as the export lists them."""
    if fmt == "rdg":
        lines = (out / "meta_info_train.txt").read_text().splitlines()
        return {ln.split()[0]: (ln.split()[0], int(ln.split()[1])) for ln in lines}
    got = {}
    for js in sorted(out.glob("*.json")):
        meta = json.loads(js.read_text())
        got[js.stem] = (Path(meta["BlendSR"]["clip"]).name, len(meta["Frames"]))
    return got


@pytest.mark.parametrize("fmt", ["nss", "nfru", "rdg"])
def test_two_appends_at_once_lose_no_sequence(request, tmp_path, fmt):
    from gbuffer_export.cli import main
    from gbuffer_export.locks import FolderLock
    src = request.getfixturevalue("hd_clips" if fmt == "nfru" else "small_clips")
    out = tmp_path / "out"
    assert main(["export-dataset", str(src["base"]), "--format", fmt, "-o", str(out)]) == 0
    held = FolderLock(out, "test holds it")  # the export's lock (OUT/.lock): both appends must wait for it
    try:
        logs = [tmp_path / "a.log", tmp_path / "b.log"]
        procs = [_start(src["a"], fmt, out, logs[0]), _start(src["b"], fmt, out, logs[1])]
        t0 = time.monotonic()
        while time.monotonic() - t0 < 120 and any(p.poll() is None for p in procs):
            if all("waiting for it" in g.read_text() for g in logs):  # both wait on the lock: let them race
                break
            time.sleep(0.1)
    finally:
        held.close()
    for p in procs:
        p.wait(timeout=300)
    texts = [g.read_text() for g in logs]
    assert [p.returncode for p in procs] == [0, 0], texts
    assert all("waiting for it" in t and "Traceback" not in t for t in texts), texts
    got = _frames_of(out, fmt)
    if fmt == "rdg":
        assert sorted(got) == ["a", "b", "base"] and got["a"][1] == 3 and got["b"][1] == 2
        assert (out / "meta_info_test.txt").read_text().split()[::3] == list(got)
        for scene, (_, n) in got.items():  # no scene's folder holds another's frames
            assert len(list((out / "GT" / scene / "Image").glob("*.png"))) == n
    else:
        assert sorted(got) == ["0000", "0001", "0002"], got
        assert sorted(c for c, _ in got.values()) == sorted(src[k].name for k in ("base", "a", "b"))
        for seq, (_, n) in got.items():  # each sequence's folders hold its own frames, not a mix
            assert len(list((out / "ground_truth" / seq).glob("*.exr"))) == n
    assert not list(tmp_path.glob(".out.*")), list(tmp_path.iterdir())  # no sibling left
