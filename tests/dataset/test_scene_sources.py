"""``kind = "scene"`` dataset sources (gbuffer_export/dataset/spec.py) and the scene memory check: pure Python."""
from __future__ import annotations

import re

import pytest

from gbuffer_export.config import ConfigError, RenderConfig
from gbuffer_export.dataset.spec import SpecError, expand, parse_spec, region_cells
from gbuffer_export.resources import ResourceError, check_render_resources


@pytest.fixture()
def level(tmp_path):
    (tmp_path / "a").mkdir()
    for name in ("a/hall.blend", "a/street.glb", "a/notes.txt"):
        (tmp_path / name).write_bytes(b"x")
    return tmp_path / "a"


def _spec(level, **kw):
    src = {"kind": "scene", "name": "lv", "paths": [str(level)], **kw}
    return parse_spec({"source": [src]})


def test_scene_files_clips_cameras_and_regions(level):
    jobs = expand(_spec(level, clips_per_scene=5, cameras=["walk", "fly"], regions="3x2", region_test=1,
                        region_val=1))
    assert [j.id for j in jobs[:2]] == ["lv-hall-00", "lv-hall-01"] and len(jobs) == 10  # .txt is not a scene
    hall = [j for j in jobs if j.id.startswith("lv-hall")]
    assert [j.camera for j in hall] == ["walk", "fly", "walk", "fly", "walk"]
    assert [j.split for j in hall] == ["test", "val", "train", "train", "train"]
    cells = hall[0].region["cells"]
    assert sorted(map(tuple, cells["test"] + cells["val"] + cells["train"])) == [(i, j) for i in range(3)
                                                                                  for j in range(2)]
    for j in hall:
        assert j.region["cell"] in cells[j.split] and j.scene_id == f"hall@cell{j.region['cell'][0]}-" \
                                                                    f"{j.region['cell'][1]}"
    assert {j.kind for j in jobs} == {"scene"} and all(j.light == "auto" for j in jobs)
    again = expand(_spec(level, clips_per_scene=5, cameras=["walk", "fly"], regions="3x2", region_test=1,
                         region_val=1))
    assert [j.to_json() for j in again] == [j.to_json() for j in jobs]


def test_region_cells_are_disjoint_and_seeded(level):
    src = _spec(level, regions="4x4", region_test=2, region_val=3).sources[0]
    a, b = region_cells(src, 0, "hall"), region_cells(src, 1, "hall")
    assert (len(a["test"]), len(a["val"]), len(a["train"])) == (2, 3, 11)
    flat = [tuple(c) for v in a.values() for c in v]
    assert len(flat) == len(set(flat)) == 16 and a != b


def test_without_regions_the_scene_is_one_split_and_variation_is_recorded(level):
    spec = parse_spec({"splits": {"test": ["street"]}, "source": [
        {"kind": "scene", "name": "lv", "paths": [str(level)], "cameras": ["scene:*"], "light": "sky",
         "clips_per_scene": 3, "world_strength": [0.5, 2.0], "sun_elevation_deg": [10, 40]}]})
    jobs = expand(spec)
    assert {j.split for j in jobs if "street" in j.id} == {"test"} and {j.split for j in jobs if "hall" in j.id} == \
        {"train"}
    assert [j.camera_index for j in jobs[:3]] == [0, 1, 2] and jobs[0].light == "sky"
    for j in jobs:
        v = j.variation
        assert 0.5 <= v["world_strength"] <= 2.0 and 10 <= v["sun_elevation_deg"] <= 40
        assert 0 <= v["sun_azimuth_deg"] < 360


@pytest.mark.parametrize("kw, message", [
    ({"regions": "0x3"}, "regions"),
    ({"regions": "2x2", "region_test": 4}, "region_val + region_test below the 4 cells"),
    ({"regions": "2x2", "region_test": 1, "cameras": ["walk", "scene:*"]}, "only walk and fly"),
    ({"regions": "2x2", "region_test": 1, "split": "train"}, "exclude each other"),
    ({"cameras": ["dolly"]}, "cameras item 'dolly'"),
    ({"light": "moon"}, "light 'moon'"),
    ({"clutter": 2}, "not for kind = \"scene\""),
    ({"sun_elevation_deg": [10, 95]}, "sun_elevation_deg"),
])
def test_bad_scene_sources_are_one_line_errors(level, kw, message):
    with pytest.raises(SpecError, match=re.escape(message)) as e:
        _spec(level, **kw)
    assert "\n" not in str(e.value)


