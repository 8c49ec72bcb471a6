"""Generated camera paths (gbuffer_export.blender.camera_paths), run in subprocesses."""
from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import requires_bpy
from tests.render.test_scene_default import run_probe

pytestmark = [pytest.mark.bpy, requires_bpy]
FRAMES = (1, 24)
# walk seeds 15 and 17: their first candidate path runs into geometry (the retry logic is exercised)
RUNS = [["orbit", 0], ["orbit", 0], ["orbit", 7], ["walk", 0], ["walk", 0], ["walk", 7], ["walk", 15], ["walk", 17]]


@pytest.fixture(scope="module")
def default_paths():
    return run_probe("paths_default", {"frames": list(FRAMES), "runs": RUNS})


@pytest.fixture(scope="module")
def scaled_paths():
    """The same small scene (a block, a post, a hidden box, an unflagged ground) at 7 cm and at 100 m scale."""
    return {s: run_probe("paths_scaled", {"frames": list(FRAMES), "runs": RUNS, "scale": s}) for s in (0.07, 100.0)}


@pytest.fixture(params=["default", "7cm", "100m"])
def paths(request, default_paths, scaled_paths):
    return {"default": default_paths, "7cm": scaled_paths[0.07], "100m": scaled_paths[100.0]}[request.param]


def _positions(run):
    return np.array(run["matrices"])[:, :3, 3]


def test_keys_on_every_frame_from_start_minus_one(paths):
    expect = [float(f) for f in range(FRAMES[0] - 1, FRAMES[1] + 1)]
    for run in paths["runs"]:
        assert run["type"] == "PERSP" and run["is_scene_camera"] and run["name"] == "BlendSR Camera"
        curves = {(fc[0], fc[1]): fc for fc in run["fcurves"]}
        assert set(curves) == {(p, i) for p in ("location", "rotation_euler") for i in range(3)}
        for fc in curves.values():
            assert fc[2] == expect and fc[3] == ["LINEAR"]


def test_reuses_one_camera_and_action(paths):
    runs = paths["runs"]
    assert all(run["n_cameras"] == 1 for run in runs)
    assert runs[0]["actions_added"] == 1 and all(run["actions_added"] == 0 for run in runs[1:])


def test_same_seed_same_path_other_seed_differs(paths):
    runs = paths["runs"]
    for i, j, k in ((0, 1, 2), (3, 4, 5)):
        assert runs[i]["matrices"] == runs[j]["matrices"]
        assert np.abs(_positions(runs[i]) - _positions(runs[k])).max() > 0.05 * paths["radius"]


def test_paths_are_smooth(paths):
    r = paths["radius"]
    for run in paths["runs"]:
        pos = _positions(run)
        step = np.linalg.norm(np.diff(pos, axis=0), axis=1)
        acc = np.linalg.norm(np.diff(pos, 2, axis=0), axis=1)
        assert step.min() > 1e-3 * r, run["kind"]
        assert acc.max() < 0.2 * step.mean() + 1e-9 * r, run["kind"]
        if run["kind"] == "walk":
            # constant, walking-like speed relative to the scene: 1.2-2.2 % of the framing radius per frame
            assert np.ptp(step) < 0.05 * step.mean()
            assert 0.01 * r < step.mean() < 0.025 * r
        fwd = -np.array(run["matrices"])[:, :3, 2]
        turn = np.degrees(np.arccos(np.clip(np.sum(fwd[1:] * fwd[:-1], axis=1), -1, 1)))
        assert turn.max() < 3.0, run["kind"]
        assert np.abs(np.diff(turn)).max() < 0.5, run["kind"]


def test_orbit_circles_the_centre_and_sees_it(paths):
    c = np.array(paths["centre"])
    for run in paths["runs"]:
        if run["kind"] != "orbit":
            continue
        pos = _positions(run)
        d = np.linalg.norm(pos - c, axis=1)
        assert np.ptp(d) < 1e-4 * d.mean()
        assert d.min() > paths["radius"]                     # outside the framing sphere
        elev = np.degrees(np.arcsin((pos[:, 2] - c[2]) / d))
        assert np.ptp(elev) < 1e-3 and 11.9 < elev[0] < 35.1
        proj = np.array(run["projected"])[:, 0]            # centre in normalised view coords (x, y, depth)
        assert np.allclose(proj[:, :2], 0.5, atol=1e-3)


def test_cameras_stay_clear_of_geometry_and_above_ground(paths):
    r = paths["radius"]
    boxes = paths["boxes"]
    ground_top = max(b[2][2] for b in boxes if b[3])
    for run in paths["runs"]:
        pos = _positions(run)
        # dense check between keys too: linear interpolation between frames is what Blender evaluates
        t = np.linspace(0, 1, 9)[:, None, None]
        dense = (pos[:-1][None] * (1 - t) + pos[1:][None] * t).reshape(-1, 3)
        assert (dense[:, 2] > ground_top + 0.07 * r).all(), run["kind"]
        for name, lo, hi, ground in boxes:
            if ground:
                continue
            inside = np.all((dense > np.array(lo) - 0.07 * r) & (dense < np.array(hi) + 0.07 * r), axis=1)
            assert not inside.any(), (run["kind"], run["seed"], name)
        near = min(np.min(np.linalg.norm(pos - np.clip(pos, lo, hi), axis=1)) for _, lo, hi, _ in boxes)
        assert run["clip"][0] < near
        corners = np.array([[x, y, z] for _, lo, hi, _ in boxes
                            for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        far = np.linalg.norm(corners[None] - pos[:, None], axis=2).max()
        assert run["clip"][1] > far


def test_walk_keeps_the_scene_in_view(paths):
    for run in paths["runs"]:
        proj = np.array(run["projected"])[:, 0]
        assert (proj[:, 2] > 0).all()                       # centre in front of the camera
        if run["kind"] == "walk":
            assert (np.abs(proj[:, :2] - 0.5) < 0.75).all()  # and never far outside the frame


def test_framing_is_scale_invariant(scaled_paths):
    small, big = scaled_paths[0.07], scaled_paths[100.0]
    for res, s in ((small, 0.07), (big, 100.0)):
        # Bounds ignore the hidden object and include the flat ground, found without a custom property.
        lo, hi = np.array(res["bounds"])
        assert np.allclose(lo, np.array([-15, -15, -0.02]) * s, rtol=1e-5)
        assert np.allclose(hi, np.array([15, 15, 1.8]) * s, rtol=1e-5)
        assert [b[0] for b in res["boxes"] if b[3]] == ["Ground"]
        assert res["radius"] == pytest.approx(0.5 * np.linalg.norm([1.45, 0.65, 1.8]) * s, rel=1e-5)
    # The same seed gives the same path and clipping in units of the scene's size.
    for a, b in zip(small["runs"], big["runs"]):
        assert np.allclose(_positions(a) / 0.07, _positions(b) / 100.0, rtol=1e-4, atol=1e-4)
        assert np.allclose(np.array(a["clip"]) / 0.07, np.array(b["clip"]) / 100.0, rtol=1e-4)
