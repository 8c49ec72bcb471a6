"""The built-in default scene (gbuffer_export.blender.default_scene), built and rendered in subprocesses."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ENV, REPO, requires_bpy

pytestmark = [pytest.mark.bpy, requires_bpy]
PROBES = Path(__file__).resolve().parent.parent / "scene_probes.py"


def run_probe(name: str, args: dict, timeout: int = 240) -> dict:
    proc = subprocess.run([sys.executable, str(PROBES), name, json.dumps(args)], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=timeout)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("PROBE-RESULT ")]
    assert proc.returncode == 0 and lines, f"probe {name} failed ({proc.returncode}):\n{proc.stderr[-3000:]}"
    return json.loads(lines[-1][len("PROBE-RESULT "):])


@pytest.fixture(scope="module")
def probe():
    return run_probe("default", {"builds": [
        {"seed": 0, "frames": [1, 48], "resolution": [640, 360]},
        {"seed": 0, "frames": [1, 48], "resolution": [640, 360]},
        {"seed": 1, "frames": [1, 48], "resolution": [640, 360]},
        {"seed": 5, "frames": [3, 20], "resolution": [320, 180]},
        {"seed": 1, "frames": [1, 48], "resolution": [640, 360], "props": ["broken_pane"]},
        {"seed": 1, "frames": [1, 48], "resolution": [640, 360], "props": ["window_pane"]},
    ]})


@pytest.fixture(scope="module")
def scene(probe):
    return probe["builds"][0]


def _principled(scene):
    return {n: m["inputs"] for n, m in scene["materials"].items() if m["surface"] == "BSDF_PRINCIPLED"}


def _used_materials(scene):
    return {m for ob in scene["objects"].values() for m in ob["materials"]}


def test_same_seed_gives_identical_scene(probe):
    a, b = probe["builds"][0], probe["builds"][1]
    assert a == b


def test_other_seed_gives_a_different_scene(probe):
    a, c = probe["builds"][0], probe["builds"][2]
    assert sorted(a["objects"]) == sorted(c["objects"])  # same cast ...
    moved = [n for n in a["objects"] if not np.allclose(a["objects"][n]["matrix"], c["objects"][n]["matrix"])]
    assert len(moved) >= 5, moved                           # ... placed differently
    cam_a = np.array(a["animated_matrices"]["Camera"])
    cam_c = np.array(c["animated_matrices"]["Camera"])
    assert np.abs(cam_a - cam_c).max() > 0.05


def test_frame_range_resolution_and_engine(probe):
    factory_engine = probe["factory"]["engine"]
    for b, (frames, res) in zip(probe["builds"], [((1, 48), (640, 360))] * 3 + [((3, 20), (320, 180))]):
        assert b["frames"] == list(frames)
        assert b["resolution"] == [*res, 100]
        assert b["engine"] == factory_engine  # the renderer chooses engine and sampling, not the scene


def test_all_materials_are_principled_and_procedural(scene):
    used = _used_materials(scene)
    assert len(used) >= 15
    for name in used:
        m = scene["materials"][name]
        assert m["surface"] == "BSDF_PRINCIPLED", name
        assert "TEX_IMAGE" not in m["node_types"], name
    textured = [n for n in used if {"TEX_CHECKER", "TEX_BRICK", "TEX_WAVE", "TEX_NOISE"} & set(
        scene["materials"][n]["node_types"])]
    assert len(textured) >= 5, textured


def test_metals_span_roughness(scene):
    p = _principled(scene)
    rough = sorted(v["Roughness"]["value"] for n, v in p.items()
                   if n in _used_materials(scene) and v["Metallic"]["value"] == 1.0 and not v["Roughness"]["linked"])
    assert len(rough) >= 3
    assert rough[0] <= 0.1 and rough[-1] >= 0.5
    assert len({round(r, 2) for r in rough}) >= 3


def test_glass_emission_and_hard_cases(scene):
    p = {n: v for n, v in _principled(scene).items() if n in _used_materials(scene)}
    glass = [n for n, v in p.items() if v["Transmission Weight"]["value"] == 1.0 and v["Roughness"]["value"] < 0.1]
    assert glass
    emissive = [n for n, v in p.items()
                if v["Emission Strength"]["value"] > 0 and max(v["Emission Color"]["value"][:3]) > 0]
    assert emissive
    aniso = [n for n, v in p.items() if v["Anisotropic"]["value"] > 0 and v["Metallic"]["value"] > 0]
    sss = [n for n, v in p.items() if v["Subsurface Weight"]["value"] > 0]
    assert aniso and sss
    dielectric = [n for n, v in p.items() if v["Metallic"]["value"] == 0 and v["Transmission Weight"]["value"] == 0]
    assert len(dielectric) >= 8


def test_feature_table_names_existing_things(probe, scene):
    names = set(scene["objects"]) | {"BlendSR World"}
    for feature, owners in probe["features"].items():
        assert owners and set(owners) <= names, (feature, owners)


@pytest.mark.parametrize("build, prop", [(4, "broken_pane"), (5, "window_pane")])
def test_optional_props_add_only_their_objects(probe, build, prop):
    """A prop adds its objects and leaves every other object, key and material of the seed as it was."""
    from gbuffer_export.dataset.spec import BUILTIN_PROPS
    assert tuple(probe["optional_props"]) == BUILTIN_PROPS  # the spec's names are the bpy layer's
    plain, pane = probe["builds"][2], probe["builds"][build]
    added = set(pane["objects"]) - set(plain["objects"])
    assert added == set(probe["optional_props"][prop])
    for name, ob in plain["objects"].items():
        assert np.allclose(ob["matrix"], pane["objects"][name]["matrix"]), name
    for name, m in plain["animated_matrices"].items():  # the rolling ball and the seed's own camera path
        assert np.allclose(m, pane["animated_matrices"][name]), name
    for name, m in plain["materials"].items():
        assert pane["materials"][name] == m, name


def _thin_cracked_glass(build, name):
    glass = build["objects"][name]
    m = build["materials"][glass["materials"][0]]
    assert m["surface"] == "BSDF_PRINCIPLED" and "TEX_VORONOI" in m["node_types"]
    p = m["inputs"]
    assert p["Transmission Weight"]["value"] == 1.0 and p["Roughness"]["value"] < 0.1
    assert p["Alpha"]["linked"] and p["Normal"]["linked"] and p["Metallic"]["linked"]
    return glass


def test_broken_pane_is_alpha_cut_thin_glass(probe):
    pane = probe["builds"][4]
    glass = _thin_cracked_glass(pane, "Broken Pane Glass")
    z = np.array(glass["matrix"])[2, 3]
    frame = np.array(pane["objects"]["Broken Pane Frame"]["matrix"])
    assert np.allclose(frame, glass["matrix"]) and z > 0.76  # stands on the table top


def test_window_pane_stands_on_the_floor_across_the_cameras_line_of_sight(probe):
    """The window's frame reaches the floor, its glass lies between the camera's arc and the table (front edge y =
    -0.45 m), and on every frame the camera's optical axis passes through the glass: the view is seen through it."""
    win = probe["builds"][5]
    glass = _thin_cracked_glass(win, "Window Pane Glass")
    frame = win["objects"]["Window Pane Frame"]
    (gx0, gy0, gz0), (gx1, gy1, gz1) = glass["bounds"]
    (fx0, fy0, fz0), (fx1, fy1, fz1) = frame["bounds"]
    assert np.allclose(frame["matrix"], glass["matrix"]) and abs(fz0) < 1e-4      # the feet on the floor
    assert abs(fz1 - (gz1 + 0.04)) < 1e-4 and fx0 < gx0 and fx1 > gx1            # the top bar over the glass
    assert fy0 > -1.0 and fy1 < -0.37 - 0.025                                    # short of the table legs
    y = (gy0 + gy1) / 2
    cams = np.array(win["animated_matrices"][win["camera"]])  # (frames, 4, 4), the camera looks along its -Z
    eye, look = cams[:, :3, 3], -cams[:, :3, 2]
    assert np.all(eye[:, 1] < gy0 - 0.3) and gy1 < -0.45
    t = (y - eye[:, 1]) / look[:, 1]
    hit = eye + t[:, None] * look
    assert np.all(t > 0)
    assert np.all((hit[:, 0] > gx0) & (hit[:, 0] < gx1) & (hit[:, 2] > gz0) & (hit[:, 2] < gz1))