def test_scene_keys_belong_to_scene_sources(level):
    with pytest.raises(SpecError, match='regions: only for kind = "scene"'):
        parse_spec({"source": [{"kind": "builtin", "seeds": "0:1", "regions": "2x2"}]})


def test_render_config_takes_scene_files_cameras_lights_devices(level, tmp_path):
    cfg = RenderConfig(output=tmp_path / "o", scene=level / "street.glb", camera_path="scene:Cam 2", light="sky",
                       device="cpu")
    assert cfg.camera_path == "scene:Cam 2"
    for kw, msg in (({"camera_path": "dolly"}, "^camera_path 'dolly'"), ({"light": "moon"}, "^light 'moon'"),
                    ({"device": "tpu"}, "^device 'tpu'"), ({"scene": level / "notes.txt"}, "not a scene file")):
        with pytest.raises(ConfigError, match=msg):
            RenderConfig(output=tmp_path / "o", **{"scene": level / "hall.blend", **kw})


def test_scene_memory_above_the_machine_is_refused_naming_the_scene(tmp_path):
    with pytest.raises(ResourceError, match=r"city.blend: its geometry and textures need about 40 GB"):
        check_render_resources((64, 36), 4, ("radiance",), 1, tmp_path, available=(16 * 10**9, 10**12),
                               scene_bytes=40 * 10**9, scene="city.blend")
    check_render_resources((64, 36), 4, ("radiance",), 1, tmp_path, available=(16 * 10**9, 10**12),
                           scene_bytes=10**9, scene="city.blend")


def _two_sources(level, first: dict, second: dict):
    base = {"kind": "scene", "paths": [str(level / "hall.blend")], "cameras": ["walk", "fly"]}
    return parse_spec({"source": [{**base, "name": "a", **first}, {**base, "name": "b", **second}]})


def test_a_level_in_several_sources_has_one_layout_and_one_order(level):
    """Two sources of one level (its stem: hall.blend and hall.glb alike): the first draws the cells, the second
    reuses them and continues the level's order test, val, train, so no cell is test in one and train in another;
    the first source's clips are those it has alone (a source appended to a spec changes no clip before it)."""
    grid = {"regions": "3x3", "region_test": 1, "region_val": 1}
    jobs = expand(_two_sources(level, {**grid, "clips_per_scene": 2}, {**grid, "clips_per_scene": 4}))
    alone = expand(parse_spec({"source": [{"kind": "scene", "name": "a", "paths": [str(level / "hall.blend")],
                                           "cameras": ["walk", "fly"], "clips_per_scene": 2, **grid}]}))
    assert [j.to_json() for j in jobs[:2]] == [j.to_json() for j in alone]
    assert [j.split for j in jobs] == ["test", "val", "train", "train", "train", "train"]
    assert len({str(j.region["cells"]) for j in jobs}) == 1
    cells = {}
    for j in jobs:
        cells.setdefault(tuple(j.region["cell"]), set()).add(j.split)
    assert all(len(s) == 1 for s in cells.values()), cells
    # what the shared layout prevents: the second source's own draw (seeded by its name) differs from the first's
    assert region_cells(_two_sources(level, grid, grid).sources[1], 0, "hall") != jobs[0].region["cells"]


@pytest.mark.parametrize("second, message", [
    ({"regions": "2x2", "region_test": 1, "region_val": 1}, 'use its regions = "3x3", region_test = 1'),
    ({"regions": "3x3", "region_test": 2, "region_val": 1}, "region_test = 1, region_val = 1"),
    ({}, "is split otherwise than in source 'a'"),
    ({"split": "train"}, "is split otherwise than in source 'a'"),
])
def test_a_level_split_two_ways_is_refused(level, second, message):
    spec = _two_sources(level, {"regions": "3x3", "region_test": 1, "region_val": 1}, second)
    with pytest.raises(SpecError, match=re.escape(message)) as e:
        expand(spec)
    assert "\n" not in str(e.value) and "source 'b': level 'hall'" in str(e.value)


