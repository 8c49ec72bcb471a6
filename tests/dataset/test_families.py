"""Held-out families (gbuffer_export/dataset/families.py): the split rule, what each clip records, the gap report."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from gbuffer_export.dataset.build import check_folder
from gbuffer_export.dataset.families import BUILTIN_FAMILIES
from gbuffer_export.commands.family_gap import main
from gbuffer_export.dataset.family_gap import family_gap, gap_table, read_margins
from gbuffer_export.dataset.spec import SpecError, expand, parse_spec, plan_totals
from gbuffer_export.dataset.writer import spec_to_toml
from tests.conftest import shared_or_skip


def _spec(splits: dict, *sources, path="fam.toml"):
    return parse_spec({"render": {"frames": 2, "hr_size": "32x16"}, "splits": splits, "source": list(sources)},
                      path)


TRAIN = {"name": "tr", "kind": "builtin", "seeds": "0:3", "hdri": ["builtin:city", "builtin:forest"],
         "props": ["mat_wave", "railing"]}
TEST = {"name": "te", "kind": "builtin", "seeds": "10:11", "split": "test", "hdri": ["builtin:night"],
        "props": ["mat_voronoi", "railing"]}


def test_clips_record_their_families_and_group():
    jobs = {j.id: j for j in expand(_spec({"test_families": ["material:voronoi", "hdri:night"]}, TRAIN, TEST))}
    tr, te = jobs["tr-s0000"], jobs["te-s0010"]
    assert tr.split == "train" and tr.family_group == "in-family"
    assert set(tr.families) - {"material:wave", "geometry:railing"} in ({"hdri:city"}, {"hdri:forest"})
    assert te.families == ["geometry:railing", "hdri:night", "material:voronoi"] and te.family_group == "held-out"
    totals = plan_totals(list(jobs.values()))
    assert totals["all"] == {"clips": 6, "frames": 12, "hr_pixels": 12 * 32 * 16}
    assert totals["test held-out"]["clips"] == 2 and totals["train in-family"]["clips"] == 4


@pytest.mark.parametrize("fam, why", [
    ("material:wave", "props"),        # a prop family the train source adds
    ("hdri:forest", "pool"),           # in the train source's HDRI pool, drawn or not
    ("geometry:railing", "both")])     # in train and test sources alike
def test_a_train_clip_that_can_hold_a_held_out_family_is_refused(fam, why):
    with pytest.raises(SpecError, match=rf"fam.toml: source 'tr': clip tr-s0000 is in train but can hold "
                                        rf"'{fam}', a test family"):
        expand(_spec({"test_families": [fam]}, TRAIN, TEST))


def test_a_val_clip_may_not_hold_a_test_family_but_a_test_clip_may_hold_a_val_family():
    val = {**TEST, "name": "va", "split": "val", "seeds": "20:21"}
    with pytest.raises(SpecError, match="clip va-s0020 is in val but can hold 'hdri:night', a test family"):
        expand(_spec({"test_families": ["hdri:night"]}, val))
    jobs = expand(_spec({"val_families": ["hdri:night"]}, TEST))
    assert {j.family_group for j in jobs} == {"held-out"}


def test_bad_family_ids_and_families_held_by_no_clip():
    with pytest.raises(SpecError, match=r"splits.test_families item 'material:plaid': the built-in generator has "
                                        r"no such family: its material families are material:noise, "):
        _spec({"test_families": ["material:plaid"]}, TEST)
    with pytest.raises(SpecError, match="unknown kind 'colour'"):
        _spec({"val_families": ["colour:red"]}, TEST)
    with pytest.raises(SpecError, match="hdri:night listed in both val_families and test_families"):
        _spec({"val_families": ["hdri:night"], "test_families": ["hdri:night"]}, TEST)
    with pytest.raises(SpecError, match=r"splits.test_families: asset:SheenChiar held by no clip"):
        expand(_spec({"test_families": ["asset:SheenChiar"]}, TEST))


def test_camera_families_need_the_scene_camera():
    with pytest.raises(SpecError, match=r"source\[0\].props: the camera families \(cam_pan\) move the built-in"):
        _spec({}, {**TEST, "props": ["cam_pan"], "cameras": ["orbit"]})
    jobs = expand(_spec({}, {**TEST, "props": ["cam_pan"], "cameras": ["scene"]}))
    assert "camera:pan" in jobs[0].families


def test_asset_and_level_families_move_their_scenes_and_clutter_stays_inside_its_split():
    gltf = shared_or_skip("scenes/gltf")
    src = {"name": "obj", "kind": "assets", "paths": [str(gltf)], "clutter": 3, "hdri": ["builtin:studio"]}
    jobs = expand(_spec({"test_families": ["asset:SheenChair"], "val_families": ["asset:Fox"]}, src))
    split = {Path(j.asset).stem: j.split for j in jobs}
    assert split["SheenChair"] == "test" and split["Fox"] == "val"
    assert {s for k, s in split.items() if k not in ("SheenChair", "Fox")} == {"train"}
    for j in jobs:
        assert (j.family_group == "held-out") == (j.split != "train")
        assert all(split[Path(c).stem] == j.split for c in j.clutter)   # no held-out asset as train clutter
        assert f"asset:{Path(j.asset).stem}" in j.families
    with pytest.raises(SpecError, match="split = 'train' but holds 'SheenChair', whose family 'asset:SheenChair' "
                                        "is in"):
        expand(_spec({"test_families": ["asset:SheenChair"]}, {**src, "split": "train"}))


def test_a_held_out_level_may_not_be_split_by_regions():
    garage = shared_or_skip("scenes/levels/garage/garage.blend")
    src = {"name": "lv", "kind": "scene", "paths": [str(garage)], "clips_per_scene": 2, "cameras": ["walk"]}
    jobs = expand(_spec({"test_families": ["level:garage"]}, src))
    assert {(j.split, j.family_group) for j in jobs} == {("test", "held-out")}
    with pytest.raises(SpecError, match="level 'garage' is a test family .* but split by regions"):
        expand(_spec({"test_families": ["level:garage"]}, {**src, "regions": "2x2", "region_test": 1}))


def test_spec_writer_keeps_the_families_and_resume_ignores_them(tmp_path):
    import tomllib
    spec = _spec({"test_families": ["material:voronoi", "hdri:night"]}, TRAIN, TEST)
    again = parse_spec(tomllib.loads(spec_to_toml(spec)), "fam.toml")
    assert again.splits == spec.splits
    jobs = expand(spec)
    (tmp_path / "clips" / jobs[0].id).mkdir(parents=True)
    (tmp_path / "clips" / jobs[0].id / "manifest.json").write_text("{}")
    old = [{**{k: v for k, v in j.to_json().items() if k not in ("families", "family_group")},
            "path": f"clips/{j.id}"} for j in jobs]
    (tmp_path / "dataset.json").write_text(json.dumps({"schema": "blendsr-dataset", "schema_version": 1,
                                                       "name": spec.name, "seed": 0, "clips": old}))
    check_folder(tmp_path, spec, jobs)   # an index written before families: the same renders, no refusal
    old[0]["hdri"] = "builtin:sunset"    # ... while a changed render is still refused
    (tmp_path / "dataset.json").write_text(json.dumps({"schema": "blendsr-dataset", "schema_version": 1,
                                                       "name": spec.name, "seed": 0, "clips": old}))
    with pytest.raises(ValueError, match=r"clip tr-s0000 was rendered from a different spec \(hdri\)"):
        check_folder(tmp_path, spec, jobs)


def test_gap_report_from_worst_case_json(tmp_path, capsys):
    margins = {"objects": {"clips": [], "notes": [], "models": {"pretrained:fusesr": {"mean": {}, "per_clip": [
        {"clip": "/d/clips/a", "margin": 2.0}, {"clip": "/d/clips/b", "margin": 1.0},
        {"clip": "/d/clips/c", "margin": 0.5}, {"clip": "/d/clips/d", "margin": None}]}}}}
    (tmp_path / "m.json").write_text(json.dumps(margins))
    models = read_margins(tmp_path / "m.json")
    assert models == {"pretrained:fusesr": {"a": 2.0, "b": 1.0, "c": 0.5}}
    groups = {"a": "in-family", "b": "held-out", "c": "held-out"}
    g = family_gap(models["pretrained:fusesr"], groups)
    assert g["in-family"] == {"n": 1, "mean": 2.0, "min": 2.0} and g["held-out"]["mean"] == 0.75
    assert g["gap"] == pytest.approx(1.25)
    assert "| `pretrained:fusesr` | +2.00 (+2.00, 1) | +0.75 (+0.50, 2) | +1.25 |" in gap_table(models, groups)
    ds = tmp_path / "ds"
    (ds / "clips").mkdir(parents=True)
    (ds / "dataset.json").write_text(json.dumps({"schema": "blendsr-dataset", "schema_version": 1, "clips": [
        {"id": k, "path": f"clips/{k}", "split": "test", "family_group": v} for k, v in groups.items()]}))
    assert main([str(tmp_path / "m.json"), "--data", str(ds), "--json", str(tmp_path / "gap.json")]) == 0
    assert "+1.25 |" in capsys.readouterr().out
    record = json.loads((tmp_path / "gap.json").read_text())  # what the results page's `table` kind reads
    assert record["gap"]["rows"] == [["`pretrained:fusesr`", "+2.00 (+2.00, 1)", "+0.75 (+0.50, 2)", "+1.25"]]
    assert record["gap"]["columns"][0] == "model" and len(record["gap"]["columns"]) == 4
    (tmp_path / "bad.json").write_text("{}")
    assert main([str(tmp_path / "bad.json"), "--data", str(ds)]) == 2
    assert "bad.json: no per-clip margins" in capsys.readouterr().err


def test_evaluate_json_margins(tmp_path):
    (tmp_path / "e.json").write_text(json.dumps({"model": "fusesr-l", "per_clip": [{"clip": "x/c1", "margin": -0.3}]}))
    assert read_margins(tmp_path / "e.json") == {"fusesr-l": {"c1": -0.3}}


def test_builtin_family_names():
    assert len(BUILTIN_FAMILIES) == len(set(BUILTIN_FAMILIES))
    from gbuffer_export.dataset.families import BUILTIN_FAMILY_IDS
    assert len(set(BUILTIN_FAMILY_IDS)) == len(BUILTIN_FAMILY_IDS)


def test_the_scale_spec_plans_ten_times_the_wide_set_with_held_out_families():
    shared_or_skip("scenes/levels")
    from gbuffer_export.dataset.spec import load_spec
    from tests.conftest import REPO
    spec = load_spec(REPO / "examples" / "dataset_scale.toml")
    jobs = expand(spec)
    totals = plan_totals(jobs)
    assert totals["all"]["hr_pixels"] >= 215e6 and totals["all"]["hr_pixels"] >= 10 * 21.5e6
    for split in ("test", "val"):   # both groups in both splits: the gap can be measured
        assert totals[f"{split} held-out"]["clips"] >= 20 and totals[f"{split} in-family"]["clips"] >= 20
    train = {f for j in jobs if j.split == "train" for f in j.families}
    assert not train & set(spec.splits.test_families + spec.splits.val_families)
    kinds = {f.split(":")[0] for f in spec.splits.test_families}
    assert kinds >= {"asset", "level", "hdri", "material", "geometry", "light", "camera"}
    # chosen once (2026-11-28, before any clip was rendered) and never to change: another list is another dataset
    assert list(spec.splits.test_families) == [
        "asset:SheenChair", "asset:ClearcoatWicker", "asset:GlassBrokenWindow", "asset:IridescenceAbalone",
        "asset:Avocado", "asset:DamagedHelmet", "asset:TransmissionRoughnessTest", "level:steelribs",
        "hdri:empty_warehouse_01_1k", "hdri:sunrise", "material:voronoi", "geometry:foliage_cards", "light:neon",
        "camera:strafe"]
    assert list(spec.splits.val_families) == [
        "asset:IridescenceLamp", "asset:ClearCoatTest", "level:room", "hdri:forest_slope_1k", "material:brick",
        "geometry:text_panel", "light:small_emitters", "camera:turn"]
    assert {j.render["lr_spp"] for j in jobs} <= {4, 16, 32, 128} and {j.render["hr_spp"] for j in jobs} == {32}


def test_the_games_spec_holds_out_one_later_family_for_test_and_one_for_val_and_trains_on_the_rest():
    """``dataset_games.toml``: the scale set's held-out families, then ``geometry:instanced`` for test and
    ``geometry:displaced`` for val (chosen once, 2026-12-01, before any of their clips was rendered); every other
    family the scale set lacks is trained on and has in-family test and val clips."""
    shared_or_skip("scenes/levels")
    from gbuffer_export.dataset.spec import load_spec
    from tests.conftest import REPO
    scale = load_spec(REPO / "examples" / "dataset_scale.toml")
    spec = load_spec(REPO / "examples" / "dataset_games.toml")
    assert list(spec.splits.test_families) == [*scale.splits.test_families, "geometry:instanced"]
    assert list(spec.splits.val_families) == [*scale.splits.val_families, "geometry:displaced"]
    later = {"geometry:boolean", "light:fog", "motion:objects", "motion:character", "material:surfaces"}
    held = {}
    for j in expand(spec):
        for f in later & set(j.families):
            held.setdefault(f, set()).add((j.split, j.family_group))
    assert all(v >= {("train", "in-family"), ("test", "in-family"), ("val", "in-family")} for v in held.values()), held
    assert held.keys() == later


def test_a_network_trained_elsewhere_is_grouped_by_its_own_lineage(tmp_path, capsys):
    """A shipped network trained on another spec may have seen a held-out family of this dataset, and never seen an
    in-family one: with ``--seen-from`` its clips are grouped by its lineage (a weights JSON naming a spec and one of
    its train clips; the families as the spec expands them): in-family when it trained on every family of the clip."""
    from gbuffer_export.dataset.family_gap import index_families, lineage_families, lineage_groups
    spec = {"render": {"frames": 2, "hr_size": "32x16"},
            "source": [{"name": "b", "kind": "builtin", "seeds": "0:3", "split": "train"}]}
    (tmp_path / "s.toml").write_text(spec_to_toml(parse_spec(spec, tmp_path / "s.toml")))
    jobs = expand(parse_spec(spec, tmp_path / "s.toml"))
    fam = jobs[0].families[0]  # e.g. an HDRI family the network trained on
    ds = tmp_path / "ds"
    (ds / "clips").mkdir(parents=True)
    clips = [("a", "test", "in-family", [fam]),                     # in-family here, and seen by the network
             ("n", "test", "in-family", ["level:garage"]),          # in-family here, never seen by the network
             ("b", "test", "held-out", [fam]),                      # held out here, seen by the network
             ("c", "test", "held-out", [fam, "asset:Lamp"])]        # the lamp: unseen either way
    (ds / "dataset.json").write_text(json.dumps({"schema": "blendsr-dataset", "schema_version": 1, "clips": [
        {"id": k, "path": f"clips/{k}", "split": sp, "family_group": g, "families": f} for k, sp, g, f in clips]}))
    families = index_families(ds)
    assert families["c"] == {fam, "asset:Lamp"}
    assert lineage_groups(families, {fam}) == {"a": "in-family", "n": "held-out", "b": "in-family", "c": "held-out"}
    (tmp_path / "w.json").write_text(json.dumps({"dataset": {"spec_file": "s.toml", "train_clips": [jobs[0].id]},
                                                 "init_from": {"weights": "x", "commands": ["INIT='pretrained:<M>'"]}}))
    trained, notes = lineage_families(tmp_path / "w.json", tmp_path)
    assert trained == set(jobs[0].families) and len(notes) == 1 and "is not recorded" in notes[0]
    (tmp_path / "w2.json").write_text(json.dumps({"dataset": {"spec_file": "s.toml", "train_clips": ["gone"]},
                                                  "init_from": {"commands": ['SPEC="s.toml" pretrain.sh']}}))
    trained, notes = lineage_families(tmp_path / "w2.json", tmp_path)
    assert trained == {f for j in jobs for f in j.families} and "1 train clip(s) not in s.toml" in notes[0]
    margins = {"m": {"models": {"pretrained:m": {"mean": {}, "per_clip": [
        {"clip": "a", "margin": 3.0}, {"clip": "n", "margin": 1.0}, {"clip": "b", "margin": 4.0},
        {"clip": "c", "margin": 2.0}]}}}}
    (tmp_path / "m.json").write_text(json.dumps(margins))
    assert main([str(tmp_path / "m.json"), "--data", str(ds), "--repo", str(tmp_path),
                 "--seen-from", f"pretrained:m={tmp_path / 'w.json'}"]) == 0
    out = capsys.readouterr().out
    assert "| `pretrained:m` (by its training lineage) | +3.50 (+3.00, 2) | +1.50 (+1.00, 2) | +2.00 |" in out
    assert main([str(tmp_path / "m.json"), "--data", str(ds)]) == 0  # without it: the dataset's groups
    assert "| `pretrained:m` | +2.00 (+1.00, 2) | +3.00 (+2.00, 2) | -1.00 |" in capsys.readouterr().out
    assert main([str(tmp_path / "m.json"), "--data", str(ds), "--seen-from", "nope=w.json"]) == 2
    assert "--seen-from 'nope=w.json': expected LABEL=WEIGHTS.json" in capsys.readouterr().err
    for bad, says in ((f"{tmp_path}/x.json", "x.json: no training lineage"),):
        assert main([str(tmp_path / "m.json"), "--data", str(ds), "--seen-from", f"pretrained:m={bad}"]) == 2
        assert says in capsys.readouterr().err
    (tmp_path / "w3.json").write_text(json.dumps({"dataset": {"spec_file": 123, "train_clips": None}}))
    assert main([str(tmp_path / "m.json"), "--data", str(ds), "--seen-from", f"pretrained:m={tmp_path}/w3.json"]) == 2
    assert "w3.json: no training lineage" in capsys.readouterr().err
    (tmp_path / "w4.json").write_text(json.dumps({"dataset": {"spec_file": "missing.toml", "train_clips": []}}))
    assert main([str(tmp_path / "m.json"), "--data", str(ds), "--repo", str(tmp_path),
                 "--seen-from", f"pretrained:m={tmp_path}/w4.json"]) == 2
    line, = capsys.readouterr().err.strip().splitlines()
    assert "w4.json: its spec missing.toml" in line


def test_the_lineage_of_a_fine_tune_reaches_every_recorded_stage():
    """A fine-tune's JSON keeps the shipped JSON it started from with that JSON's own dataset and init_from
    (release_weights.shipped_origin): every stage is read, newest first; an older JSON's init stage comes from the
    SPEC= of its commands, and a stage beyond what is recorded is said."""
    from gbuffer_export.dataset.family_gap import lineage_stages
    old = {"weights": "w", "commands": ["SPEC=examples/dataset_large.toml INIT='pretrained:<M>' pretrain.sh"]}
    wide = {"weights": "pretrained:m as shipped", "dataset": {"spec_file": "wide.toml", "train_clips": ["a"]},
            "init_from": old}
    doc = {"dataset": {"spec_file": "scale.toml", "train_clips": ["s1", "s2"]}, "init_from": wide}
    stages, notes = lineage_stages(doc, "m.json")
    assert stages == [("scale.toml", {"s1", "s2"}), ("wide.toml", {"a"}), ("examples/dataset_large.toml", None)]
    assert len(notes) == 1 and "a stage before 'w' is not recorded" in notes[0]
    stages, notes = lineage_stages({"dataset": {"spec_file": "s.toml", "train_clips": []}}, "m.json")
    assert stages == [("s.toml", set())] and notes == []
    # a stage that started from shipped weights without recording them is said, at the top or nested
    tuned = ['blendsr train --model m --set run.init_from="pretrained:m"']
    _, notes = lineage_stages({"dataset": {"spec_file": "s.toml", "train_clips": []}, "commands": tuned}, "m.json")
    assert len(notes) == 1 and "its last stage started from shipped weights that it does not record" in notes[0]
    scored = ["blendsr train --model m", "blendsr evaluate --checkpoint pretrained:m"]  # from scratch, then scored
    _, notes = lineage_stages({"dataset": {"spec_file": "s.toml", "train_clips": []}, "commands": scored}, "m.json")
    assert notes == []
    zoo = {"weights": "z", "commands": tuned, "dataset": {"spec_file": "zoo.toml", "train_clips": ["z1"]}}
    stages, notes = lineage_stages({**doc, "init_from": {**wide, "init_from": zoo}}, "m.json")
    assert stages[-1] == ("zoo.toml", {"z1"}) and len(notes) == 1 and "'z' started from shipped weights" in notes[0]


def test_networks_of_different_training_compare_on_the_clips_none_of_them_saw():
    """``--unseen-by-all``: the held-out clips that every --seen-from lineage holds out too; each model's mean and
    smallest margin there, n/a for a model not scored on all of them."""
    from gbuffer_export.dataset.family_gap import unseen_by_all, unseen_table
    groups = {"a": "in-family", "r": "held-out", "x": "held-out", "y": "held-out"}
    own = {"shipped": {"a": "in-family", "r": "in-family", "x": "held-out", "y": "held-out"},
           "fine-tune": {"a": "in-family", "r": "in-family", "x": "in-family", "y": "held-out"}}
    assert unseen_by_all(groups, own) == {"y"}
    assert unseen_by_all(groups, {}) == {"r", "x", "y"}
    table = unseen_table({"m": {"x": 1.0, "y": 3.0}, "short": {"x": 1.0}}, {"x", "y"})
    assert "| `m` | +2.00 (+1.00) |" in table and "| `short` | n/a (clips missing) |" in table
    assert "margin on the 2 clips no network trained on" in table


def test_the_kind_matched_gap_compares_each_held_out_clip_with_in_family_clips_of_its_own_kind(tmp_path, capsys):
    """Levels score higher margins than objects; a split whose held-out clips are mostly objects has a plain gap
    from the mix alone. Here no clip gains from being in-family within its kind: the plain gap is large, every
    per-kind gap and the matched one are zero; then a per-kind gap, weighted by the held-out clips of each kind."""
    from gbuffer_export.dataset.family_gap import kind_gap, kind_table
    kinds = {"o1": "objects", "o2": "objects", "o3": "objects", "o4": "objects", "l1": "levels", "l2": "levels",
             "l3": "levels"}
    groups = {"o1": "in-family", "l1": "in-family", "l2": "in-family",
              "o2": "held-out", "o3": "held-out", "o4": "held-out", "l3": "held-out"}
    margins = {c: (3.0 if k == "levels" else 1.0) for c, k in kinds.items()}
    assert family_gap(margins, groups)["gap"] == pytest.approx((1 + 3 + 3) / 3 - (1 + 1 + 1 + 3) / 4)  # 0.83
    g = kind_gap(margins, groups, kinds)
    assert g["objects"]["gap"] == g["levels"]["gap"] == g["matched"] == 0.0
    margins.update(o1=2.0, l1=3.5, l2=3.5)  # in-family objects +1.0 above held-out ones, levels +0.5
    g = kind_gap(margins, groups, kinds)
    assert g["objects"]["gap"] == pytest.approx(1.0) and g["levels"]["gap"] == pytest.approx(0.5)
    assert g["matched"] == pytest.approx((1.0 * 3 + 0.5 * 1) / 4)
    assert kind_gap({"o1": 2.0, "o2": 1.0, "l3": 9.0}, groups, kinds)["matched"] == 1.0  # no in-family level
    row = kind_table({"m": margins}, groups, kinds).splitlines()[2]
    assert row == ("| `m` | +2.00 / +1.00 (1 / 3) | +1.00 | +3.50 / +3.00 (2 / 1) | +0.50 "
                   "| +0.88 (4 of 4 held-out) |"), row
    own = {"m": {c: "held-out" for c in kinds}}  # a lineage that saw none of them: nothing to match within a kind
    row = kind_table({"m": {**margins, "zz": 1.0}}, groups, kinds, own).splitlines()[2:]
    assert row[0].startswith("| `m` (by its training lineage) | n/a / +") and row[0].endswith("| n/a (0 of 7 held-out) |")
    assert row[1] == "| `m` | 1 clips not in the datasets' indexes | | | | |"
    ds = tmp_path / "ds"
    (ds / "clips").mkdir(parents=True)
    unseen = {"o2": "asset:new", "l3": "level:new"}  # an asset and a level no train clip (o1: asset:seen) shows
    (ds / "dataset.json").write_text(json.dumps({"schema": "blendsr-dataset", "schema_version": 1, "clips": [
        {"id": c, "path": f"clips/{c}", "split": "train" if c == "o1" else "test", "family_group": groups[c],
         "kind": "scene" if k == "levels" else "asset", "families": [unseen.get(c, "asset:seen"), "hdri:x"]}
        for c, k in kinds.items()]}))
    (tmp_path / "e.json").write_text(json.dumps({"model": "m", "per_clip": [
        {"clip": f"x/{c}", "margin": m} for c, m in margins.items()]}))
    assert main([str(tmp_path / "e.json"), "--data", str(ds), "--by-kind"]) == 0
    out = capsys.readouterr().out
    assert "| +0.50 | +0.88 (4 of 4 held-out) |" in out
    # the held-out clips of an asset (o2, margin 1.0) or a level (l3, 3.0) no train clip shows, apart
    assert out.rstrip().endswith("| `m` | +1.00 (+1.00, 1) | +3.00 (+3.00, 1) |"), out
    from gbuffer_export.dataset.family_gap import content_groups, content_table
    families = {c: {unseen.get(c, "asset:seen"), "hdri:x"} for c in kinds}
    lineage = content_groups(families, {c: "held-out" for c in kinds}, {"asset:seen", "asset:new", "hdri:x"})
    assert lineage == {"l3": ("held-out level",)}  # a lineage that trained on asset:new: only the level is unseen
    assert content_table({"m": margins}, {"m": lineage}).splitlines()[2] == "| `m` | n/a (0) | +3.00 (+3.00, 1) |"
    text = (ds / "dataset.json").read_text()
    (ds / "dataset.json").write_text(text.replace("asset:new", "asset:seen").replace("level:new", "asset:seen"))
    assert main([str(tmp_path / "e.json"), "--data", str(ds), "--by-kind"]) == 0
    assert "never trained on" not in capsys.readouterr().out  # no clip shows unseen content: no table
