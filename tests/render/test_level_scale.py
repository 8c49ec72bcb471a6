"""A level's unit from its geometry (gbuffer_export/blender/level_scale.py) on synthetic levels built with trimesh
(no Blender): interiors, a town and a jungle, each in metres, centimetres (x100) and inches (x39.37), and with
spawn points in Cube units (0.12 m) and kilometres too; the engine line of an OBJ; the unit checked on the planned
views (level_cameras.plan_level_camera)."""
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


# ------------------------------------------------------------------------------------------------ issue 55 item 2

#: scene units per metre of every unit the synthetic levels are built in (issue 55: metres, centimetres, inches,
#: Cube units of about 0.12 m, kilometres)
ALL_UNITS = {**PER_METRE, "cube": 1 / 0.12, "km": 1e-3}


def _spawns(g: LevelGeometry, per_metre: float, n: int = 6) -> np.ndarray:
    """``n`` spawn points (player starts) 1.6 m over the first surface below seeded (x, y) points of the level."""
    rng = np.random.default_rng(1)
    lo, hi = g.content_bounds()
    xy = rng.uniform(lo[:2], hi[:2], (n, 2))
    top = g.bounds()[1][2] + 1.0
    d, _ = g.first_hits(np.c_[xy, np.full(n, top)], np.tile([0.0, 0.0, -1.0], (n, 1)))
    return np.c_[xy, top - d + 1.6 * per_metre]


@pytest.mark.parametrize("unit", list(ALL_UNITS))
@pytest.mark.parametrize("level", list(LEVELS))
def test_with_spawn_points_every_level_is_read_within_a_factor_1_5_in_every_unit(level, unit):
    """Spawn points (a game's player starts, where the file has them) stand an eye height over the floor: with
    them every synthetic level in every unit is read within a factor 1.5 of its unit (issue 55's acceptance),
    including those the geometry alone cannot tell apart (a town in inches or in Cube units)."""
    g = _geometry(LEVELS[level](), ALL_UNITS[unit])
    r = level_scale.detect_unit_scale(g, spawns=_spawns(g, ALL_UNITS[unit]))
    ratio = r["metres_per_unit"] * ALL_UNITS[unit]
    assert 1 / 1.5 <= ratio <= 1.5, r
    assert "spawn" in r["used"] and r["cues"]["spawns"] == 6 and r["cues"]["spawn_units"] == pytest.approx(
        1.6 * ALL_UNITS[unit], rel=1e-6)


@pytest.mark.parametrize("unit", ["cube", "km"])
def test_an_interior_in_cube_units_or_kilometres_is_read_from_its_geometry(unit):
    r = level_scale.detect_unit_scale(_geometry(_apartment(), ALL_UNITS[unit]))
    assert r["unit"] == unit and "headroom" in r["used"], r


def _hangar_obj(tmp_path, first_line: str):
    """An OBJ whose only geometry is a Cube-style map's: halls with 64-unit (7.7 m) ceilings. Its first line is
    ``first_line``."""
    path = tmp_path / "map.obj"
    path.write_text(f"{first_line}\n\nmtllib map.mtl\n\nv 540 25 0\n")
    parts = []
    for i in range(4):
        parts.append(_box((320.0, 256.0, 64.0), (i * 330.0, 0, 32.0), inward=True))
        parts.append(_box((32.0, 32.0, 16.0), (i * 330.0 - 80, 40, 8.0)))
    return path, _geometry(parts, 1.0)


def test_an_obj_naming_the_cube_engine_is_read_in_cube_units(tmp_path):
    """Cube 2's /writeobj opens the file with '# obj file of Cube 2 level' (the shared steelribs map): the file
    declares its engine's unit (0.12 m), which its halls alone (64 units high: 1.6 m in inches) would not say."""
    path, g = _hangar_obj(tmp_path, "# obj file of Cube 2 level")
    assert level_scale.engine_unit(path)["unit"] == "cube"
    rec = level_scale.resolve_unit_scale(g, "auto", path)
    assert rec["unit"] == "cube" and g.metres_per_unit == 0.12 and rec["engine"]["engine_line"].startswith("# obj")
    other, g2 = _hangar_obj(tmp_path / "x" if (tmp_path / "x").mkdir() is None else tmp_path, "# exported")
    assert level_scale.engine_unit(other) is None
    assert level_scale.resolve_unit_scale(g2, "auto", other)["unit"] == "in"
    assert level_scale.engine_unit(tmp_path / "absent.obj") is None


def test_a_unit_whose_walk_sees_hundreds_of_metres_indoors_gives_way_to_the_next(monkeypatch):
    """The apartment in centimetres, with the detection forced to read it in metres: the walk's eye stands 1.6 cm
    over the floor and its views reach hundreds of 'metres' inside an interior, so the view check takes the next
    unit by score (centimetres) and records why."""
    from gbuffer_export.blender import level_cameras
    hfov, vfov = math.atan(0.75), math.atan(0.75 * 9 / 16)
    clip = level_cameras.ClipPlan("walk", 9, 24.0, 0, (hfov, vfov))
    _, right = level_cameras.plan_level_camera(_geometry(_apartment(), 100.0), clip, rules=PathRules(tries=20))
    assert right["view_check"]["rejected"] == [] and right["unit"] == "cm"  # detected right: nothing rejected
    g = _geometry(_apartment(), 100.0)
    real = level_scale.detect_unit_scale

    def wrong(geom, declared=None, spawns=None):
        r = real(geom, declared, spawns)
        return {**r, "unit": "m", "metres_per_unit": 1.0, "scores": {**r["scores"], "m": 99.0}}
    monkeypatch.setattr(level_scale, "detect_unit_scale", wrong)
    path, unit = level_cameras.plan_level_camera(g, clip, rules=PathRules(tries=20))
    check = unit["view_check"]
    assert check["rejected"][0]["unit"] == "m" and "inside an interior" in check["rejected"][0]["why"]
    assert unit["unit"] == "cm" and unit["metres_per_unit"] == 0.01 and unit["chosen_by"] == "view check"
    assert g.metres_per_unit == 0.01 and check["plausible"] and check["far_depth_m"] < 40
    assert path.report["metres_per_unit"] == 0.01