def test_world_is_a_bundled_studiolight(scene):
    w = scene["world"]
    assert w["background_color_from"] == "TEX_ENVIRONMENT"
    assert Path(w["image"]).parent == Path(w["studiolights"])
    assert Path(w["image"]).suffix == ".exr" and w["strength"] > 0


def _keyed_frames(fcurves, path):
    return [fc[2] for fc in fcurves if fc[0] == path]


@pytest.mark.parametrize("build, start, end", [(0, 1, 48), (3, 3, 20)])
def test_camera_and_moving_object_keyed_from_start_minus_one(probe, build, start, end):
    sc = probe["builds"][build]
    expect = [float(f) for f in range(start - 1, end + 1)]
    cam = sc["objects"][sc["camera"]]
    assert cam["type"] == "CAMERA" and cam["camera"]["type"] == "PERSP"
    for path in ("location", "rotation_euler"):
        keys = _keyed_frames(cam["fcurves"], path)
        assert len(keys) == 3 and all(k == expect for k in keys)
    movers = [n for n, o in sc["objects"].items() if o["type"] == "MESH" and o["fcurves"]]
    assert movers
    for n in movers:
        assert all(k == expect for k in _keyed_frames(sc["objects"][n]["fcurves"], "location"))
        assert {i for fc in sc["objects"][n]["fcurves"] for i in fc[3]} == {"LINEAR"}
        m = np.array(sc["animated_matrices"][n])
        assert np.linalg.norm(m[1, :3, 3] - m[0, :3, 3]) > 1e-4  # motion into the first frame is real


