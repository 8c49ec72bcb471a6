"""Real third-party scenes from ../shared/scenes render into clips that validate."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import requires_bpy, run_cli, shared_or_skip
from gbuffer_export import open_clip
from gbuffer_export.conventions import Flag
from gbuffer_export.validate import validate_clip

pytestmark = [pytest.mark.bpy, requires_bpy]
FAST = ["--hr-spp", "4", "--lr-spp", "2", "--gbuffer-spp", "1", "--no-progress"]


def test_robot_expressive_old_blend(tmp_path):
    """An old file: own view-layer name, interleaved-EXR setting, armatures, no camera."""
    scene = shared_or_skip("scenes/blend/RobotExpressive.blend")
    out = tmp_path / "robot"
    proc = run_cli("render", scene, "-o", out, "--frames", "2:3", "--hr-size", "96x64", "--buffers", "all", *FAST)
    assert proc.returncode == 2 and "no camera" in proc.stderr
    run_cli("render", scene, "-o", out, "--frames", "2:3", "--hr-size", "96x64", "--buffers", "all",
            "--camera-path", "orbit", *FAST, check=True)
    rep = validate_clip(out)
    assert rep.ok, [f.line() for f in rep.errors]
    clip = open_clip(out)
    flags = clip.read(2, "hr/flags")[..., 0]
    surf = (flags & int(Flag.BACKGROUND)) == 0
    assert 0.02 < surf.mean() < 0.98  # the robot is in view
    assert (flags[surf] & int(Flag.MOVING)).all()  # armature-deformed
    assert (flags[surf] & int(Flag.NON_PRINCIPLED)).all()  # Diffuse BSDF materials
    assert clip.read(2, "hr/albedo")[surf].max() > 0.1  # diffuse colour still exported
    assert clip.manifest["scene"]["file"] == "RobotExpressive.blend"
