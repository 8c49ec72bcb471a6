"""A level is never silently dropped (issue 55 item 3): ``validate`` of a dataset reports each source's share of
usable clips, and a source (a scene source's level) with none fails the dataset's quick validation, with every
clip's reason in one table. Synthetic clips, no render."""
from __future__ import annotations

import json
import shutil

import pytest

from gbuffer_export.dataset.check import source_of, validate_dataset
from gbuffer_export.synthetic import make_synthetic_clip
from tests.conftest import run_cli


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("good") / "clip", frames=(1, 2), hr_size=(16, 8), scale=2)


def _dataset(root, good, entries):
    """A dataset folder: entries with ``"done": True`` get a copy of the valid synthetic clip."""
    from gbuffer_export.dataset.build import INDEX, SCHEMA
    (root / "clips").mkdir(parents=True)
    rows = []
    for e in entries:
        e = dict(e)
        if e.pop("done", False):
            shutil.copytree(good, root / "clips" / e["id"])
        rows.append({"path": f"clips/{e['id']}", "split": "train", "frames_planned": 2,
                     "licence": {"licence": "CC0-1.0"}, **e})
    (root / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": 1, "name": "t", "seed": 0,
                                          "splits": {}, "clips": rows}))
    return root


CITY = "/levels/city/city.glb"
JUNGLE = "/levels/jungle/jungle.obj"


def test_each_source_gets_its_share_and_a_level_without_clips_fails_with_a_table(good, tmp_path):
    no_walk = "blendsr: error: lv-jungle-00: jungle.obj: no walk path meets the rules after 60 tries"
    ds = _dataset(tmp_path / "ds", good, [
        {"id": "lv-city-00", "source": "lv", "kind": "scene", "asset": CITY, "scene_id": "city", "done": True},
        {"id": "lv-city-01", "source": "lv", "kind": "scene", "asset": CITY, "scene_id": "city",
         "state": "failed", "error": "blendsr: error: lv-city-01: city.glb: no fly path meets the rules"},
        {"id": "lv-jungle-00", "source": "lv", "kind": "scene", "asset": JUNGLE, "scene_id": "jungle",
         "state": "failed", "error": no_walk},
        {"id": "lv-jungle-01", "source": "lv", "kind": "scene", "asset": JUNGLE, "scene_id": "jungle"},
    ])
    rep = validate_dataset(ds, quick=True, progress=False)
    assert not rep.ok
    assert rep.sources["lv/city"]["usable"] == 1 and rep.sources["lv/city"]["share"] == 0.5
    jungle = rep.sources["lv/jungle"]
    assert jungle["usable"] == 0 and jungle["clips"] == 2
    assert jungle["reasons"] == {"lv-jungle-00": f"failed: {no_walk}", "lv-jungle-01": "not rendered (pending)"}
    lines = rep.lines()
    assert "source lv/city: 1/2 clips usable (50%)" in lines and "source lv/jungle: 0/2 clips usable (0%)" in lines
    head = lines.index("ERROR dataset: 1 source(s) without a usable clip: lv/jungle (each clip's reason below)")
    table = lines[head + 1:]
    assert table[0].split() == ["source", "clip", "reason"] and len(table) == 3
    assert table[1].split()[:2] == ["lv/jungle", "lv-jungle-00"] and no_walk in table[1]
    assert rep.to_dict()["sources"]["lv/jungle"]["usable"] == 0
    proc = run_cli("validate", ds, "--quick", "--no-progress", timeout=120)
    assert proc.returncode == 1 and "lv/jungle" in proc.stdout and "without a usable clip" in proc.stdout


def test_a_dataset_whose_every_source_has_a_usable_clip_passes(good, tmp_path):
    ds = _dataset(tmp_path / "ds", good, [
        {"id": "lv-city-00", "source": "lv", "kind": "scene", "asset": CITY, "scene_id": "city", "done": True},
        {"id": "b-s0", "source": "builtin", "kind": "builtin", "scene_id": "s0", "done": True}])
    rep = validate_dataset(ds, quick=True, progress=False)
    assert rep.ok, rep.lines()
    assert {k: v["share"] for k, v in rep.sources.items()} == {"lv/city": 1.0, "builtin": 1.0}


def test_a_source_is_its_level_for_scene_files_and_its_name_otherwise():
    assert source_of({"source": "lv", "kind": "scene", "asset": "/x/garage.blend"}) == "lv/garage"
    assert source_of({"source": "gltf", "kind": "assets", "asset": "/x/Fox.glb"}) == "gltf"
