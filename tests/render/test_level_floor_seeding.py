"""Cameras that find a path in any level (issue 55 item 1), on synthetic levels built with trimesh (no Blender):
walk and fly starts seeded where the level has floor, a clip whose region cell has no floor moved to one of its
split that has (recorded), and a fix named for a clip that has no path."""
from __future__ import annotations

import math

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")

from gbuffer_export.blender.level_cameras import (NO_FLOOR, ClipPlan, PathError, PathRules, Region,  # noqa: E402
                                                  _start_points, clip_regions, floor_samples, plan_clip_path,
                                                  suggest_fix)
from gbuffer_export.blender.level_geometry import LevelGeometry  # noqa: E402

HFOV, VFOV = math.atan(0.75), math.atan(0.75 * 9 / 16)
FPS = 24.0


def _slab(x0, x1, y0, y1, z=0.0, t=0.2):
    b = trimesh.creation.box(extents=(x1 - x0, y1 - y0, t))
    b.apply_translation([(x0 + x1) / 2, (y0 + y1) / 2, z - t / 2])
    return b


def _hall() -> LevelGeometry:
    """A 40 x 40 m pit open to the sky, its walls 30 m high and 20 m deep, with no bottom: floor covers the half
    x > 1 (cells (1, 0) and (1, 1) of a 2 x 2 grid), a 3 x 3 m platform is all the floor of cell (0, 0) (2 % of
    it) and cell (0, 1) has none. Pillars and crates give the views content."""
    hall = trimesh.creation.box(extents=(40.0, 40.0, 50.0))
    hall.apply_translation([0, 0, 5.0])
    hall.invert()
    z = hall.vertices[hall.faces][:, :, 2]
    hall.update_faces(~(np.all(np.isclose(z, -20.0), axis=1) | np.all(np.isclose(z, 30.0), axis=1)))  # open
    for _ in range(4):  # many wall triangles: the content box is the hall's, its 2 x 2 grid splits at x = y = 0
        hall = hall.subdivide()
    parts = [hall, _slab(1.0, 20.0, -20.0, 20.0), _slab(-16.5, -13.5, -16.5, -13.5)]
    for x in (4.0, 16.0):  # on the floored half only: a pillar's top is floor too
        for y in (-16.0, -4.0, 4.0, 16.0):
            p = trimesh.creation.box(extents=(0.6, 0.6, 50.0))
            p.apply_translation([x, y, 5.0])
            parts.append(p)
    for k in range(12):
        c = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
        c.apply_translation([3.0 + 1.4 * k, -10.0 + 1.7 * (k % 5), 0.5])
        parts.append(c)
    m = trimesh.util.concatenate(parts)
    owner = np.concatenate([np.full(len(p.faces), i) for i, p in enumerate(parts)])
    return LevelGeometry(np.asarray(m.vertices), np.asarray(m.faces), owner=owner)


@pytest.fixture(scope="module")
def hall():
    return _hall()


def _cell(g: LevelGeometry, cells) -> Region:
    lo, hi = g.content_bounds()
    return Region((float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])), 2, 2, tuple(cells))


def test_starts_are_seeded_on_the_floor_of_a_mostly_empty_cell(hall):
    """Cell (0, 0) is 2 % floor: every start stands 1.6 m over the platform, and there are many of the 48 drawn
    (48 points over the cell's box would put about one on it; the platform's underside, floor seen from below,
    gives none)."""
    region = _cell(hall, [(0, 0)])
    rng = np.random.default_rng(0)
    starts = _start_points(hall, region, rng, "walk", PathRules())
    assert len(starts) >= 16
    eyes = np.array([s[0] for s in starts])
    assert np.all((eyes[:, 0] >= -16.5) & (eyes[:, 0] <= -13.5) & (eyes[:, 1] >= -16.5) & (eyes[:, 1] <= -13.5))
    assert np.allclose(eyes[:, 2], 1.6)
    fly = _start_points(hall, region, rng, "fly", PathRules())
    assert len(fly) >= 40 and all(1.0 <= s[0][2] for s in fly)


