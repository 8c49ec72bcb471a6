"""``blendsr demo`` end to end at a tiny size: it renders the buffers every shipped network reads and scores all of
them (a shipped network whose buffer the demo did not render failed the demo after the fact)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("bpy")
pytest.importorskip("torch")
pytestmark = [pytest.mark.bpy, pytest.mark.torch]
ROOT = Path(__file__).resolve().parents[2]


def test_demo_scores_every_shipped_network_on_its_own_clips(tmp_path):
    from training.pretrained import available
    r = subprocess.run([sys.executable, "-m", "gbuffer_export.cli", "demo", "-o", str(tmp_path / "d"),
                        "--hr-size", "64x36", "--frames", "1:2", "--hr-spp", "2", "--lr-spp", "2",
                        "--no-hr-denoise", "--train-steps", "0"],
                       capture_output=True, text=True, cwd=ROOT, timeout=900,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-3000:]
    scored = [line.split()[0] for line in r.stdout.splitlines() if " PSNR " in line]
    assert {"bicubic", "demod-jbu", *available()} <= set(scored), scored
    assert (tmp_path / "d" / "side_by_side.png").is_file() and (tmp_path / "d" / "contact_sheet.png").is_file()
