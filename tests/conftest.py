"""Shared test helpers: run the CLI in a subprocess, build tiny .blend fixtures, locate ../shared."""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
SCENES_SCRIPT = Path(__file__).with_name("scenes.py")
HAVE_BPY = importlib.util.find_spec("bpy") is not None

# The suite runs models on the fast inference path unless a test asks for another: the product's default ("auto",
# training.inference.fastpath.AutoPath) compiles the whole model on the CPU (tens of seconds a model), which the tests of
# the paths themselves (tests/train/test_inference_paths.py) pay once, not every command test.
os.environ.setdefault("BLENDSR_INFERENCE_PATH", "fast")


def _worker_threads() -> None:
    """Under pytest-xdist, each worker's share of the cores as OMP_NUM_THREADS (torch, and the library's default
    threads, ``resources.default_threads``, read it; subprocesses inherit it): two workers with two torch threads
    each on 2 cores wait for each other (the demo's fine-tune: 0.18 steps/s against 1.43 with one thread beside two
    busy processes, docs/bench/demo_speed). A value the user set is kept."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if workers > 1 and "OMP_NUM_THREADS" not in os.environ:
        from gbuffer_export.resources import usable_cores
        os.environ["OMP_NUM_THREADS"] = str(max(1, usable_cores() // workers))


_worker_threads()
ENV = dict(os.environ, MALLOC_MMAP_THRESHOLD_="4294967296", MALLOC_TRIM_THRESHOLD_="68719476736")


def run_cli(*args, timeout=600, check=False) -> subprocess.CompletedProcess:
    """Run ``blendsr ARGS`` in a fresh Python process; returns the completed process (text output)."""
    proc = subprocess.run([sys.executable, "-m", "gbuffer_export.cli", *map(str, args)], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=timeout)
    if check and proc.returncode != 0:
        raise AssertionError(f"blendsr {' '.join(map(str, args))} exited {proc.returncode}:\n{proc.stderr[-3000:]}")
    return proc


def set_args(items) -> list[str]:
    """``--set`` arguments for the CLI: ["a=1", "b=2"] -> ["--set", "a=1", "--set", "b=2"]."""
    return [a for s in items for a in ("--set", s)]


def make_blend(kind: str, path: Path) -> Path:
    """Build one of the fixtures of tests/scenes.py into ``path`` (in a subprocess)."""
    proc = subprocess.run([sys.executable, str(SCENES_SCRIPT), kind, str(path)], capture_output=True, text=True,
                          timeout=120, env=ENV)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return path


def shared_or_skip(rel: str) -> Path:
    p = SHARED / rel
    if not p.exists():
        pytest.skip(f"{p} is absent (../shared/scenes is not beside the repository)")
    return p


def builtin_spec(path: Path, seeds: str = "0:11") -> Path:
    """A dataset spec of built-in scenes only (no ../shared), for tests that plan or dry-run a dataset."""
    path.write_text('[dataset]\nname = "builtin-only"\n[render]\nframes = 4\nhr_size = "64x36"\n'
                    f'[[source]]\nname = "b"\nkind = "builtin"\nseeds = "{seeds}"\n')
    return path


requires_bpy = pytest.mark.skipif(not HAVE_BPY, reason="bpy is not installed (pip install 'blendsr[render]')")


@pytest.fixture(scope="session")
def blend_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("blends")


def assert_same_render(a: dict, b: dict) -> int:
    """Two renders of one command, as ``{(frame, 'lvl/buffer'): array}``: the guarantee of docs/clip-format.md,
    "Reproducibility". G-buffers agree to float rounding (flags exactly); radiance is the same image in expectation
    (per-frame means within 3%). Returns how many radiance images are bit-identical (the usual case on an idle
    machine with ``--threads 1``; not guaranteed under CPU contention, so not asserted)."""
    import numpy as np
    assert a.keys() == b.keys() and a, (sorted(a)[:4], sorted(b)[:4])
    identical = 0
    for k in a:
        x, y = np.asarray(a[k]), np.asarray(b[k])
        assert x.shape == y.shape and x.dtype == y.dtype, k
        if k[1].endswith("radiance"):
            fx, fy = np.isfinite(x), np.isfinite(y)
            assert np.array_equal(fx, fy), f"{k}: non-finite pixels differ"
            mx, my = float(x[fx].mean()), float(y[fy].mean())
            assert abs(mx - my) <= 0.03 * max(abs(mx), abs(my), 1e-6), f"{k}: mean {mx} vs {my}"
            identical += x.tobytes() == y.tobytes()
        elif k[1].endswith("flags") or not np.issubdtype(x.dtype, np.floating):
            assert np.array_equal(x, y), f"{k} differs"
        else:
            assert np.allclose(x, y, rtol=1e-6, atol=1e-6, equal_nan=True), f"{k} differs beyond float rounding"
    return identical


def edit_manifest(clip: Path, fn) -> None:
    """Apply ``fn`` to a clip's manifest (a dict) and write it back atomically."""
    import json

    from gbuffer_export.clip import write_json_atomic
    m = json.loads((clip / "manifest.json").read_text())
    fn(m)
    write_json_atomic(clip / "manifest.json", m)


def edit_header(clip: Path, fn) -> None:
    """Apply ``fn`` to a clip's manifest and re-stamp its identity (``clip.header_identity``), as a render with the
    edited settings would have written it (``edit_manifest`` alone leaves the old identity: ``manifest-identity``)."""
    from gbuffer_export.clip import header_identity

    def stamped(m):
        fn(m)
        m["identity"] = header_identity(m)
    edit_manifest(clip, stamped)


def edit_record(clip: Path, frame: int, fn) -> None:
    """Apply ``fn`` to a frame's record both in the manifest and in frames/ (so they stay merged)."""
    import json

    from gbuffer_export.clip import write_json_atomic
    edit_manifest(clip, lambda m: fn(m["frame_data"][str(frame)]))
    rp = clip / "frames" / f"{frame:06d}.json"
    rec = json.loads(rp.read_text())
    fn(rec)
    write_json_atomic(rp, rec)


def mark_folder(items, folder: Path, *marks) -> None:
    """Add ``marks`` to every collected test that lives under ``folder`` (each test folder's conftest.py calls this
    from ``pytest_collection_modifyitems``, which pytest calls with every item of the session)."""
    for item in items:
        if folder in Path(item.path).parents:
            for mark in marks:
                item.add_marker(mark)