def test_a_walk_and_a_fly_are_planned_in_the_mostly_empty_cell(hall):
    region = _cell(hall, [(0, 0)])
    for kind in ("walk", "fly"):
        p = plan_clip_path(hall, kind, 9, FPS, 3, (HFOV, VFOV), region, PathRules(tries=8))
        assert region.contains(p.eyes[:, :2]).all()
        assert "region_move" not in p.report


def test_a_cell_without_floor_is_refused_with_its_reason(hall):
    region = _cell(hall, [(0, 1)])
    assert len(floor_samples(hall, region)) == 0
    with pytest.raises(PathError, match=NO_FLOOR) as e:
        plan_clip_path(hall, "walk", 9, FPS, 0, (HFOV, VFOV), region, PathRules(tries=5))
    assert e.value.most_often == NO_FLOOR and "\n" not in str(e.value)


def test_a_clip_whose_cell_has_no_floor_moves_to_a_floored_cell_of_its_split(hall):
    spec = {"grid": [2, 2], "cell": [0, 1], "split": "train", "cells": {"test": [[1, 0]], "val": [],
                                                                          "train": [[0, 1], [0, 0], [1, 1]]}}
    regions = clip_regions(hall, spec)
    first, move = regions[0]
    assert first.cells == ((0, 0),)  # the nearest floored train cell (1, 1 is as near; ties go to the lower)
    assert move == {"from": [0, 1], "to": [[0, 0]], "reason": NO_FLOOR + " of its cell"}
    assert regions[1][0].cells == ((0, 0), (1, 1))  # never the test cell (1, 0)
    p = plan_clip_path(hall, "walk", 9, FPS, 2, (HFOV, VFOV), spec, PathRules(tries=8))
    assert p.report["region_move"]["from"] == [0, 1]
    cells = {tuple(c) for c in _cell(hall, [(0, 0)]).cell_of(p.eyes[:, :2])}
    assert cells <= {(0, 0), (1, 1)} and p.report["region"]["cells"] in ([[0, 0]], [[0, 0], [1, 1]])
    own = clip_regions(hall, {**spec, "cell": [1, 1]})
    assert own[0] == (_cell(hall, [(1, 1)]), None)


def test_a_clip_with_no_floor_in_its_split_is_told_to_use_fewer_regions(hall):
    spec = {"grid": [2, 2], "cell": [0, 1], "split": "test", "cells": {"test": [[0, 1]], "val": [],
                                                                         "train": [[0, 0], [1, 0], [1, 1]]}}
    with pytest.raises(PathError, match=NO_FLOOR):
        plan_clip_path(hall, "walk", 9, FPS, 0, (HFOV, VFOV), spec, PathRules(tries=4))
    fix = suggest_fix(hall, ClipPlan("walk", 9, FPS, 0, (HFOV, VFOV), spec), PathRules(tries=8))
    assert fix.startswith('use fewer regions (regions = "1x1")'), fix


def test_a_single_object_is_told_to_use_orbit():
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    g = LevelGeometry(ball.vertices, ball.faces)
    g.__dict__.pop("_floor_samples", None)
    bottom_up = np.abs(g.normals[:, 2]) > math.cos(math.radians(45.0))
    assert bottom_up.any()  # a sphere has near-horizontal faces at its poles: they are floor samples...
    fix = suggest_fix(g, ClipPlan("walk", 9, FPS, 0, (HFOV, VFOV), None), PathRules(tries=3))
    assert "orbit" in fix  # ...but nothing plans on them, and the advice for one object is orbit


def test_a_long_walk_turns_before_its_cells_border():
    """A 3.5 s walk (85 frames, 4.8 m) in 11 x 6 m cells of a room: a walker that turns at most 45 degrees a second
    needs 3.6 m for a U-turn, so it must turn before the border, which steers as a wall does (the issue's city:
    'walked into a dead end' in its 2 x 2 cells)."""
    from tests.render.test_level_cameras import _room
    g = _room(size=(24.0, 18.0, 3.0))
    lo, hi = g.content_bounds()
    for cell in [(1, 0), (1, 1)]:
        r = Region((float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])), 2, 2, (cell,))
        p = plan_clip_path(g, "walk", 85, FPS, 3, (HFOV, VFOV), r, PathRules(tries=20))
        assert r.contains(p.eyes[:, :2]).all()