def test_camera_motion_is_smooth_and_looks_at_the_table(scene):
    m = np.array(scene["animated_matrices"]["Camera"])  # (49, 4, 4)
    pos = m[:, :3, 3]
    step = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    acc = np.linalg.norm(np.diff(pos, 2, axis=0), axis=1)
    assert step.min() > 1e-3                     # always moving
    assert step.max() < 0.1                      # < 2.4 m/s at 24 fps
    assert acc.max() < 0.1 * step.mean()         # no kinks
    fwd = -m[:, :3, 2]                           # camera looks along its -Z
    fwd_turn = np.degrees(np.arccos(np.clip(np.sum(fwd[1:] * fwd[:-1], axis=1), -1, 1)))
    assert fwd_turn.max() < 2.0
    table = np.array(scene["objects"]["Table"]["matrix"])[:3, 3] + np.array([0, 0, 0.76])
    to_table = table - pos
    to_table /= np.linalg.norm(to_table, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.sum(fwd * to_table, axis=1))).max() < 15.0


def test_rolling_ball_rolls_without_slipping(scene):
    m = np.array(scene["animated_matrices"]["Rolling Ball"])
    pos = m[:, :3, 3]
    radius = 0.045
    # Rotation about +Y by angle = distance / radius: compare the rotation between frames with the travel.
    for a, b, pa, pb in zip(m[:-1], m[1:], pos[:-1], pos[1:]):
        r = b[:3, :3] @ a[:3, :3].T
        angle = np.arctan2(r[0, 2], r[0, 0])
        assert angle == pytest.approx((pb[0] - pa[0]) / radius, abs=1e-4)
    assert np.ptp(pos[:, 1]) < 1e-6 and np.ptp(pos[:, 2]) < 1e-6
    table_top = np.array(scene["objects"]["Table"]["matrix"])[2, 3] + 0.76
    assert pos[0, 2] == pytest.approx(table_top + radius, abs=1e-5)


def test_tiny_cycles_render_sees_the_scene(tmp_path):
    from gbuffer_export.exr import read_exr_channels
    out = tmp_path / "tiny.exr"
    info = run_probe("default_render", {"out": str(out), "frame": 1})
    ch = read_exr_channels(out)
    layer = info["view_layer"]
    depth = ch[f"{layer}.Depth.Z"]
    rgb = np.stack([ch[f"{layer}.Combined.{c}"] for c in "RGB"], axis=-1)
    assert depth.shape == (36, 64)
    assert np.isfinite(rgb).all() and rgb.min() >= 0
    background = depth >= 1e9
    # The camera looks at the table: sky only near the top, geometry in most pixels, a range of depths.
    assert background.mean() < 0.35
    assert not background[-12:].any()
    fg = depth[~background]
    assert 0.5 < np.median(fg) < 6.0 and np.ptp(fg) > 1.0
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
    assert lum.std() > 0.05 and 0.05 < np.median(lum) < 5.0
