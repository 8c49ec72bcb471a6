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

ENV = dict(os.environ, MALLOC_MMAP_THRESHOLD_="4294967296", MALLOC_TRIM_THRESHOLD_="68719476736")


def run_cli(*args, timeout=600, check=False) -> subprocess.CompletedProcess:
    """Run ``blendsr ARGS`` in a fresh Python process; returns the completed process (text output)."""
    proc = subprocess.run([sys.executable, "-m", "gbuffer_export.cli", *map(str, args)], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=timeout)
    if check and proc.returncode != 0:
        raise AssertionError(f"blendsr {' '.join(map(str, args))} exited {proc.returncode}:\n{proc.stderr[-3000:]}")
    return proc


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


requires_bpy = pytest.mark.skipif(not HAVE_BPY, reason="bpy is not installed (pip install 'blendsr[render]')")


@pytest.fixture(scope="session")
def blend_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("blends")
