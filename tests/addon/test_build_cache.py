"""Two add-on builds at once share the graph cache (``build/addon-onnx``) without emptying it under each other: the
second waits on ``<cache>.lock`` and reuses what the first exported. (Two test workers building the zip at once
lost a graph that way: one emptied the folder while the other was checking its export.)"""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from filelock import FileLock

REPO = Path(__file__).resolve().parents[2]
EXPORT = """
import sys
from pathlib import Path
import filelock, onnxruntime, training.inference.export, training.inference.loading, training.inference.onnx_infer
from blender_addon import build
print("ready", flush=True)  # the imports done: export_graphs reaches the lock within a moment
build.preview_graphs = lambda: [("bilinear", None)]
print(sorted(p.name for p in build.export_graphs(Path(sys.argv[1])).iterdir()))
"""


def _export(cache: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", EXPORT, str(cache)], cwd=REPO, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def test_a_second_build_waits_for_the_first_and_reuses_its_graphs(tmp_path):
    cache = tmp_path / "addon-onnx"
    with FileLock(str(cache) + ".lock"):  # a build in progress holds the cache
        waiting = _export(cache)
        assert waiting.stdout.readline().strip() == "ready", waiting.stderr.read()
        time.sleep(2)
        assert waiting.poll() is None and not cache.exists(), "the build did not wait for the cache's lock"
    out, err = waiting.communicate(timeout=300)
    assert waiting.returncode == 0, err
    assert "bilinear_xany.onnx" in out
    stamp = (cache / "training.sha256").stat().st_mtime_ns
    again = _export(cache)
    out2, err2 = again.communicate(timeout=300)
    assert again.returncode == 0, err2
    # reused, not re-exported: the same listing after its "ready" line, the stamp untouched
    assert out2.split("\n", 1)[1] == out and (cache / "training.sha256").stat().st_mtime_ns == stamp
