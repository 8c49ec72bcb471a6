"""``blendsr dataset --dry-run`` plans every walk and fly clip in its level (issue 55 item 1): import and plan only,
no render; per clip the path it would take or the reason it has none with a fix that works, and a warning for a
single object. Two small shared files (the garage level and a bottle), each imported once, and two hand-made asset
files (one this Blender cannot import), in one process."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from tests.conftest import requires_bpy, run_cli, shared_or_skip
from tests.gltf_fixtures import write_glb

pytestmark = [requires_bpy, pytest.mark.bpy, pytest.mark.shared]


def _assets(folder: Path) -> None:
    """Film.glb (requires KHR_materials_iridescence, which BlendSR applies), Packed.glb (requires
    EXT_meshopt_compression, which Blender 5.0.1's importer lacks) and Deep.gltf (JSON nested too deeply to read)."""
    write_glb(folder / "Film.glb")
    bad = write_glb(folder / "Packed.glb", required=False)
    data = bad.read_bytes()
    n = int.from_bytes(data[12:16], "little")
    doc = json.loads(data[20:20 + n])
    doc["extensionsUsed"].append("EXT_meshopt_compression")
    doc["extensionsRequired"] = ["EXT_meshopt_compression"]
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = len(text).to_bytes(4, "little") + b"JSON" + text + data[20 + n:]
    bad.write_bytes(b"glTF" + (2).to_bytes(4, "little") + (12 + len(body)).to_bytes(4, "little") + body)
    (folder / "Deep.gltf").write_text('{"asset": {"version": "2.0"}, "extras": ' + "[" * 100000 + "]" * 100000 + "}")


@pytest.fixture(scope="module")
def dry_run(tmp_path_factory):
    garage = shared_or_skip("scenes/levels/garage/garage.blend")
    bottle = shared_or_skip("scenes/gltf/WaterBottle/glTF/WaterBottle.gltf")
    tmp = tmp_path_factory.mktemp("dry")
    _assets(tmp / "assets")
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

[[source]]
name = "a"
kind = "assets"
paths = ["{tmp / 'assets'}"]
clips_per_asset = 2
clutter = 1
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
    assert len(clips) == 11, lines  # 5 level clips, 2 of each asset
    assert not any(ln.startswith(("IMPORTS ", "NO IMPORT ")) for ln in lines)


def test_every_asset_file_is_imported_once_before_the_render_and_one_that_cannot_be_is_named(dry_run):
    """A glTF requiring an extension this Blender lacks fails every clip that imports it, as asset or clutter; the
    dry run imports each asset file once, as the jobs do, and names it (the iridescent file imports: BlendSR applies
    its extension)."""
    proc, tmp = dry_run
    out = proc.stdout.splitlines()
    imports = [ln for ln in out if ln.startswith(("IMPORTS ", "NO IMPORT "))]
    good, bad = tmp / "assets" / "Film.glb", tmp / "assets" / "Packed.glb"
    assert len(imports) == 3, proc.stdout  # each file once, though each is also another's clutter
    assert f"IMPORTS {good}: 2 top-level object(s)" in imports
    refused = [ln for ln in imports if ln.startswith(f"NO IMPORT {bad}: ")]
    assert len(refused) == 1 and "EXT_meshopt_compression is not available" in refused[0], imports
    deep = [ln for ln in imports if ln.startswith(f"NO IMPORT {tmp / 'assets' / 'Deep.gltf'}: ")]
    assert len(deep) == 1 and "nested too deeply" in deep[0], imports  # one file's failure stops no other
    assert "blendsr: imported 3 asset files: 1 import, 2 do not" in out