@pytest.mark.parametrize("name", ["dataset_levels.toml", "dataset_large.toml", "dataset_wide.toml"])
def test_the_shipped_level_specs_keep_every_cell_in_one_split(name):
    from gbuffer_export.dataset.spec import load_spec
    from tests.conftest import REPO, shared_or_skip
    shared_or_skip("scenes/levels")
    cells: dict = {}
    for j in expand(load_spec(REPO / "examples" / name)):
        if j.region:
            stem = j.scene_id.split("@")[0]
            cells.setdefault((stem, tuple(j.region["cell"])), set()).add(j.split)
            assert j.region["cell"] in j.region["cells"][j.split]
    assert cells and all(len(s) == 1 for s in cells.values()), {k: v for k, v in cells.items() if len(v) > 1}


def test_materials_is_a_render_key_a_source_overrides(level, tmp_path):
    spec = parse_spec({"render": {"materials": "keep"}, "source": [
        {"kind": "scene", "name": "grey", "paths": [str(level / "hall.blend")], "materials": "untextured"},
        {"kind": "scene", "name": "kept", "paths": [str(level / "street.glb")]}]})
    jobs = expand(spec)
    assert {j.source: j.render["materials"] for j in jobs} == {"grey": "untextured", "kept": "keep"}
    from gbuffer_export.blender.dataset_job import render_config
    assert render_config(jobs[0], tmp_path / "c").materials == "untextured"
    with pytest.raises(SpecError, match=re.escape("materials 'grey'")) as e:
        _spec(level, materials="grey")
    assert "\n" not in str(e.value)


def _level_clip(root, cid: str, asset: str, split: str, cell, lo, hi) -> dict:
    """An index entry of a level clip with split regions and its manifest (only what the region check reads)."""
    import json

    from gbuffer_export.clip import SCHEMA, SCHEMA_VERSION
    cells = {"test": [[0, 0]], "train": [[1, 0]]}
    (root / "clips" / cid).mkdir(parents=True)
    (root / "clips" / cid / "manifest.json").write_text(json.dumps({
        "schema": SCHEMA, "schema_version": SCHEMA_VERSION, "scale": 4, "levels": {}, "buffers": [], "frames": [],
        "frame_data": {},
        "camera": {"region": {"lo": lo, "hi": hi, "grid": [2, 1], "cells": [cell]}}}))
    stem = asset.rsplit("/", 1)[-1].split(".")[0]
    return {"id": cid, "kind": "scene", "asset": asset, "split": split, "path": f"clips/{cid}",
            "scene_id": f"{stem}@cell{cell[0]}-{cell[1]}",
            "region": {"grid": [2, 1], "cell": cell, "split": split, "cells": cells}}


def test_a_level_file_in_other_coordinates_is_a_split_leak(tmp_path):
    """The dive arena's level.glb lies turned by 180 degrees against its level.blend (measured: box
    (-59.1, -49.3)..(44.8, 35.5) against (-44.8, -35.5)..(59.1, 49.3)): one layout, other places. The index check
    names the clip; files of a level in the same coordinates (garage.blend and garage.gltf) pass."""
    from gbuffer_export.dataset.check import region_errors
    blend = _level_clip(tmp_path, "a", "/l/level.blend", "test", [0, 0], [-44.8, -35.5], [59.1, 49.3])
    same = _level_clip(tmp_path, "b", "/l/level.gltf", "train", [1, 0], [-44.8, -35.5], [59.1, 49.3])
    turned = _level_clip(tmp_path, "c", "/l/level.glb", "train", [1, 0], [-59.1, -49.3], [44.8, 35.5])
    assert region_errors({"clips": [blend, same]}, tmp_path) == []
    errs = region_errors({"clips": [blend, same, turned]}, tmp_path)
    assert len(errs) == 1 and errs[0].startswith("clip c: the regions of level 'level' lie over the box "
                                                 "(-59.1, -49.3)..(44.8, 35.5), clip a's over (-44.8, -35.5)..")
    assert "other coordinates" in errs[0] and "\n" not in errs[0]
