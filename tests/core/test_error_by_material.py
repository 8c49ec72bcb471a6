"""benchmarks/error_by_material.py: per group and material class, the pooled PSNR, gain and error share, checked
against the squared errors of hand-made frames summed directly."""
from __future__ import annotations

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
        rows.append({"clip": f"/data/clips/{clip}", "frame": f, "pixels": H * W, "materials": {
            k: {"fraction": v["fraction"], "err_share": v["err_share"],
                "psnr": -10 * math.log10(v["mse"]) if v["mse"] else None} for k, v in b.items()}})
    rows.append({"clip": "/data/clips/a", "frame": 3, "pixels": H * W, "materials": None})  # no breakdown: left out
    return {"model": model, "per_frame": rows}


def test_pooled_gain_and_share_match_direct_sums():
    fr = frames(0)
    base, model = ebm.pooled(result(fr, 0, "demod-jbu")), ebm.pooled(result(fr, 1, "m"))
    assert set(base) == {("a", 1), ("a", 2), ("b", 1), ("b", 2)}
    rows = ebm.group_rows({"a": ("objects", "held-out"), "b": ("objects",)}, base, [model])
    got = {(g, c): cells for g, c, cells in rows}
    for group, clips in (("objects (2 clips)", ("a", "b")), ("held-out (1 clips)", ("a",))):
        keys = [k for k in fr if k[0] in clips]
        total = sum(fr[k][2].sum() for k in keys)
        for c in MATERIALS:
            n = sum(fr[k][0][c].sum() for k in keys)
            if n == 0:
                assert (group, c) not in got
                continue
            sb, sm = (sum(fr[k][i][fr[k][0][c]].sum() for k in keys) for i in (1, 2))
            share, psnr_b, gain, err_share = got[(group, c)]
            assert share == pytest.approx(n / (len(keys) * H * W))
            assert psnr_b == pytest.approx(-10 * math.log10(sb / n))
            assert gain == pytest.approx(10 * math.log10(sb / sm))
            assert err_share == pytest.approx(sm / total)
    assert [g for g, _, _ in rows][0].startswith("objects")  # kinds first
    text = ebm.table(rows, ["m"], "demod-jbu")
    assert text.splitlines()[0].count("|") == 7 and len(text.splitlines()) == len(rows) + 2


def test_refuses_results_without_a_breakdown(tmp_path):
    (tmp_path / "b.json").write_text('{"model": "demod-jbu", "per_frame": [{"clip": "x", "frame": 1, "pixels": 4, '
                                     '"materials": null}]}')
    with pytest.raises(SystemExit, match="b.json: no frame has a material breakdown"):
        ebm.main([str(tmp_path), str(tmp_path / "b.json"), str(tmp_path / "b.json")])


def test_labels_must_name_every_model(tmp_path, capsys):
    import json
    fr = frames(1)
    for name, which in (("b", 0), ("m", 1)):
        (tmp_path / f"{name}.json").write_text(json.dumps(result(fr, which, name)))
    with pytest.raises(SystemExit):
        ebm.main([str(tmp_path), str(tmp_path / "b.json"), str(tmp_path / "m.json"), "--labels", "x,y"])
    assert "--labels names 2 models; 1 results follow" in capsys.readouterr().err
