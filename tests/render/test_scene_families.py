"""The built-in generator's families (gbuffer_export/blender/default_scene/families.py): each adds only its own
objects (or changes only its own light or camera), draws from its own stream, keeps its parameters in the stated
ranges, and renders."""
from __future__ import annotations

import json

import numpy as np
import pytest

from gbuffer_export import open_clip
from gbuffer_export.dataset.families import BUILTIN_FAMILIES
from tests.conftest import requires_bpy
from tests.render.cli_batch import run_cli_batch
from tests.render.test_scene_default import run_probe

pytestmark = [pytest.mark.bpy, requires_bpy]
NEW = [n for n in BUILTIN_FAMILIES if n not in ("broken_pane", "window_pane")]
#: The texture node each material family's pattern is made of.
TEX = {"noise": "TEX_NOISE", "voronoi": "TEX_VORONOI", "wave": "TEX_WAVE", "brick": "TEX_BRICK",
       "layered": "TEX_VORONOI"}
MIXED = ["mat_noise", "railing", "neon", "cam_pan", "boolean", "instanced", "motion_objects"]


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
    classes = set()
    for pattern, node in TEX.items():
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


def test_material_surfaces_are_large_and_of_a_principled_class(probe):
    b = probe["alone"]["mat_surfaces"]
    tagged = _tagged(b, "mat_surfaces")
    assert set(tagged) == {"Surface Wall", "Surface Floor", "Surface Sculpture"}
    for name, ob in tagged.items():
        m = b["materials"][ob["materials"][0]]
        assert ob["props"]["principled_class"] in probe["family_classes"]
        assert TEX[ob["props"]["pattern"]] in m["node_types"] and m["inputs"]["Base Color"]["linked"], name
    size = {n: np.subtract(*reversed(ob["bounds"])) for n, ob in tagged.items()}
    assert min(size["Surface Wall"][0], size["Surface Wall"][1]) < 0.5 and max(size["Surface Wall"][:2]) > 1.55
    assert size["Surface Wall"][2] > 0.99 and size["Surface Floor"][0] * size["Surface Floor"][1] > 1.9
    assert size["Surface Floor"][2] < 0.011 and size["Surface Sculpture"].min() > 0.39


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
    # fog is rendered through the pipeline below (a raw Cycles depth pass stops at the fog's scattering events)
    props = [n for n in NEW if not n.startswith("cam_") and n != "fog"] + ["cam_cut"]
    info = run_probe("default_render", {"out": str(out), "frame": 1, "size": [32, 18], "props": props})
    ch = read_exr_channels(out)
    layer = info["view_layer"]
    rgb = np.stack([ch[f"{layer}.Combined.{c}"] for c in "RGB"], axis=-1)
    depth = ch[f"{layer}.Depth.Z"]
    assert rgb.shape == (18, 32, 3) and np.isfinite(rgb).all() and rgb.min() >= 0 and rgb.max() > 0
    assert (depth < 1e9).mean() > 0.6


def test_booleans_cut_through_and_displacement_roughens(probe):
    b = probe["alone"]["boolean"]["objects"]
    wall, block = b["Boolean Wall"], b["Boolean Block"]
    assert wall["verts"] > 150 and block["verts"] > 40      # a bevelled box alone has 32: the cuts were applied
    assert not any(n.endswith("Cutter") for n in b)         # the cutters are gone
    assert not wall["fcurves"] and wall["props"]["blendsr_family"] == "boolean"
    d = probe["alone"]["displaced"]["objects"]
    for name in ("Displaced Boulder", "Displaced Column"):
        assert d[name]["verts"] > 1500, name                # subdivided before the displacement was applied
    lo, hi = np.array(d["Displaced Column"]["bounds"])
    assert hi[2] - lo[2] > 0.95 and lo[2] > -0.06


def test_instances_are_realised_at_a_game_density(probe):
    b = probe["alone"]["instanced"]
    soil = b["objects"]["Instanced Soil"]
    params = json.loads(soil["props"]["family_params"])
    area = params["length_m"] * params["depth_m"]
    count = soil["props"]["instance_count"]
    assert count >= 150 and abs(count - params["density_per_m2"] * area) < 0.25 * params["density_per_m2"] * area
    assert soil["verts"] > 20 * count                       # realised meshes, not instances
    assert {"Pebble Stone", "Grass Blades"} <= set(soil["materials"])
    (x0, y0, z0), (x1, y1, z1) = soil["bounds"]
    assert z1 < params["height_m"] + 0.12 and z0 > params["height_m"] - 0.06


