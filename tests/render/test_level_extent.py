"""The level path planner at any extent (issue 43, items 4 and 7): a path is kept only when Blender's 32-bit
positions reproduce its motion (a 1e7 m level gave wrong walk motion and a fly camera at twice its declared speed),
a level too far from the origin or too small is refused at once in one line, and a mesh of zero extent is a typed
error (it was an IndexError traceback)."""
from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("trimesh")

from tests.conftest import requires_bpy, run_cli  # noqa: E402
from gbuffer_export.blender.level_cameras import (FLOAT32_STEP_TOLERANCE, PathError, PathRules,  # noqa: E402
                                                  float32_step_error, plan_level_path)
from gbuffer_export.blender.level_geometry import LevelGeometry, LevelGeometryError  # noqa: E402
from tests.render.test_level_cameras import FPS, HFOV, VFOV, _room  # noqa: E402


def _scaled(scale: float, shift: float = 0.0) -> LevelGeometry:
    r = _room()
    return LevelGeometry(r.vertices * scale + shift, r.faces, owner=r.owner)


def _as_blender_moves(eyes: np.ndarray) -> np.ndarray:
    """Speeds (scene units per frame) of the eyes as Blender stores them (float32)."""
    return np.linalg.norm(np.diff(eyes.astype(np.float32).astype(np.float64), axis=0), axis=1)


@pytest.mark.parametrize("kind", ["walk", "fly"])
def test_a_1e7_m_level_gives_paths_blender_moves_as_planned_or_none(kind):
    geom = _scaled(1e6)  # a room 12 000 km wide: extent about 1.3e7 m
    assert geom.extent > 1e7
    rules = PathRules(tries=20)
    try:
        path = plan_level_path(geom, kind, 12, FPS, 0, (HFOV, VFOV), rules=rules)
    except PathError as exc:
        assert "32-bit" in str(exc)
        return
    declared = rules.walk_speed_mps if kind == "walk" else rules.fly_speed_mps
    measured = _as_blender_moves(path.eyes) * FPS
    assert measured.max() <= declared * 1.02 * (np.sqrt(2) if kind == "walk" else 1.0), measured
    assert float32_step_error(path.eyes) <= FLOAT32_STEP_TOLERANCE


@pytest.mark.parametrize("kind", ["walk", "fly"])
def test_a_level_far_from_the_origin_is_refused_at_once(kind):
    geom = _scaled(1.0, shift=1e7)  # a 12 m room 10 000 km from the origin: float32 positions 1 m apart
    t0 = time.process_time()  # this process's CPU: other work on the machine does not count
    with pytest.raises(PathError, match=r"from the scene's origin.*32-bit positions are 1 m apart"):
        plan_level_path(geom, kind, 12, FPS, 0, (HFOV, VFOV))
    assert time.process_time() - t0 < 2


def test_a_large_level_near_the_origin_plans_exactly():
    geom = _scaled(1e3)  # 12 km across, centred on the origin
    path = plan_level_path(geom, "fly", 12, FPS, 1, (HFOV, VFOV), rules=PathRules(tries=20))
    assert float32_step_error(path.eyes) <= FLOAT32_STEP_TOLERANCE
    assert np.allclose(_as_blender_moves(path.eyes) * FPS, PathRules().fly_speed_mps, rtol=0.02)


def test_a_level_smaller_than_a_cameras_clearance_is_refused():
    with pytest.raises(PathError, match="too small to hold a camera"):
        plan_level_path(_scaled(0.02), "fly", 6, FPS, 0, (HFOV, VFOV))


def test_a_mesh_of_zero_extent_is_a_typed_error():
    with pytest.raises(LevelGeometryError, match="zero extent"):
        LevelGeometry(np.zeros((3, 3)), np.array([[0, 1, 2]]))


@requires_bpy
@pytest.mark.bpy
def test_render_fly_on_a_mesh_of_zero_extent_is_one_line(tmp_path):
    import trimesh
    scene = tmp_path / "zero.glb"
    trimesh.Trimesh(np.zeros((3, 3)), [[0, 1, 2]], process=False).export(scene)
    proc = run_cli("render", scene, "-o", tmp_path / "out", "--camera-path", "fly", "--light", "sky",
                   "--hr-size", "64x36", "--frames", "1:2", "--hr-spp", "1", "--lr-spp", "1", "--threads", "1",
                   "--no-progress", timeout=300)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert f"error: {scene}: " in proc.stderr and "zero extent" in proc.stderr
