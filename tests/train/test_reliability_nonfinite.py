"""Issue 26 item 9: NaN/Inf outside training. ``evaluate`` refuses a ground truth with NaN/Inf naming its file and
warns about (and counts) a model output with NaN; ``upscale`` writes no EXR with NaN pixels (0 there, a warning,
``upscale.json`` lists them)."""
from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.clip import buffer_path  # noqa: E402
from gbuffer_export.exr import read_exr, write_exr  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402



@pytest.fixture
def clip(tmp_path):
    return make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)


def _poison(clip, frame, level, value, n=5):
    p = buffer_path(clip, frame, level, "radiance")
    a = read_exr(p, ("R", "G", "B"))
    a[2, :n, 0] = value
    write_exr(p, {c: a[..., i] for i, c in enumerate("RGB")})
    return p


@pytest.mark.parametrize("value", [np.inf, np.nan])
def test_evaluate_refuses_a_non_finite_ground_truth_naming_its_file(clip, tmp_path, capsys, value):
    p = _poison(clip, 2, "hr", value)
    rc = main(["evaluate", "--model", "bilinear", "--data", str(clip), "--json", str(tmp_path / "e.json")])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    kind = "0 NaN, 5 Inf" if value == np.inf else "5 NaN, 0 Inf"
    assert err.splitlines()[-1] == (f"blendsr: error: {p}: frame 2 hr/radiance: 5 of 2304 pixel(s) non-finite "
                                    f"({kind}) [non-finite] (as 'blendsr validate' reports)")  # issue 43 item 8
    assert not (tmp_path / "e.json").exists()


def test_evaluate_warns_about_and_counts_a_non_finite_model_output(clip, tmp_path, capsys, caplog):
    """The library's evaluate_model on an LR input with NaN (the command refuses that input: issue 43 item 8)."""
    from training.evaluate import EvalOptions, evaluate_model
    from training.inference.loading import load_model
    p = _poison(clip, 2, "lr", np.nan)
    assert main(["evaluate", "--model", "bilinear", "--data", str(clip), "--json", str(tmp_path / "e.json")]) == 2
    assert f"{p}: frame 2 lr/radiance: 5 of 144 pixel(s) non-finite" in capsys.readouterr().err
    caplog.set_level("WARNING", logger="training")
    res = evaluate_model(load_model("bilinear", 4), [str(clip)], EvalOptions(flip=False, warmup=0))
    err = caplog.text
    assert "warning:" in err and "frame 2" in err and "non-finite" in err
    assert res["sr_nonfinite_frames"] == 1 and len(res["warnings"]) == 1
    rows = {r["frame"]: r for r in res["per_frame"]}
    assert rows[2]["sr_nonfinite"] > 0 and rows[1]["sr_nonfinite"] == 0


def test_upscale_writes_no_nan_pixels_and_says_so(clip, tmp_path, capsys):
    _poison(clip, 2, "lr", np.nan)
    out = tmp_path / "sr"
    assert main(["upscale", "--model", "bilinear", "--clip", str(clip), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "warning:" in err and "000002.exr" in err
    for f in (1, 2, 3):
        assert np.isfinite(read_exr(out / f"{f:06d}.exr", ("R", "G", "B"))).all()
    meta = json.loads((out / "upscale.json").read_text())
    assert set(meta["nonfinite_values"]) == {"2"}