def test_fog_is_a_volume_domain_around_every_camera(probe):
    b = probe["alone"]["fog"]
    fog = b["objects"]["Fog Volume"]
    mat = b["materials"][fog["materials"][0]]
    assert mat["surface"] is None and "PRINCIPLED_VOLUME" in mat["node_types"]
    (x0, y0, z0), (x1, y1, z1) = fog["bounds"]
    for name in ("plain", "mixed"):
        eye = np.array(probe[name]["animated_matrices"][probe[name]["camera"]])[:, :3, 3]
        assert (eye > [x0, y0, z0]).all() and (eye < [x1, y1, z1]).all()


def test_moving_objects_move_and_spin(probe):
    b = probe["alone"]["motion_objects"]
    movers = _tagged(b, "motion_objects")
    assert 2 <= len(movers) <= 4
    for name in movers:
        m = np.array(b["animated_matrices"][name])
        step = np.linalg.norm(np.diff(m[:, :3, 3], axis=0), axis=1)
        assert np.all((step > 0.0095) & (step < 0.061)), (name, step)
        r = m[:, :3, :3] / np.linalg.norm(m[:, :3, 0], axis=1)[:, None, None]
        cos = (np.einsum("fij,fij->f", r[1:], r[:-1]) - 1) / 2
        assert np.all(np.degrees(np.arccos(np.clip(cos, -1, 1))) > 1.9), name


def test_new_families_render_and_validate(tmp_path):
    """A builtin clip with the new families through ``blendsr dataset``: the movers are recorded as moving, the fog
    leaves the G-buffers on the surfaces behind it, and ``validate`` (motion check included) passes."""
    spec = tmp_path / "fam.toml"
    spec.write_text("""
[dataset]
name = "fam"
[render]
frames = 2
hr_size = "64x32"
hr_spp = 1
lr_spp = 1
gbuffer_spp = 1
hr_denoise = false
[[source]]
name = "fam"
kind = "builtin"
props = ["motion_objects", "fog", "boolean", "displaced", "instanced"]
seeds = "3:3"
cameras = ["scene"]
hdri = ["builtin:courtyard"]
""")
    out = tmp_path / "ds"
    proc, val = run_cli_batch(["dataset", spec, "-o", out, "--threads", "2", "--no-progress"],
                              ["validate", out, "--no-progress"])  # one process (cli_batch)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    man = json.loads((out / "clips" / "fam-s0003" / "manifest.json").read_text())
    assert {"Mover 1", "Mover 2"} <= set(man["moving_objects"])
    assert "Fog Volume" not in man["moving_objects"]
    families = set(man["scene"]["families"])
    assert {"motion:objects", "light:fog", "geometry:boolean", "geometry:displaced", "geometry:instanced"} <= families
    assert val.returncode == 0 and "1/1 clips valid" in val.stdout, val.stdout + val.stderr[-2000:]


@pytest.fixture(scope="module")
def walkers():
    """Seed 3 with the walkers (two: one behind the table, one in front), 24 frames (over half a stride cycle at the
    slowest walk, so each foot is lifted and put): ``probe_deformed``."""
    return run_probe("deformed", {"seed": 3, "frames": [1, 24], "props": ["motion_character"], "every": 1})


def test_walkers_walk_along_their_lanes_facing_where_they_go(probe, walkers):
    from gbuffer_export.blender.default_scene.families import FENCE_LANE_Y, LANE_SPREAD
    tagged = _tagged(probe["alone"]["motion_character"], "motion_character")
    assert {ob["type"] for ob in tagged.values()} == {"ARMATURE", "MESH"}
    assert set(walkers["rigs"]) == {"Walker 1 Rig", "Walker 2 Rig"}
    for k, (rig, rec) in enumerate(sorted(walkers["rigs"].items())):
        params = json.loads(walkers["params"][rig])
        h = params["front_height_m" if k else "height_m"]
        assert params["count"] == 2 and abs(walkers["meshes"][f"Walker {k + 1}"]["height"] - h) < 0.001 * h
        m = np.array(rec["matrix"])
        step = np.diff(m[:, :3, 3], axis=0)
        assert np.allclose(np.linalg.norm(step[:, :2], axis=1), params["m_per_frame"], rtol=1e-4), rig
        facing = -m[:, :3, 1]                                   # the rest pose faces -Y
        assert np.all(np.einsum("fi,fi->f", facing[1:, :2], step[:, :2]) > 0.99 * params["m_per_frame"]), rig
        start = json.loads(walkers["starts"][rig])
        lane = start["lane_m"]
        assert np.allclose(m[0, :2, 3], (start["x_m"], lane), atol=1e-6), rig
        assert np.sign(step[0, 0]) == start["direction"], rig
        d = np.array(walkers["meshes"][f"Walker {k + 1}"]["deformed"]).reshape(-1, 3)
        reach = np.abs(d[:, 1] - lane).max()                 # the walk's reach across its lane clears the table
        side, fence = abs(lane) - 0.47 - reach, lane - reach - FENCE_LANE_Y  # or it walks behind the fence
        ok = (0.0 <= side <= LANE_SPREAD + 1e-6 or -1e-4 <= fence <= LANE_SPREAD + 1e-6) if k == 0 else abs(side) < 1e-4
        assert ok and (lane > 0) == (k == 0), (rig, side, fence)
        near = d[(np.abs(d[:, 0]) < 0.8) & (d[:, 2] < 0.8)]            # what could meet the table top
        assert len(near) and np.abs(near[:, 1]).min() > 0.45, (rig, np.abs(near[:, 1]).min())


