"""``blendsr dataset --dry-run`` plans every walk and fly clip in its level (issue 55 item 1): import and plan only,
no render; per clip the path it would take or the reason it has none with a fix that works, and a warning for a
single object. Two small shared files (the garage level and a bottle), each imported once, in one process."""
from __future__ import annotations

import re

import pytest

from tests.conftest import requires_bpy, run_cli, shared_or_skip

pytestmark = [requires_bpy, pytest.mark.bpy, pytest.mark.shared]


@pytest.fixture(scope="module")
def dry_run(tmp_path_factory):
    garage = shared_or_skip("scenes/levels/garage/garage.blend")
    bottle = shared_or_skip("scenes/gltf/WaterBottle/glTF/WaterBottle.gltf")
    tmp = tmp_path_factory.mktemp("dry")
    spec = tmp / "spec.toml"
    spec.write_text(f"""[dataset]
name = "dry"
seed = 1

[render]
hr_size = "32x16"
frames = 2

[[source]]
name = "lv"
kind = "scene"
paths = ["{garage}"]
cameras = ["walk", "fly"]
clips_per_scene = 4
regions = "2x2"
region_test = 1
region_val = 1

[[source]]
name = "obj"
kind = "scene"
paths = ["{bottle}"]
cameras = ["walk"]
clips_per_scene = 1
""")
    return run_cli("dataset", spec, "-o", tmp / "ds", "--dry-run", timeout=600), tmp


def test_every_walk_and_fly_clip_gets_its_path_or_its_reason_and_a_fix(dry_run):
    proc, tmp = dry_run
    out = proc.stdout.splitlines()
    paths = [ln for ln in out if ln.startswith("PATH ")]
    assert [ln.split()[1].rstrip(":") for ln in paths] == [f"lv-garage-{k:02d}" for k in range(4)], proc.stdout
    for ln in paths:
        assert re.search(r": (walk|fly) cell \(\d, \d\)", ln) and "median view depth" in ln
        assert ln.endswith("unit m (1 m/unit)")
    bottle = [ln for ln in out if ln.startswith("NO PATH obj-WaterBottle-00: ")]
    assert len(bottle) == 1 and "too small to hold a camera" in bottle[0] and bottle[0].endswith("use the camera orbit")
    assert out[-1] == "blendsr: planned 5 walk/fly clips: 4 have a path, 1 none"
    assert proc.returncode == 1  # a clip without a path: the dataset would fail it
    assert re.search(r"WaterBottle.gltf: the scene is a single object.*orbit", proc.stderr)
    assert "Traceback" not in proc.stderr and not (tmp / "ds").exists()  # nothing rendered, no folder made


def test_no_plan_prints_the_clips_only(dry_run, tmp_path):
    _, tmp = dry_run
    proc = run_cli("dataset", tmp / "spec.toml", "-o", tmp / "ds", "--dry-run", "--no-plan", timeout=120)
    lines = proc.stdout.splitlines()
    clips = [ln for ln in lines if not ln.startswith(("total ", "export "))]  # the totals and formats follow them
    assert proc.returncode == 0 and not any(ln.startswith(("PATH ", "NO PATH ")) for ln in lines)
    assert len(clips) == 5, lines
