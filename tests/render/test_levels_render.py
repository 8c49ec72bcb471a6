"""Datasets from real levels as they are (../shared/scenes/levels): the file's cameras, cameras that move inside,
the scene checks, a dataset with split regions, validate and the contact sheet. Rendered tiny (64x36, few spp)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ENV, REPO, requires_bpy, run_cli, shared_or_skip
from tests.render.cli_batch import run_cli_batch

pytestmark = [requires_bpy, pytest.mark.bpy, pytest.mark.shared]

TINY = ["--hr-size", "64x36", "--hr-spp", "2", "--lr-spp", "1", "--gbuffer-spp", "1", "--threads", "1",
        "--no-progress"]
GARAGE = "scenes/levels/garage/garage.blend"
TOWN = "scenes/levels/truck_town/town_model.gltf"


def _manifest(clip: Path) -> dict:
    return json.loads((clip / "manifest.json").read_text())


def test_the_garages_own_camera_renders_through_scene_star(tmp_path):
    garage = shared_or_skip(GARAGE)
    out = tmp_path / "own"
    r, v = run_cli_batch(["render", garage, "-o", out, "--camera-path", "scene:*", "--frames", "1:1", *TINY],
                         ["validate", out])
    assert r.returncode == 0, r.stderr[-2000:]
    m = _manifest(out)
    assert m["scene"]["camera"] == "Camera" and m["camera"] == {"kind": "scene", "choice": "scene:*",
                                                               "name": "Camera"}
    assert m["light"]["light"] == "auto" and m["light"]["kept"] == "scene" and not m["light"]["added"]
    assert m["light"]["scene_sources"]["lamps"] == 2 and m["light"]["probe"]["scene_light"]["log_average"] > 0.02
    assert m["render"]["device"] == "CPU" and m["render"]["device_names"]
    assert "CUEW" not in r.stderr  # probing for GPUs prints nothing
    assert v.returncode == 0, v.stdout + v.stderr


def test_walk_inside_the_garage_keeps_its_rules_and_validates(tmp_path):
    garage = shared_or_skip(GARAGE)
    out = tmp_path / "walk"
    r, v = run_cli_batch(["render", garage, "-o", out, "--camera-path", "walk", "--frames", "1:2", "--seed", "3",
                          *TINY], ["validate", out, "--json"])
    assert r.returncode == 0, r.stderr[-2000:]
    cam = _manifest(out)["camera"]
    assert cam["kind"] == "walk" and cam["speed_mps"] == pytest.approx(1.4, rel=1e-3)
    assert cam["clearance_m"] >= 0.25 and cam["fps"] == 24.0 and cam["ray_engine"] == "embree"
    frames = json.loads((out / "manifest.json").read_text())["frame_data"]
    eyes = np.array([np.array(frames[k]["hr"]["world_from_camera"])[:3, 3] for k in sorted(frames, key=int)])
    lo, hi = np.array(cam["region"]["lo"]), np.array(cam["region"]["hi"])
    assert np.all(eyes[:, :2] >= lo) and np.all(eyes[:, :2] <= hi)  # inside the garage's walls
    assert np.allclose(eyes[:, 2], eyes[0, 2], atol=0.05) and 1.4 < eyes[0, 2] < 1.8  # eye height, flat floor
    assert v.returncode == 0, v.stdout + v.stderr
    views = json.loads(v.stdout)["stats"]["camera_view"]
    assert len(views) == 2 and all(x["background_fraction"] < 0.5 and 0.75 <= x["median_depth_m"] <= cam[
        "level_extent_m"] for x in views.values())


def test_an_unlit_level_is_refused_under_scene_with_the_fix_then_lit_with_sky(tmp_path):
    town = shared_or_skip(TOWN)
    out = tmp_path / "sky"
    r, r_sky, v = run_cli_batch(
        ["render", town, "-o", tmp_path / "dark", "--camera-path", "fly", "--light", "scene", "--frames", "1:1", *TINY],
        ["render", town, "-o", out, "--camera-path", "fly", "--light", "sky", "--frames", "1:1", *TINY],
        ["validate", out])
    assert r.returncode == 2
    line = r.stderr.strip().splitlines()[-1]
    assert "no lights" in line and "set --light auto" in line and str(town.name) in line
    assert not (tmp_path / "dark" / "manifest.json").exists()
    assert r_sky.returncode == 0, r_sky.stderr[-2000:]
    m = _manifest(out)
    assert m["light"]["light"] == "sky" and 25 <= m["light"]["sun_elevation_deg"] <= 60
    assert m["camera"]["kind"] == "fly" and m["camera"]["background_fraction_max"] <= 0.4
    assert v.returncode == 0, v.stdout + v.stderr[-2000:]


def _garage_with_two_cameras(tmp_path: Path) -> Path:
    garage = shared_or_skip(GARAGE)
    out = tmp_path / "two_cams.blend"
    code = (f"import bpy; bpy.ops.wm.open_mainfile(filepath={str(garage)!r}); s = bpy.context.scene; "
            "c = bpy.data.objects.new('Zeta', bpy.data.cameras.new('Zeta')); s.collection.objects.link(c); "
            "c.location = (0.0, -1.0, 1.6); c.rotation_euler = (1.45, 0.0, 0.0); s.camera = None; "
            f"bpy.ops.wm.save_as_mainfile(filepath={str(out)!r})")
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, env=ENV, cwd=REPO, timeout=120)
    return out


def test_cameras_present_but_none_active_are_listed_and_any_can_be_chosen(tmp_path):
    blend = _garage_with_two_cameras(tmp_path)
    r, r_zeta, r_nope = run_cli_batch(
        ["render", blend, "-o", tmp_path / "none", "--frames", "1:1", *TINY],
        ["render", blend, "-o", tmp_path / "zeta", "--camera-path", "scene:Zeta", "--frames", "1:1", *TINY],
        ["render", blend, "-o", tmp_path / "nope", "--camera-path", "scene:Nope", "--frames", "1:1", *TINY])
    assert r.returncode == 2
    line = r.stderr.strip().splitlines()[-1]
    assert "2 camera(s) but none is active (Camera, Zeta)" in line and "scene:NAME" in line
    assert r_zeta.returncode == 0, r_zeta.stderr[-2000:]
    assert _manifest(tmp_path / "zeta")["scene"]["camera"] == "Zeta"
    assert r_nope.returncode == 2 and "no camera named 'Nope'" in r_nope.stderr


def test_a_gpu_that_cycles_does_not_see_is_refused(tmp_path):
    garage = shared_or_skip(GARAGE)
    r = run_cli("render", garage, "-o", tmp_path / "g", "--device", "cuda", "--frames", "1:1", *TINY)
    assert r.returncode == 2 and "--device cuda: Cycles sees no CUDA device" in r.stderr


@pytest.mark.heavy
def test_levels_dataset_with_split_regions_validates_and_previews(tmp_path):
    garage, town = shared_or_skip(GARAGE), shared_or_skip(TOWN)
    spec = tmp_path / "levels.toml"
    spec.write_text(f"""