def test_a_walk_turned_and_moved_has_the_boxes_the_rule_predicts():
    """The rule measures a walk once (keyed at the origin heading +X) and moves its boxes to each start, turning them
    180 degrees for -X: ``placement.measure`` gives the evaluated vertices' box in every frame (the walker moving),
    and the same walk keyed at a start, either way, has the boxes ``sweep.placed`` predicts (0.01 mm)."""
    from gbuffer_export import sweep
    starts = [[0.3, 1.1, 1.0], [-0.4, -0.8, -1.0]]
    r = run_probe("walk_turn", {"starts": starts})
    measured, origin = np.array(r["measured"]), np.array(r["origin"])
    assert measured.shape == (8, 2, 3) and np.allclose(measured, origin, atol=1e-5)
    assert np.allclose(np.diff(origin[:, :, 0].mean(axis=1)), 0.05, atol=0.02)      # it walks +X, frame by frame
    for start, moved in zip(starts, r["moved"]):
        want = np.stack([sweep.placed(box, np.array([start]))[0] for box in origin])
        assert np.allclose(np.array(moved), want, atol=1e-5), (start, np.abs(np.array(moved) - want).max())


CROWD = ["boolean", "motion_objects", "mat_surfaces", "motion_character"]


def test_walkers_pass_through_nothing_and_one_without_room_is_left_out():
    """Beside a boolean wall, flying movers and ``mat_surfaces`` (seed 3: without the rule a walker's vertices enter
    their boxes), no vertex of either walker comes within 1 cm of another object's box (its evaluated vertices') in
    any frame; the rule keeps 2 cm between boxes. Behind a railing at y -1 (seed 3) the walker in front has no lane
    there: it walks behind the table, clear of the first walker too. Beside the crowd of seed 5 the first walker finds
    no start the scene camera sees (the boolean wall stands on its lanes and hides those behind the fence): it is left
    out (the scene records it), and nothing of it stays in ``bpy.data``."""
    crowd = run_probe("crowd", {"seed": 3, "frames": [1, 48], "shown": [1, 8], "gap": 0.01, "props": CROWD})
    assert crowd["walkers"] == ["Walker 1", "Walker 2"], crowd["walkers"]
    assert all(len(n) == 8 and max(n) == 0 for n in crowd["near"].values()), crowd["near"]
    railed = run_probe("crowd", {"seed": 3, "frames": [1, 8], "gap": 0.01, "props": ["railing", "motion_character"]})
    assert railed["walkers"] == ["Walker 1", "Walker 2"] and railed["left_out"] == [], railed
    assert railed["starts"]["Walker 2"]["lane_m"] > 0.45, railed["starts"]          # behind the table, not in front
    assert all(len(n) == 8 and max(n) == 0 for n in railed["near"].values()), railed["near"]
    hidden = run_probe("crowd", {"seed": 5, "frames": [1, 48], "shown": [1, 8], "gap": 0.01, "props": CROWD})
    assert hidden["walkers"] == ["Walker 2"] and hidden["params"]["Walker 2"]["count"] == 2, hidden
    assert not [n for n in hidden["left"] if n.startswith("Walker 1")], hidden["left"]
    assert hidden["left_out"] == ["Walker 1"] and crowd["left_out"] == []


