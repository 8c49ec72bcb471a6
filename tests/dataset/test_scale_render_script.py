"""Issue 54: benchmarks/scale_render.sh renders the scale round in the order its runs wait for: the index, val, the
scaling subsets as prefixes smallest first, test, then the rest (DRY=1: the lists are written and the render commands
printed, nothing rendered)."""
from __future__ import annotations

import os
import subprocess
import sys

from tests.conftest import REPO


def _spec(path):
    path.write_text('[dataset]\nname = "round"\n[render]\nframes = 2\nhr_size = "64x36"\n'
                    '[[source]]\nname = "tr"\nkind = "builtin"\nseeds = "0:8"\nsplit = "train"\n'
                    '[[source]]\nname = "va"\nkind = "builtin"\nseeds = "20:21"\nsplit = "val"\n'
                    '[[source]]\nname = "te"\nkind = "builtin"\nseeds = "30:31"\nsplit = "test"\n')
    return path


def test_the_round_renders_val_then_nested_subsets_then_test_then_the_rest(tmp_path):
    spec, data = _spec(tmp_path / "round.toml"), tmp_path / "ds"
    env = {**os.environ, "DRY": "1", "PY": sys.executable, "SUBSETS": "1 1,3", "UNIT": str(2 * 64 * 36)}
    out = subprocess.run(["bash", str(REPO / "benchmarks/scale_render.sh"), "ds", "round.toml"], env=env,
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)  # paths read from the caller's
    assert out.returncode == 0, out.stderr[-2000:]
    lists = [(tmp_path / "ds.lists" / f"subset_{m}.txt").read_text().split() for m in ("1", "1_3")]
    assert len(lists[0]) == 1 and len(lists[1]) == 3 and lists[1][:1] == lists[0]  # nested: a prefix
    steps = [line.split(" -o ")[1] for line in out.stdout.splitlines() if line.startswith("+ ")]
    want = ["--split val", *(f"--clips @{tmp_path}/ds.lists/subset_{m}.txt" for m in ("1", "1_3")), "--split test", ""]
    assert [s.split("--workers 2")[1].strip() for s in steps] == want
    assert (data / "dataset.json").is_file()
    assert not (data / "clips").exists() or not any((data / "clips").iterdir())  # DRY: nothing rendered
