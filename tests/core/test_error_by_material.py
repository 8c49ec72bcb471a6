"""benchmarks/error_by_material.py: per group and material class, the pooled PSNR, gain and error share, checked
against the squared errors of hand-made frames summed directly."""
from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest

from gbuffer_export.conventions import Flag
from gbuffer_export.regions import MATERIALS, error_breakdown, material_regions
from tests.conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
import error_by_material as ebm  # noqa: E402

H, W = 6, 8


def frames(seed: int):
    """{(clip, frame): (masks, squared error of the baseline, of the model)} for two clips of two frames."""
    rng = np.random.default_rng(seed)
    out = {}
    for clip in ("a", "b"):
        for f in (1, 2):
            flags = rng.choice(np.array([0, Flag.BACKGROUND, Flag.COAT, Flag.TRANSMISSION], np.uint32), (H, W))
            masks = material_regions(flags, rng.random((H, W)))
            out[(clip, f)] = (masks, rng.random((H, W)) * 0.01, rng.random((H, W)) * 0.004)
    return out


def result(fr: dict, which: int, model: str) -> dict:
    """An evaluate result's per-frame rows as ``blendsr evaluate`` writes them (PSNR from the mean squared error)."""
    rows = []
    for (clip, f), (masks, *sq) in fr.items():
        b = error_breakdown(sq[which], masks)
        rows.append({"clip": f"/data/clips/{clip}", "frame": f, "scale": 4.0, "pixels": H * W, "materials": {
            k: {"fraction": v["fraction"], "err_share": v["err_share"],
                "psnr": -10 * math.log10(v["mse"]) if v["mse"] else None} for k, v in b.items()}})
    rows.append({"clip": "/data/clips/a", "frame": 3, "scale": 4.0, "pixels": H * W, "materials": None})  # left out
    return {"model": model, "per_frame": rows}


def test_pooled_gain_and_share_match_direct_sums(capsys):
    fr = frames(0)
    b_doc, m_doc = result(fr, 0, "demod-jbu"), result(fr, 1, "m")
    m_doc["per_frame"] = [r for r in m_doc["per_frame"] if (r["clip"], r["frame"]) != ("/data/clips/b", 2)]
    base, model = ebm.pooled(b_doc, "b.json"), ebm.pooled(m_doc, "m.json")
    assert set(base) == {("a", 4.0, 1), ("a", 4.0, 2), ("b", 4.0, 1), ("b", 4.0, 2)}
    keys = ebm.common_frames(base, [model], ["b.json", "m.json"])
    assert "b.json: 1 of its 4 frames are not in every result" in capsys.readouterr().err
    del fr[("b", 2)]  # what every result has in common
    rows = ebm.group_rows({"a": ("objects", "held-out"), "b": ("objects",)}, base, [model], keys)
    got = {(g, c): cells for g, c, cells in rows}
    assert any(not m[0][c].any() for m in fr.values() for c in MATERIALS)  # a class empty in some frame: psnr None
    for group, clips in (("objects (2 clips)", ("a", "b")), ("held-out (1 clips)", ("a",))):
        keys = [k for k in fr if k[0] in clips]
        totals = [sum(fr[k][i].sum() for k in keys) for i in (1, 2)]
        for c in MATERIALS:
            n = sum(fr[k][0][c].sum() for k in keys)
            if n == 0:
                assert (group, c) not in got
                continue
            sb, sm = (sum(fr[k][i][fr[k][0][c]].sum() for k in keys) for i in (1, 2))
            share, psnr_b, share_b, gain, err_share = got[(group, c)]
            assert share == pytest.approx(n / (len(keys) * H * W))
            assert psnr_b == pytest.approx(-10 * math.log10(sb / n))
            assert share_b == pytest.approx(sb / totals[0])
            assert gain == pytest.approx(10 * math.log10(sb / sm))
            assert err_share == pytest.approx(sm / totals[1])
    assert [g for g, _, _ in rows][0].startswith("objects")  # kinds first
    text = ebm.table(rows, ["m"], "demod-jbu")
    assert text.splitlines()[0].count("|") == 8 and len(text.splitlines()) == len(rows) + 2


def test_a_frame_at_two_scales_is_two_frames_and_twice_one_is_refused():
    fr = frames(2)
    doc = result(fr, 0, "bilinear")
    x2 = [dict(r, scale=2.0) for r in doc["per_frame"]]
    assert len(ebm.pooled({"per_frame": doc["per_frame"] + x2}, "r.json")) == 2 * len(fr)
    with pytest.raises(SystemExit, match="r.json: frame 1 of a at scale 4 is scored twice"):
        ebm.pooled({"per_frame": doc["per_frame"] + doc["per_frame"][:1]}, "r.json")
    with pytest.raises(SystemExit, match="w.json: not a blendsr evaluate result"):
        ebm.pooled({"objects": {}}, "w.json")
    base = ebm.pooled(doc, "b.json")
    other = {k: {("sky" if c == "background" else c): v for c, v in cls.items()} for k, cls in base.items()}
    with pytest.raises(SystemExit, match="m.json: frame .* has classes"):
        ebm.common_frames(base, [other], ["b.json", "m.json"])
    with pytest.raises(SystemExit, match="m.json: no frame in common with b.json"):
        ebm.common_frames(base, [{}], ["b.json", "m.json"])


def test_refuses_results_without_a_breakdown(tmp_path):
    (tmp_path / "b.json").write_text('{"model": "demod-jbu", "per_frame": [{"clip": "x", "frame": 1, "pixels": 4, '
                                     '"scale": 4, "materials": null}]}')
    (tmp_path / "m.json").write_text(json.dumps(result(frames(0), 1, "m")))
    with pytest.raises(SystemExit, match="b.json: no frame has a material breakdown"):
        ebm.main([str(tmp_path), str(tmp_path / "b.json"), str(tmp_path / "m.json")])
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(SystemExit, match="bad.json: cannot read a JSON result"):
        ebm.main([str(tmp_path), str(tmp_path / "bad.json"), str(tmp_path / "m.json")])


def test_labels_must_name_every_model(tmp_path, capsys):
    fr = frames(1)
    for name, which in (("b", 0), ("m", 1)):
        (tmp_path / f"{name}.json").write_text(json.dumps(result(fr, which, name)))
    with pytest.raises(SystemExit):
        ebm.main([str(tmp_path), str(tmp_path / "b.json"), str(tmp_path / "m.json"), "--labels", "x,y"])
    assert "--labels names 2 models; 1 results follow" in capsys.readouterr().err