def test_the_share_of_the_frame_a_walker_is_placed_by_is_what_cycles_renders(tmp_path):
    """``placement.frame_share`` (one ray per pixel, on through glass and alpha-cut surfaces) against the Object
    Index pass of Cycles at the same frame (one sample on each pixel's centre; the glass on the table hidden from its
    camera rays, which the placement's rays pass through): a walker in front and one behind the
    fence, seen through its pickets and wire mesh (seed 3 beside the crowd), and one behind the table beside a second
    one (seed 3 beside a railing), and the first two through the camera made orthographic (3 m wide), the same
    within 0.05 % of the frame; each start records the share placement measured (first, middle and last frames), at
    least the floor."""
    railed = ["railing", "motion_character"]
    for props, lanes, ortho in ((CROWD, ("fence", "front"), 0), (railed, ("table", "table"), 0),
                                (CROWD, ("fence", "front"), 3)):
        r = run_probe("walker_share", {"seed": 3, "props": props, "size": [128, 72], "frame": 4, "ortho": ortho,
                                       "out": str(tmp_path / "index.exr")})
        assert sorted(r["rays"]) == ["Walker 1", "Walker 2"], r
        for name, lane in zip(("Walker 1", "Walker 2"), lanes):
            y = r["starts"][name]["lane_m"]
            assert {"fence": y > r["fence_y"], "front": y < 0, "table": 0 < y < r["fence_y"]}[lane], (name, y)
            assert r["rendered"][name] > 0.002 and abs(r["rays"][name] - r["rendered"][name]) <= 5e-4, r
            assert r["starts"][name]["frame_share"] >= r["floor"], r["starts"]


def test_walkers_are_skinned_whole_and_bend_without_tearing(walkers):
    for name, rec in walkers["meshes"].items():
        assert rec["ungrouped"] == 0 and abs(rec["weight_sum"][0] - 1) < 1e-5 and abs(rec["weight_sum"][1] - 1) < 1e-5
        assert rec["feet_groups"] == ["foot.L", "foot.R", "shin.L", "shin.R"], name
        assert rec["hand_groups"] == ["forearm.L", "forearm.R"], name
        assert max(rec["edge_stretch"]) < 1.6, (name, rec["edge_stretch"])
        for a, b in zip(rec["deformed"][:-1], rec["deformed"][1:]):   # not rigid: the best rigid fit leaves cm
            a, b = np.array(a) - np.mean(a, axis=0), np.array(b) - np.mean(b, axis=0)
            u, _, vt = np.linalg.svd(a.T @ b)
            assert np.linalg.norm(a @ (u @ vt) - b, axis=1).max() > 0.02, name


def test_walkers_stand_on_the_ground_and_a_foot_on_it_stays_put(walkers):
    """Every frame the lowest vertex is a sole on the ground (within 1 cm); a foot on the ground in two frames (its
    sole within 0.1 mm per metre of height of its rest level) has not moved between them; each foot is lifted
    (swing) and put (stance) in the 24 frames; a straight (stance) leg's thigh at a negative angle puts its ankle ahead
    of its hip."""
    for k, (rig, rec) in enumerate(sorted(walkers["rigs"].items())):
        mesh = walkers["meshes"][f"Walker {k + 1}"]
        d, rest, h = np.array(mesh["deformed"]), np.array(mesh["rest"]), mesh["height"]
        assert np.all(np.abs(d[:, :, 2].min(axis=1)) < 0.01), d[:, :, 2].min(axis=1)
        fwd = np.diff(np.array(rec["matrix"])[:, :2, 3], axis=0)[0]
        fwd /= np.linalg.norm(fwd)
        for side, sx in (("L", 1.0), ("R", -1.0)):
            foot = d[:, (rest[:, 2] < 0.045 * h) & (np.sign(rest[:, 0]) == sx)]
            down = foot[:, :, 2].min(axis=1) < -0.0009 * h             # the sole is at -0.001 h
            assert down.any() and not down.all(), (rig, side, foot[:, :, 2].min(axis=1))
            slide = np.linalg.norm(np.diff(foot[:, :, :2].mean(axis=1), axis=0), axis=1)
            assert np.all(slide[down[1:] & down[:-1]] < 0.001), (rig, side, slide)
            for (angle, hip, ankle), grounded in zip(rec["legs"][side], down):
                if grounded and abs(angle) > 0.05:                     # the stance leg is straight
                    assert np.sign(np.dot(np.subtract(ankle, hip)[:2], fwd)) == -np.sign(angle), (rig, side)


