"""A level's unit from its geometry (gbuffer_export/blender/level_scale.py) on synthetic levels built with trimesh
(no Blender): interiors, a town and a jungle, each in metres, centimetres (x100) and inches (x39.37)."""
from __future__ import annotations

import math

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")

from gbuffer_export.blender import level_scale  # noqa: E402
from gbuffer_export.blender.level_cameras import PathRules, plan_level_path  # noqa: E402
from gbuffer_export.blender.level_geometry import LevelGeometry  # noqa: E402
from gbuffer_export.config import UNIT_NAMES, RenderConfig  # noqa: E402
from gbuffer_export.typed_table import ConfigError  # noqa: E402

PER_METRE = {"m": 1.0, "cm": 100.0, "in": 1 / 0.0254}  # scene units per metre (x1, x100, x39.37)


def _box(extents, centre, inward=False):
    b = trimesh.creation.box(extents=extents)
    b.apply_translation(centre)
    if inward:
        b.invert()
    return b


def _geometry(parts, per_metre: float) -> LevelGeometry:
    """The parts (metres) as one level in units of 1/``per_metre`` m; the file declares nothing (1 m per unit),
    as a glTF or OBJ exported from an engine in centimetres does."""
    m = trimesh.util.concatenate(parts)
    owner = np.concatenate([np.full(len(p.faces), i) for i, p in enumerate(parts)])
    return LevelGeometry(np.asarray(m.vertices) * per_metre, np.asarray(m.faces), 1.0, owner=owner)


def _apartment():
    """Two storeys of rooms (2.7 m clear height, 0.3 m slabs) with tables and shelves."""
    parts = []
    for storey in range(2):
        z0 = storey * 3.0
        for i in range(3):
            parts.append(_box((5.0, 4.0, 2.7), (i * 5.3, 0, z0 + 1.35), inward=True))
            parts.append(_box((1.2, 0.8, 0.75), (i * 5.3 - 1.0, 0.5, z0 + 0.375)))
            parts.append(_box((0.4, 1.8, 2.0), (i * 5.3 + 2.2, 0.0, z0 + 1.0)))
    return parts


def _town():
    """A 160 m square of ground with 30 houses (3-12 m tall) and a few flat roofs over passages: no interiors."""
    rng = np.random.default_rng(3)
    parts = [_box((160.0, 160.0, 0.2), (0, 0, -0.1))]
    for _ in range(30):
        w, d, h = rng.uniform(6, 14), rng.uniform(6, 14), rng.uniform(3, 12)
        parts.append(_box((w, d, h), (*rng.uniform(-70, 70, 2), h / 2)))
    return parts


def _jungle():
    """A bumpy 120 m terrain with 60 trees: trunks 12-25 m tall under canopies (the issue's jungle, whose walk saw
    86-100 'metres' of view depth: a level in centimetres read as metres)."""
    rng = np.random.default_rng(5)
    n = 40
    xs = np.linspace(-60, 60, n)
    X, Y = np.meshgrid(xs, xs)
    Z = 0.8 * np.sin(X / 9.0) * np.cos(Y / 7.0)
    v = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            f += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    parts = [trimesh.Trimesh(v, np.array(f), process=False)]
    for _ in range(60):
        h, (x, y) = rng.uniform(12, 25), rng.uniform(-55, 55, 2)
        trunk = trimesh.creation.cylinder(radius=0.4, height=h, sections=8)
        trunk.apply_translation([x, y, h / 2])
        crown = trimesh.creation.icosphere(subdivisions=1, radius=rng.uniform(3, 6))
        crown.apply_translation([x, y, h])
        parts += [trunk, crown]
    return parts


def _open_world():
    """A 4 km terrain with 400 m hills, as one mesh, and 200 props (rocks, trees, huts: 1-15 m): about the size in
    units of the jungle in centimetres, told apart by its props."""
    rng = np.random.default_rng(9)
    n = 48
    xs = np.linspace(-2000, 2000, n)
    X, Y = np.meshgrid(xs, xs)
    Z = 200.0 * (1 + np.sin(X / 500.0) * np.cos(Y / 650.0))
    v = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    f = [[i * n + j, i * n + j + 1, (i + 1) * n + j + 1] for i in range(n - 1) for j in range(n - 1)]
    f += [[i * n + j, (i + 1) * n + j + 1, (i + 1) * n + j] for i in range(n - 1) for j in range(n - 1)]
    parts = [trimesh.Trimesh(v, np.array(f), process=False)]
    for _ in range(200):
        x, y = rng.uniform(-1800, 1800, 2)
        z = 200.0 * (1 + math.sin(x / 500.0) * math.cos(y / 650.0))
        size = rng.uniform(1.0, 15.0)
        parts.append(_box((size, size * 0.8, size), (x, y, z + size / 2)))
    return parts


LEVELS = {"apartment": _apartment, "town": _town, "jungle": _jungle, "open_world": _open_world}


