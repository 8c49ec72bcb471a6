"""The built-in generator's families (gbuffer_export/blender/default_scene/families.py): each adds only its own
objects (or changes only its own light or camera), draws from its own stream, keeps its parameters in the stated
ranges, and renders."""
from __future__ import annotations

import json

import numpy as np
import pytest

from gbuffer_export.dataset.families import BUILTIN_FAMILIES
from tests.conftest import requires_bpy
from tests.render.test_scene_default import run_probe

pytestmark = [pytest.mark.bpy, requires_bpy]
NEW = [n for n in BUILTIN_FAMILIES if n not in ("broken_pane", "window_pane")]
MIXED = ["mat_noise", "railing", "neon", "cam_pan"]


@pytest.fixture(scope="module")
def probe():
    builds = [{"seed": 1, "frames": [1, 12], "resolution": [64, 36], "props": p} for p in [[], *[[n] for n in NEW],
                                                                                              MIXED]]
    out = run_probe("default", {"builds": builds}, timeout=600)
    out["plain"], out["mixed"] = out["builds"][0], out["builds"][-1]
    out["alone"] = dict(zip(NEW, out["builds"][1:-1]))
    return out


def _tagged(build, family):
    return {n: ob for n, ob in build["objects"].items() if ob["props"].get("blendsr_family") == family}


def _camera(build):
    cams = np.array(build["animated_matrices"][build["camera"]])   # (frames, 4, 4): start-1 .. end
    return cams[:, :3, 3], -cams[:, :3, 2]


@pytest.mark.parametrize("family", NEW)
def test_a_family_adds_or_changes_only_its_own(probe, family):
    plain, b = probe["plain"], probe["alone"][family]
    kind = BUILTIN_FAMILIES[family]
    added = set(b["objects"]) - set(plain["objects"])
    assert set(plain["objects"]) <= set(b["objects"])
    assert added == {n for n in _tagged(b, family) if n not in plain["objects"]}
    assert (len(added) > 0) == (family not in ("strong_sun", "cam_pan", "cam_strafe", "cam_turn", "cam_cut"))
    changed = {n for n, ob in plain["objects"].items() if not np.allclose(ob["matrix"], b["objects"][n]["matrix"])}
    for n, m in plain["animated_matrices"].items():
        if not np.allclose(m, b["animated_matrices"][n]):
            changed.add(n)
    assert changed == ({plain["camera"]} if kind == "camera" else set())
    for name, m in plain["materials"].items():
        assert b["materials"][name] == m, name
    lit = {n for n, ob in plain["objects"].items() if ob["props"] != b["objects"][n]["props"]}
    assert lit <= ({"Sun"} if family in ("strong_sun", "night") else {plain["camera"]} if kind == "camera" else set())
    assert (b["world"]["strength"] < 0.06 * plain["world"]["strength"]) == (family == "night")


def test_each_family_draws_from_its_own_stream(probe):
    """With other families added, a family's objects, materials and camera are those it has alone."""
    mixed = probe["mixed"]
    for family in MIXED:
        alone = probe["alone"][family]
        for name, ob in _tagged(alone, family).items():
            assert mixed["objects"][name]["matrix"] == ob["matrix"] and mixed["objects"][name]["props"] == ob["props"]
            assert mixed["objects"][name].get("bounds") == ob.get("bounds"), name
            for m in ob["materials"]:
                assert mixed["materials"][m] == alone["materials"][m], m
    assert np.allclose(mixed["animated_matrices"][mixed["camera"]],
                       probe["alone"]["cam_pan"]["animated_matrices"][mixed["camera"]])


def test_parameters_are_within_their_stated_ranges(probe):
    ranges = probe["family_ranges"]
    for family in NEW:
        tagged = _tagged(probe["alone"][family], family)
        assert tagged, family
        for name, ob in tagged.items():
            params = json.loads(ob["props"]["family_params"])
            assert set(params) <= set(ranges[family]) and params, (family, name)
            for k, v in params.items():
                lo, hi = ranges[family][k]
                assert lo <= v <= hi, (family, k, v)


