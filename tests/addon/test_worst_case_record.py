"""benchmarks/worst_case.py --record: a shipped network's margin on a wider val set, written beside its weights,
marks it below demod-jbu (training.pretrained.val_margin takes the worst val set; a record of other weights is
ignored)."""
import importlib.util
import json

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
    result = {"objects": {"models": {"pretrained:rdg-s": {"mean": {"margin": 1.0},
                                                          "per_clip": [_clip("a", 8, 31.0, 30.0)]}}, "notes": []},
              "levels": {"models": {"pretrained:rdg-s": {"mean": {"margin": -1.0},
                                                         "per_clip": [_clip("b", 16, 29.2, 30.0),
                                                                      _clip("c", 8, 28.5, 30.0)]}},
                         "notes": ["left out pretrained:nsrd: c lacks lr/motion_next, which it reads"]}}
    got = wc.overall(result, "pretrained:rdg-s")
    assert got["margin"] == pytest.approx((8 * 1.0 + 16 * -0.8 + 8 * -1.5) / 32, abs=1e-3)
    assert got["margin_min"] == pytest.approx(-1.5) and got["frames"] == 32 and got["left_out"] == []
    monkeypatch.setattr("gbuffer_export.dataset.build.read_index", lambda d: {"spec": {"file": "wide.toml"}})
    wc.record(result, [tmp_path], ["DS", "--split", "val", "--record"])
    doc = json.loads(json_path.read_text())
    assert doc[pretrained.WORST_CASE_VAL]["sha256"] == "abc" and doc["scores_on_val_split"] == scores
    assert pretrained.val_margin("rdg-s") == pytest.approx(-1.0)  # the worst group: levels
    assert pretrained.below_baseline("rdg-s")
    assert pretrained.val_margins("rdg-s")["val split"] == pytest.approx(0.3)
    doc["sha256"] = "new weights"  # retrained since: the record no longer speaks for them
    json_path.write_text(json.dumps(doc))
    assert not pretrained.below_baseline("rdg-s")
    with pytest.raises(SystemExit):
        wc.main(["DS", "--split", "test", "--record"])