@pytest.mark.parametrize("unit", list(PER_METRE))
@pytest.mark.parametrize("level", list(LEVELS))
def test_the_unit_is_detected_from_the_geometry(level, unit):
    g = _geometry(LEVELS[level](), PER_METRE[unit])
    r = level_scale.detect_unit_scale(g)
    expect = unit
    if level != "apartment" and unit == "in":
        # Without ceilings only the level's size speaks: inches and centimetres (a factor 2.54) are not told apart
        # (docs/rendering.md, "A level's unit"); either keeps the eye within a factor 2.54 of 1.6 m.
        assert r["unit"] in ("in", "cm"), r
        return
    assert r["unit"] == expect, r
    assert r["metres_per_unit"] == pytest.approx(1 / PER_METRE[unit], rel=0.02)
    assert "headroom" in r["used"] or level != "apartment", r


def test_headroom_is_the_free_height_under_the_ceilings():
    cues = level_scale.measure_cues(_geometry(_apartment(), 100.0))
    assert cues["headroom_units"] == pytest.approx(270.0, abs=1.0)  # 2.7 m clear height, in centimetres
    assert cues["covered_fraction"] > 0.5


def test_a_declared_unit_is_kept_when_the_geometry_agrees():
    """A .blend whose unit scale says centimetres (scale_length 0.01) keeps it; so does a metre level."""
    parts = _apartment()
    m = trimesh.util.concatenate(parts)
    g = LevelGeometry(np.asarray(m.vertices) * 100.0, np.asarray(m.faces), 0.01)
    assert level_scale.detect_unit_scale(g)["metres_per_unit"] == 0.01
    assert level_scale.detect_unit_scale(_geometry(parts, 1.0))["metres_per_unit"] == 1.0


def test_a_skybox_is_not_a_ceiling():
    """A town under a 1 km sky dome (normals inwards) stays in metres: the dome encloses the level, so the
    floors under it count as open sky, not as a 1 km headroom."""
    sky = trimesh.creation.icosphere(subdivisions=3, radius=1000.0)
    sky.invert()
    r = level_scale.detect_unit_scale(_geometry(_town() + [sky], 1.0))
    assert r["unit"] == "m" and r["cues"]["covered_fraction"] < 0.1, r


def test_walk_speed_and_eye_height_are_metres_of_the_depicted_world():
    """The apartment in centimetres: after detection the walk's eye stands 160 units (1.6 m) above the floor and
    moves 140 units a second, as in the metre apartment."""
    g = _geometry(_apartment(), 100.0)
    rec = level_scale.resolve_unit_scale(g, "auto")
    assert rec["requested"] == "auto" and rec["declared"] == 1.0 and g.metres_per_unit == 0.01
    hfov, vfov = math.atan(0.75), math.atan(0.75 * 9 / 16)
    p = plan_level_path(g, "walk", 13, 24.0, 0, (hfov, vfov), rules=PathRules(tries=30))
    step = np.linalg.norm(np.diff(p.eyes[:, :2], axis=0), axis=1)
    assert np.median(step) * 24.0 == pytest.approx(140.0, rel=0.01)
    floors = np.array([0.0, 300.0])
    above = p.eyes[:, 2][:, None] - floors[None]
    assert np.allclose(np.min(np.where(above > 0, above, np.inf), axis=1), 160.0, atol=0.5)
    assert p.report["metres_per_unit"] == 0.01 and p.report["speed_mps"] == pytest.approx(1.4, rel=0.01)


def test_a_given_unit_scale_is_taken_as_it_is():
    g = _geometry(_apartment(), 100.0)
    rec = level_scale.resolve_unit_scale(g, 0.0254)
    assert rec == {"requested": 0.0254, "metres_per_unit": 0.0254, "declared": 1.0} and g.metres_per_unit == 0.0254


@pytest.mark.parametrize("value, expect", [("auto", "auto"), (0.01, 0.01), (1, 1.0), ("0.0254", 0.0254),
                                           ("cm", 0.01), ("IN", 0.0254), ("ft", 0.3048)])
def test_unit_scale_key_accepts_auto_numbers_and_unit_names(value, expect, tmp_path):
    assert RenderConfig(output=tmp_path, unit_scale=value).unit_scale == expect
    assert set(UNIT_NAMES) == {"m", "cm", "mm", "in", "ft"}


@pytest.mark.parametrize("value, words", [(0, "must be a number > 0"), (-1.0, "must be a number > 0"),
                                          ("yard", "expected auto, metres per scene unit"),
                                          (float("inf"), "finite"), (True, "expected a number")])
def test_unit_scale_key_refuses_bad_values_in_one_line(value, words, tmp_path):
    with pytest.raises(ConfigError) as e:
        RenderConfig(output=tmp_path, unit_scale=value)
    msg = str(e.value)
    assert msg.startswith("unit_scale") and words in msg and "\n" not in msg and e.value.key == "unit_scale"