def test_material_families_span_the_principled_classes_over_their_pattern(probe):
    tex = {"noise": "TEX_NOISE", "voronoi": "TEX_VORONOI", "wave": "TEX_WAVE", "brick": "TEX_BRICK",
           "layered": "TEX_VORONOI"}
    classes = set()
    for pattern, node in tex.items():
        b = probe["alone"][f"mat_{pattern}"]
        for name, ob in _tagged(b, f"mat_{pattern}").items():
            m = b["materials"][ob["materials"][0]]
            assert node in m["node_types"] and "BUMP" in m["node_types"] and m["inputs"]["Base Color"]["linked"]
            cls = ob["props"].get("principled_class")
            classes.add(cls)
            p = {k: v["value"] for k, v in m["inputs"].items()}
            assert {"metal": p["Metallic"] == 1.0, "anisotropy": p["Anisotropic"] >= 0.5,
                    "transmission": p["Transmission Weight"] == 1.0, "coat": p["Coat Weight"] >= 0.6,
                    "emission": 2.0 <= p["Emission Strength"] <= 15.0, None: True}.get(cls, True), (name, cls)
            lo = ob["bounds"][0][2]
            assert lo > -1e-4 and (cls is None or lo > 0.79), name   # swatches stand on their plinth
    assert len(classes - {None}) >= 3


def test_thin_structures_are_thin(probe):
    rail = probe["alone"]["railing"]["objects"]["Railing"]
    (x0, y0, z0), (x1, y1, z1) = rail["bounds"]
    assert 1.15 + 0.04 - 1e-4 <= z1 <= 1.25 + 0.04 + 1e-4 and abs(z0) < 1e-4 and -1.1 < y0 and y1 < -0.9
    wires = probe["alone"]["wires"]["objects"]["Wires"]
    assert wires["bounds"][0][2] > 0.7 and wires["bounds"][1][2] < 1.51
    cards = probe["alone"]["foliage_cards"]
    leaf = cards["materials"][cards["objects"]["Foliage Cards"]["materials"][0]]
    assert leaf["inputs"]["Alpha"]["linked"] and "TEX_VORONOI" in leaf["node_types"]


def test_camera_families_move_as_games_do(probe):
    def turn_deg(f):
        return np.degrees(np.arccos(np.clip(np.sum(f[1:] * f[:-1], axis=1), -1, 1)))
    eye, fwd = _camera(probe["alone"]["cam_pan"])
    assert np.ptp(eye, axis=0).max() < 1e-6 and 1.0 < turn_deg(fwd).max() <= 4.01
    eye, fwd = _camera(probe["alone"]["cam_strafe"])
    step = np.linalg.norm(np.diff(eye, axis=0), axis=1)
    assert np.all((step > 0.019) & (step < 0.051)) and np.ptp(turn_deg(fwd)) < 1e-3
    eye, fwd = _camera(probe["alone"]["cam_turn"])
    total = np.degrees(np.arccos(np.clip(fwd[0] @ fwd[-1], -1, 1)))
    assert 55 < total < 125 and turn_deg(fwd).max() > 10
    eye, _ = _camera(probe["alone"]["cam_cut"])
    jumps = np.flatnonzero(np.linalg.norm(np.diff(eye, axis=0), axis=1) > 0.3)
    assert len(jumps) == 1 and 1 <= jumps[0] <= 7     # one cut, between frames start .. start+6 (index 0: start-1)


def test_every_family_renders(tmp_path):
    from gbuffer_export.exr import read_exr_channels
    out = tmp_path / "fam.exr"
    props = [n for n in NEW if not n.startswith("cam_")] + ["cam_cut"]
    info = run_probe("default_render", {"out": str(out), "frame": 1, "size": [32, 18], "props": props})
    ch = read_exr_channels(out)
    layer = info["view_layer"]
    rgb = np.stack([ch[f"{layer}.Combined.{c}"] for c in "RGB"], axis=-1)
    depth = ch[f"{layer}.Depth.Z"]
    assert rgb.shape == (18, 32, 3) and np.isfinite(rgb).all() and rgb.min() >= 0 and rgb.max() > 0
    assert (depth < 1e9).mean() > 0.6