[dataset]
name = "tiny-levels"
[render]
frames = 2
hr_size = "64x36"
hr_spp = 2
hr_denoise = false
lr_spp = 1
threads = 1
[[source]]
name = "garage"
kind = "scene"
paths = ["{garage}"]
clips_per_scene = 2
cameras = ["walk", "fly"]
regions = "2x2"
region_test = 1
[[source]]
name = "town"
kind = "scene"
paths = ["{town}"]
clips_per_scene = 2
cameras = ["fly", "walk"]
light = "sky"
sun_elevation_deg = [30, 50]
regions = "2x2"
region_test = 1
""")
    ds = tmp_path / "ds"
    r = run_cli("dataset", spec, "-o", ds, "--no-progress", "--device", "cpu")
    assert r.returncode == 0, r.stdout + r.stderr[-3000:]
    index = json.loads((ds / "dataset.json").read_text())
    clips = {c["id"]: c for c in index["clips"]}
    assert [c["split"] for c in index["clips"]] == ["test", "train", "test", "train"]
    assert {c["camera"] for c in index["clips"] if c["source"] == "garage"} == {"walk", "fly"}
    for c in index["clips"]:
        cells = c["region"]["cells"]
        assert c["region"]["cell"] in cells[c["split"]]
        assert not {tuple(x) for x in cells["test"]} & {tuple(x) for x in cells["train"]}
        m = _manifest(ds / c["path"])
        assert m["camera"]["region"]["cells"] == [c["region"]["cell"]]
        assert m["render"]["device"] == "CPU"
    town_m = _manifest(ds / clips["town-town_model-00"]["path"])
    assert town_m["light"]["variation"]["sun"]["elevation_deg"] == clips["town-town_model-00"]["variation"][
        "sun_elevation_deg"]
    v = run_cli("validate", ds)
    assert v.returncode == 0, v.stdout + v.stderr
    sheet = tmp_path / "sheet.png"
    p = run_cli("preview", ds, "-o", sheet)
    assert p.returncode == 0 and sheet.is_file() and "4 clips" in p.stdout
    # a test region's clip moved into a training cell is caught by the index check and by the clip's own check
    c0 = index["clips"][0]
    c0["region"]["cell"] = index["clips"][1]["region"]["cell"]
    (ds / "dataset.json").write_text(json.dumps(index))
    v = run_cli("validate", ds)
    assert v.returncode == 1 and "not a test region" in v.stdout


def test_walk_around_a_single_object_is_refused_naming_orbit(tmp_path):
    robot = shared_or_skip("scenes/blend/RobotExpressive.blend")
    r = run_cli("render", robot, "-o", tmp_path / "r", "--camera-path", "walk", "--frames", "1:2", *TINY)
    assert r.returncode == 2 and not (tmp_path / "r").exists()
    line = r.stderr.strip().splitlines()[-1]
    assert "RobotExpressive.blend: no walk path meets the rules" in line and "--camera-path orbit" in line


def test_render_takes_the_light_variation_and_records_it(tmp_path):
    garage = shared_or_skip(GARAGE)
    out = tmp_path / "v"
    r, bad = run_cli_batch(["render", garage, "-o", out, "--camera-path", "scene", "--frames", "1:1", "--sun",
                            "35,120", "--light-strength", "0.5", "--world-strength", "2", *TINY],
                           ["render", garage, "-o", tmp_path / "b", "--sun", "95,0", *TINY])
    assert r.returncode == 0, r.stderr[-2000:]
    v = _manifest(out)["light"]["variation"]
    assert v["sun"] == {"elevation_deg": 35.0, "azimuth_deg": 120.0, "sun_lamps": 1}
    assert v["light_strength"] == {"multiplier": 0.5, "lamps": 2} and v["world_strength"]["multiplier"] == 2.0
    assert bad.returncode == 2 and "--sun '95,0': elevation" in bad.stderr
