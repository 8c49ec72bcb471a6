"""Level camera paths (gbuffer_export/blender/level_cameras.py) on synthetic rooms built with trimesh: no Blender.

Every rule is measured independently of the planner: distances with trimesh's exact closest-point query, floor
heights from the room's known geometry, view content by casting our own rays."""
from __future__ import annotations

import math

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")

from gbuffer_export.blender.level_cameras import (PathError, PathRules, Region, plan_level_path,  # noqa: E402
                                                  view_dirs)
from gbuffer_export.blender.level_geometry import LevelGeometry  # noqa: E402

HFOV, VFOV = math.atan(0.75), math.atan(0.75 * 9 / 16)
FPS = 24.0


def _room(size=(12.0, 9.0, 3.0), unit: float = 1.0, ground: float = 0.0, roof: bool = True) -> LevelGeometry:
    """A closed room (faces looking inwards) with a pillar, a table and a low step, in scene units of ``unit``
    metres; ``ground`` > 0 adds a flat ground plane of that side under everything; ``roof`` False leaves it open
    to the sky (a courtyard)."""
    parts = []
    room = trimesh.creation.box(extents=size)
    room.apply_translation([0, 0, size[2] / 2])
    room.invert()  # walls seen from inside: their normals point into the room
    if not roof:
        room.update_faces(~np.all(np.isclose(room.vertices[room.faces][:, :, 2], size[2]), axis=1))
    parts.append(room)
    pillar = trimesh.creation.box(extents=(0.6, 0.6, size[2]))
    pillar.apply_translation([1.5, 1.0, size[2] / 2])
    table = trimesh.creation.box(extents=(1.2, 0.8, 0.8))
    table.apply_translation([-3.0, -2.0, 0.4])
    parts += [pillar, table]
    for k in range(40):  # clutter on the walls: many small boxes (the 'content' of a level)
        b = trimesh.creation.box(extents=(0.2, 0.05, 0.2))
        b.apply_translation([-size[0] / 2 + 0.3 + (k % 10) * size[0] / 10, size[1] / 2 - 0.05 * (k // 10 + 1), 1.5])
        parts.append(b)
    if ground:  # two triangles, as a level's ground plane is
        h = ground / 2
        parts.append(trimesh.Trimesh([[-h, -h, -0.01], [h, -h, -0.01], [h, h, -0.01], [-h, h, -0.01]],
                                     [[0, 1, 2], [0, 2, 3]], process=False))
    m = trimesh.util.concatenate(parts)
    return LevelGeometry(np.asarray(m.vertices) / unit, np.asarray(m.faces), metres_per_unit=unit)


@pytest.fixture(scope="module")
def room():
    return _room()


@pytest.fixture(scope="module")
def walks(room):
    return [plan_level_path(room, "walk", 25, FPS, s, (HFOV, VFOV)) for s in range(3)]


def test_walk_eye_height_speed_turn_and_clearance(room, walks):
    rules = PathRules()
    for p in walks:
        e = p.eyes
        assert np.allclose(e[:, 2], rules.eye_height_m, atol=1e-6)  # the floor is z = 0 everywhere it walks
        step = np.linalg.norm(np.diff(e[:, :2], axis=0), axis=1)
        assert np.allclose(step, rules.walk_speed_mps / FPS, rtol=1e-6)
        heading = np.unwrap(np.arctan2(np.diff(e[:, 1]), np.diff(e[:, 0])))
        assert np.abs(np.diff(heading)).max() <= math.radians(rules.max_turn_deg_s) / FPS + 1e-9
        # exact distance of every eye to every triangle (trimesh), and the segment bound of the module doc
        _, d, _ = trimesh.proximity.closest_point(room.mesh, e)
        assert d.min() >= rules.clearance_m + 0.5 * rules.walk_speed_mps / FPS - 1e-9
        assert p.report["clearance_m"] == pytest.approx(d.min())
        assert p.report["speed_mps"] == pytest.approx(rules.walk_speed_mps, rel=1e-6)


def test_walk_never_enters_the_pillar_or_the_table(walks):
    for p in walks:
        xy = p.eyes[:, :2]
        assert not np.any((np.abs(xy[:, 0] - 1.5) < 0.3) & (np.abs(xy[:, 1] - 1.0) < 0.3))
        assert not np.any((np.abs(xy[:, 0] + 3.0) < 0.6) & (np.abs(xy[:, 1] + 2.0) < 0.4))
        assert np.all(np.abs(xy[:, 0]) < 6) and np.all(np.abs(xy[:, 1]) < 4.5)


def test_views_have_content(room, walks):
    """Our own rays through each frame's view: background (misses) at most the rule, median depth above it."""
    rules = PathRules()
    for p in walks:
        for e, t in zip(p.eyes, p.targets):
            f = (t - e) / np.linalg.norm(t - e)
            d = view_dirs(f, HFOV, VFOV, 8, 5)
            hit = room.mesh.ray.intersects_any(np.repeat(e[None], len(d), 0), d)
            assert hit.mean() >= 1 - rules.max_background
            loc, idx, _ = room.mesh.ray.intersects_location(np.repeat(e[None], len(d), 0), d, multiple_hits=False)
            assert np.median(np.linalg.norm(loc - e, axis=1)) >= rules.min_view_depth_m


def test_same_seed_same_path_other_seed_differs(room, walks):
    again = plan_level_path(room, "walk", 25, FPS, 0, (HFOV, VFOV))
    assert np.array_equal(again.eyes, walks[0].eyes) and np.array_equal(again.targets, walks[0].targets)
    assert not np.allclose(walks[0].eyes, walks[1].eyes)


def test_fly_keeps_clearance_height_and_speed(room):
    rules = PathRules()
    p = plan_level_path(room, "fly", 25, FPS, 4, (HFOV, VFOV))
    step = np.linalg.norm(np.diff(p.eyes, axis=0), axis=1)
    assert np.allclose(step, rules.fly_speed_mps / FPS, rtol=1e-6)
    _, d, _ = trimesh.proximity.closest_point(room.mesh, p.eyes)
    assert d.min() >= rules.clearance_m
    assert np.all(p.eyes[:, 2] >= rules.min_fly_height_m - 1e-9) and np.all(p.eyes[:, 2] < 3.0)


def test_units_are_metres_whatever_the_scene_scale():
    """A level modelled in centimetres (1 unit = 0.01 m): the same path in metres."""
    cm = _room(unit=0.01)
    p = plan_level_path(cm, "walk", 13, FPS, 0, (HFOV, VFOV))
    m = plan_level_path(_room(), "walk", 13, FPS, 0, (HFOV, VFOV))
    assert np.allclose(p.eyes * 0.01, m.eyes, atol=1e-6)
    assert p.report["speed_mps"] == pytest.approx(1.4)


def test_regions_keep_the_eyes_in_their_cell(room):
    lo, hi = room.content_bounds()
    region = Region((float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])), 2, 2, ((1, 0),))
    for kind in ("walk", "fly"):
        p = plan_level_path(room, kind, 25, FPS, 1, (HFOV, VFOV), region)
        assert region.contains(p.eyes[:, :2]).all()
        assert (region.cell_of(p.eyes[:, :2]) == [1, 0]).all()


def test_content_box_ignores_a_huge_ground_plane_and_inside_test():
    g = _room(ground=2000.0)
    lo, hi = g.content_bounds()
    assert np.all(hi[:2] - lo[:2] < 20) and g.extent < 25  # the 2 km plane does not define the level
    assert g.inside_closed_mesh(np.array([1.5, 1.0, 1.0]))      # inside the pillar
    assert not g.inside_closed_mesh(np.array([0.0, -2.0, 1.6]))  # in the room
    p = plan_level_path(g, "walk", 9, FPS, 0, (HFOV, VFOV))
    assert np.all(np.abs(p.eyes[:, :2]) < 6)


def _parts(*meshes) -> LevelGeometry:
    m = trimesh.util.concatenate(meshes)
    owner = np.concatenate([np.full(len(x.faces), i) for i, x in enumerate(meshes)])
    return LevelGeometry(np.asarray(m.vertices), np.asarray(m.faces), owner=owner)


def test_a_skybox_object_does_not_widen_the_content_box_and_encloses_the_camera():
    """A 2 km skybox sphere of many triangles around a street of boxes: left out of the content box, and the
    camera walks among the boxes inside it (the skybox looks inwards)."""
    sky = trimesh.creation.icosphere(subdivisions=4, radius=1000.0)
    sky.invert()
    floor = trimesh.creation.box(extents=(30.0, 30.0, 0.1))
    floor.apply_translation([0, 0, -0.05])
    blocks = []
    for k in range(6):
        b = trimesh.creation.box(extents=(4.0, 4.0, 6.0))
        b.apply_translation([-10.0 + 4.0 * (k % 3) * 2.0, 6.0 if k < 3 else -6.0, 3.0])
        blocks.append(b)
    g = _parts(floor, *blocks, sky)
    lo, hi = g.content_bounds()
    assert np.all(hi - lo < 40) and len(sky.faces) > 0.5 * g.n_triangles
    p = plan_level_path(g, "walk", 13, FPS, 2, (HFOV, VFOV))
    assert np.all(np.abs(p.eyes[:, :2]) < 16)


def test_a_room_with_outward_normals_is_still_a_room():
    """Blender's default cube scaled into a room (normals outwards): the eye inside is not 'inside a solid'."""
    room = trimesh.creation.box(extents=(10.0, 8.0, 3.0))
    room.apply_translation([0, 0, 1.5])
    shelf = trimesh.creation.box(extents=(4.0, 0.4, 2.0))
    shelf.apply_translation([0, 3.6, 1.0])
    g = _parts(room, shelf)
    assert not g.inside_closed_mesh(np.array([0.0, 0.0, 1.6]))
    assert g.inside_closed_mesh(np.array([0.0, 3.6, 1.0]))  # inside the shelf
    plan_level_path(g, "walk", 9, FPS, 0, (HFOV, VFOV))


def test_no_floor_in_the_region_is_a_one_line_error(room):
    far = Region((100.0, 100.0), (110.0, 110.0))
    with pytest.raises(PathError, match="no walk path meets the rules after 5 tries") as e:
        plan_level_path(room, "walk", 9, FPS, 0, (HFOV, VFOV), far, PathRules(tries=5))
    assert "\n" not in str(e.value)


def test_a_view_of_only_sky_is_redrawn_then_refused():
    """An open floor with nothing on it, seen level: every view is half sky, so no path is accepted. (Looking
    14 degrees down, a third of the view is sky, under the 40 % rule.)"""
    plane = trimesh.creation.box(extents=(200.0, 200.0, 0.01))
    g = LevelGeometry(plane.vertices, plane.faces)
    with pytest.raises(PathError, match="sky or background"):
        plan_level_path(g, "walk", 9, FPS, 0, (HFOV, VFOV), rules=PathRules(tries=6, pitch_deg=(0.0, 2.0)))


def test_a_sky_lit_level_refuses_eyes_under_a_roof():
    """light = "sky": an eye that sees no sky renders black (the town level's black test clip, 2026-11-26). The
    sky fraction is measured here with trimesh's own rays."""
    roofed, courtyard = _room(), _room(roof=False)
    rules = PathRules(min_sky_fraction=0.05, tries=8)
    with pytest.raises(PathError, match="under a roof"):
        plan_level_path(roofed, "walk", 9, FPS, 0, (HFOV, VFOV), rules=rules)
    p = plan_level_path(courtyard, "walk", 9, FPS, 0, (HFOV, VFOV), rules=rules)
    up = trimesh.sample.sample_surface_sphere(400)
    up = up[up[:, 2] > 0]
    mesh = trimesh.Trimesh(courtyard.vertices, courtyard.faces, process=False)
    for e in p.eyes:
        hit = mesh.ray.intersects_any(np.repeat(e[None], len(up), axis=0), up)
        assert 1 - hit.mean() >= 0.05
    assert p.report["sky_fraction_min"] >= 0.05
    # without the rule (a level lit by its own lights) the roofed room is a valid place
    assert "sky_fraction_min" not in plan_level_path(roofed, "walk", 9, FPS, 0, (HFOV, VFOV)).report


def test_a_path_framing_one_flat_surface_gives_way_to_one_with_near_and_far_content():
    """choose_path: the most structure wins when it shows near and far content on at least validate's share of
    frames (NEAR_FAR_MIN_FRACTION); otherwise the path with the most such frames (validate's flat-view measure)."""
    from gbuffer_export.blender.level_cameras import LevelPath, choose_path, near_far_fraction
    from gbuffer_export.validate.exposure import NEAR_FAR_MIN_FRACTION, NEAR_FAR_RATIO
    assert near_far_fraction(np.array([1.0, NEAR_FAR_RATIO, 10.0, 2.9])) == 0.5

    def path(structure, near_far):
        return LevelPath("walk", np.zeros((2, 3)), np.ones((2, 3)),
                         {"structure_fraction_mean": structure, "near_far_fraction": near_far})
    wall, deep, deeper = path(0.9, 0.2), path(0.5, 0.8), path(0.4, 1.0)
    assert choose_path([wall, deep, deeper]) is deeper
    good_wall = path(0.9, NEAR_FAR_MIN_FRACTION)
    assert choose_path([good_wall, deeper]) is good_wall


def test_planned_views_report_their_depth_spread():
    room = _room()
    p = plan_level_path(room, "walk", 13, FPS, 0, (HFOV, VFOV))
    assert 0.0 <= p.report["near_far_fraction"] <= 1.0