def _vertex_motion_errors(clip, meshes, frames, rigid: bool):
    """Per visible HR vertex of the walkers (stored depth within 1 % of its own, MOVING): the stored motion minus the
    vertex's motion from frame t to t-1 projected with the clip's cameras (un-jittered positions; the stored pixel
    is the one whose jittered sample is nearest). ``rigid``: the motion the vertex would have if it only followed
    its rig (a translation: the rig's heading is constant), instead of its skinned position at t-1."""
    from gbuffer_export.conventions import Flag, project, transform_points
    errs = []
    for f in clip.frames:
        cam, i = clip.camera(f, "hr"), f - frames[0] + 1                    # probe index 0 is frame start-1
        depth, flags = clip.read(f, "hr/depth")[..., 0], clip.read(f, "hr/flags")[..., 0]
        motion = clip.read(f, "hr/motion")
        h, w = depth.shape
        for rec in meshes.values():
            now = np.array(rec["deformed"][i])
            before = (now + np.array(rec["rigid"][i - 1]) - np.array(rec["rigid"][i]) if rigid
                      else np.array(rec["deformed"][i - 1]))
            pc = transform_points(np.linalg.inv(cam["world_from_camera"]), now)
            x, y = project(pc, cam["intrinsics"])
            xp, yp = project(transform_points(np.linalg.inv(cam["prev_world_from_camera"]), before),
                             cam["prev_intrinsics"])
            px = np.floor(x - cam["jitter"][0]).astype(int)
            py = np.floor(y - cam["jitter"][1]).astype(int)
            ok = (px >= 0) & (px < w) & (py >= 0) & (py < h)
            px, py, z = px[ok], py[ok], -pc[ok, 2]
            vis = (np.abs(depth[py, px] - z) < 0.01 * z) & ((flags[py, px] & int(Flag.MOVING)) != 0)
            expect = np.stack([xp - x, yp - y], axis=-1)[ok][vis]
            errs.append(np.linalg.norm(motion[py[vis], px[vis]] - expect, axis=-1))
    return np.concatenate(errs)


def test_walkers_motion_vectors_follow_the_deformed_surface(tmp_path):
    """A clip of two walkers through ``blendsr dataset``: they are recorded as moving, ``validate`` passes (and a
    clip whose crowd leaves the first walker no clear start in view records it in ``scene.left_out``), and the
    stored motion of the surface equals the motion of the evaluated (skinned) vertices projected with the clip's
    cameras, clearly better than the rig's rigid motion."""
    spec = tmp_path / "walk.toml"
    spec.write_text("""
[dataset]
name = "walk"
[render]
frames = 3
hr_size = "128x72"
hr_spp = 1
lr_spp = 1
gbuffer_spp = 1
hr_denoise = false
[[source]]
name = "walk"
kind = "builtin"
props = ["motion_character"]
seeds = "3:3"
cameras = ["scene"]
hdri = ["builtin:courtyard"]
[[source]]
name = "hidden"
kind = "builtin"
props = ["boolean", "motion_objects", "mat_surfaces", "motion_character"]
seeds = "5:5"
cameras = ["scene"]
hdri = ["builtin:courtyard"]
""")
    out = tmp_path / "ds"
    proc, val = run_cli_batch(["dataset", spec, "-o", out, "--threads", "2", "--no-progress"],
                              ["validate", out, "--no-progress"])
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert val.returncode == 0 and "2/2 clips valid" in val.stdout, val.stdout + val.stderr[-2000:]
    hidden = open_clip(out / "clips" / "hidden-s0005")      # no start in view: walker 1 left out
    assert hidden.manifest["scene"]["left_out"] == ["Walker 1"]
    assert "Walker 1" not in hidden.manifest["moving_objects"] and "Walker 2" in hidden.manifest["moving_objects"]
    clip = open_clip(out / "clips" / "walk-s0003")
    assert "left_out" not in clip.manifest["scene"]
    assert {"Walker 1", "Walker 2"} <= set(clip.manifest["moving_objects"])
    assert "motion:character" in clip.manifest["scene"]["families"]
    frames = [min(clip.frames), max(clip.frames)]
    deformed = run_probe("deformed", {"seed": 3, "frames": frames, "props": ["motion_character"], "every": 1})
    assert deformed["frames"] == frames and set(deformed["meshes"]) == {"Walker 1", "Walker 2"}
    err = _vertex_motion_errors(clip, deformed["meshes"], frames, rigid=False)
    rigid = _vertex_motion_errors(clip, deformed["meshes"], frames, rigid=True)
    assert len(err) > 100 and np.median(err) < 0.2 and np.mean(err < 0.5) > 0.9, (len(err), np.median(err))
    assert np.percentile(rigid, 90) > 3 * np.percentile(err, 90), (np.percentile(rigid, 90), np.percentile(err, 90))
