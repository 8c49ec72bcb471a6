"""benchmarks/worst_case.py --record: a shipped network's margin on a wider val set, written beside its weights,
marks it below demod-jbu (training.pretrained.val_margin takes the worst val set; a record of other weights is
ignored)."""
import importlib.util
import json
from pathlib import Path

import pytest

from tests.conftest import REPO


def _module():
    spec = importlib.util.spec_from_file_location("worst_case", REPO / "benchmarks" / "worst_case.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _clip(name, frames, psnr, base):
    return {"clip": name, "frames": frames, "psnr": psnr, "baseline_psnr": base, "margin": psnr - base}


def test_record_marks_a_network_below_the_baseline_on_the_wider_val(tmp_path, monkeypatch):
    from training import pretrained
    wc = _module()
    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", tmp_path)
    json_path = (tmp_path / pretrained.PRETRAINED["rdg-s"]).with_suffix(".json")
    scores = {"rdg-s": {"psnr": 30.5}, "demod-jbu": {"psnr": 30.2}}
    json_path.write_text(json.dumps({"model": "rdg-s", "sha256": "abc", "scores_on_val_split": scores}))
    assert not pretrained.below_baseline("rdg-s")
    # objects: 8 frames +1 dB; levels: 24 frames -1 dB -> frame-weighted -0.5 dB, smallest clip -1.5
    result = {"objects": {"models": {"pretrained:rdg-s": {"mean": {"margin": 1.0}, "sha256": "abc",
                                                          "per_clip": [_clip("a", 8, 31.0, 30.0)]}}, "notes": []},
              "levels": {"models": {"pretrained:rdg-s": {"mean": {"margin": -1.0}, "sha256": "abc",
                                                         "per_clip": [_clip("b", 16, 29.2, 30.0),
                                                                      _clip("c", 8, 28.5, 30.0)]}},
                         "notes": ["left out pretrained:nsrd: c lacks lr/motion_next, which it reads"]}}
    got = wc.overall(result, "pretrained:rdg-s")
    assert got["margin"] == pytest.approx((8 * 1.0 + 16 * -0.8 + 8 * -1.5) / 32, abs=1e-3)
    assert got["margin_min"] == pytest.approx(-1.5) and got["frames"] == 32 and got["left_out"] == []
    monkeypatch.setattr("gbuffer_export.dataset.build.read_index", lambda d: {"spec": {"file": "wide.toml"}})
    result["levels"]["models"]["pretrained:rdg-s"]["sha256"] = "older weights"  # one group scored other weights
    wc.record(result, [tmp_path], ["DS", "--split", "val", "--record"])
    assert pretrained.WORST_CASE_VAL not in json.loads(json_path.read_text())  # not recorded for these
    result["levels"]["models"]["pretrained:rdg-s"]["sha256"] = "abc"
    wc.record(result, [tmp_path], ["DS", "--split", "val", "--record"])
    doc = json.loads(json_path.read_text())
    assert doc[pretrained.WORST_CASE_VAL]["wide.toml val"]["sha256"] == "abc" and doc["scores_on_val_split"] == scores
    assert pretrained.val_margin("rdg-s") == pytest.approx(-1.0)  # the worst group: levels
    assert pretrained.below_baseline("rdg-s")
    assert pretrained.val_margins("rdg-s")["val split"] == pytest.approx(0.3)
    # a second val set (another spec) is recorded beside the first, which stays: the network is as good as its worst
    for g, m in (("objects", 2.0), ("levels", 1.0)):
        result[g]["models"]["pretrained:rdg-s"]["mean"]["margin"] = m
        result[g]["models"]["pretrained:rdg-s"]["per_clip"] = [_clip(g, 8, 30.0 + m, 30.0)]
    monkeypatch.setattr("gbuffer_export.dataset.build.read_index", lambda d: {"spec": {"file": "scale.toml"}})
    wc.record(result, [tmp_path], ["DS2", "--split", "val", "--record"])
    doc = json.loads(json_path.read_text())
    assert set(doc[pretrained.WORST_CASE_VAL]) == {"wide.toml val", "scale.toml val"}
    margins = pretrained.val_margins("rdg-s")
    assert margins["scale.toml val"] == pytest.approx(1.5) and margins["scale.toml val, levels"] == 1.0
    assert pretrained.val_margin("rdg-s") == pytest.approx(-1.0) and pretrained.below_baseline("rdg-s")
    wc.record(result, [tmp_path], ["DS2", "--split", "val", "--record"])  # recorded again: replaces its own only
    assert set(json.loads(json_path.read_text())[pretrained.WORST_CASE_VAL]) == {"wide.toml val", "scale.toml val"}
    flat = json.loads(json_path.read_text())  # a JSON of before 2026-11-30: one record, not keyed by its val set
    flat[pretrained.WORST_CASE_VAL] = flat[pretrained.WORST_CASE_VAL]["wide.toml val"]
    json_path.write_text(json.dumps(flat))
    assert pretrained.val_margins("rdg-s")["wide.toml val, levels"] == pytest.approx(-1.0)
    wc.record(result, [tmp_path], ["DS2", "--split", "val", "--record"])  # a record beside it: both keyed now
    assert set(json.loads(json_path.read_text())[pretrained.WORST_CASE_VAL]) == {"wide.toml val", "scale.toml val"}
    flat[pretrained.WORST_CASE_VAL] = ["not a record"]
    json_path.write_text(json.dumps(flat))
    assert pretrained.val_margins("rdg-s") == {"val split": pytest.approx(0.3)}
    doc["sha256"] = "new weights"  # retrained since: the record no longer speaks for them
    json_path.write_text(json.dumps(doc))
    assert not pretrained.below_baseline("rdg-s")
    with pytest.raises(SystemExit):
        wc.main(["DS", "--split", "test", "--record"])


def _val_split(tmp_path, monkeypatch, finished=("a", "b", "c")):
    """A dataset index planning val clips a, b (objects) and c (a level); ``finished`` of them rendered."""
    from gbuffer_export.dataset import build
    ds = tmp_path / "ds"
    ds.mkdir(parents=True)
    (ds / build.INDEX).write_text(json.dumps({
        "schema": build.SCHEMA, "schema_version": build.SCHEMA_VERSION, "name": "ds",
        "spec": {"file": "spec.toml", "sha256": "abc"},
        "clips": [{"id": n, "path": f"clips/{n}", "split": "val", "kind": "scene" if n == "c" else "asset"}
                  for n in "abc"]}))
    monkeypatch.setattr(build, "split_clips", lambda root, split, done_only=True: [
        Path(root) / "clips" / n for n in finished if split == "val"])
    return ds


def test_scores_of_several_runs_on_the_same_clips_merge_and_other_clips_are_refused(tmp_path, monkeypatch, capsys):
    """--scores A B: one table of both runs' models (the networks scored while others still trained, then those);
    files whose groups hold other clips, or not the whole split as it is now, or a shipped network's scores of other
    weights than those shipped now, are refused in one line naming the file; the record's command drops them."""
    from training import pretrained
    wc = _module()
    ds = str(_val_split(tmp_path, monkeypatch))
    row = {"mean": {"psnr": 30.0, "margin": 0.5, "margin_min": 0.1, "margin_min_clip": "a", "ssim": 0.9,
                    "tpsnr": 28.0, "artifact_fraction": 0.0, "worst_share": 0.3}, "per_clip": []}
    shipped = {n: {**row, "sha256": pretrained.info(n)["sha256"]} for n in ("rdg-s", "fusesr")}
    runs = {"a": {"objects": {"clips": ["a", "b"], "models": {"demod-jbu": row, "pretrained:rdg-s": shipped["rdg-s"]},
                              "notes": ["n1"]}},
            "b": {"objects": {"clips": ["a", "b"], "models": {"demod-jbu": row, "pretrained:fusesr": shipped["fusesr"]},
                              "notes": ["n1"]},
                  "levels": {"clips": ["c"], "models": {"pretrained:fusesr": shipped["fusesr"]}, "notes": []}},
            "other": {"objects": {"clips": ["a"], "models": {"demod-jbu": row}, "notes": []}},
            "old": {"objects": {"clips": ["a", "b"], "models": {"pretrained:rdg-s": {**row, "sha256": "0" * 64}},
                                "notes": []}},
            "unnamed": {"objects": {"clips": ["a", "b"], "models": {"pretrained:rdg-s": row}, "notes": []}}}
    for name, doc in runs.items():
        (tmp_path / f"{name}.json").write_text(json.dumps(doc))
    assert wc.main([ds, "--split", "val", "--scores", str(tmp_path / "a.json"), str(tmp_path / "b.json"),
                    "-o", str(tmp_path / "out")]) == 0
    got = json.loads((tmp_path / "out.json").read_text())
    assert list(got["objects"]["models"]) == ["demod-jbu", "pretrained:rdg-s", "pretrained:fusesr"]
    assert got["objects"]["notes"] == ["n1"] and list(got["levels"]["models"]) == ["pretrained:fusesr"]
    assert "`pretrained:rdg-s`" in capsys.readouterr().out
    assert wc.main([ds, "--split", "val", "--scores", str(tmp_path / "a.json"), str(tmp_path / "other.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "other.json: its objects clips differ" in err, err
    for name, says in (("old", "its pretrained:rdg-s row scored weights 000000000000, not the"),
                       ("unnamed", "its pretrained:rdg-s row scored weights it does not name (no sha256)")):
        assert wc.main([ds, "--split", "val", "--scores", str(tmp_path / f"{name}.json")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and f"{name}.json: {says}" in err and "score it again" in err, err
    assert wc.main([ds, "--split", "val", "--scores", str(tmp_path / "a.json")]) == 2  # no levels: not the split
    assert "their levels clips are not the whole val split" in capsys.readouterr().err
    ds = str(_val_split(tmp_path / "later", monkeypatch, finished="ab"))
    assert wc.main([ds, "--split", "val", "--scores", str(tmp_path / "a.json"), str(tmp_path / "b.json")]) == 2
    assert "1 of its 3 val clips are not finished" in capsys.readouterr().err  # scored or merged: a whole split
    assert wc.without_scores(["DS", "--scores", "x.json", "y.json", "--split", "val", "--scores=z.json",
                              "--record"]) == ["DS", "--split", "val", "--record"]
