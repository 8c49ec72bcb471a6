"""Issue 57 item 8: ColorVideoVDP per clip in ``evaluate`` and ``bench models`` (the ``video`` extra), and one line
naming the extra when it is missing."""
from __future__ import annotations

import json
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 5), hr_size=(64, 36), scale=4)


def test_missing_extra_is_one_line_naming_it(clip, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "pycvvdp", None)  # as if cvvdp were not installed
    out = tmp_path / "e.json"
    assert main(["evaluate", "--model", "bicubic", "--data", str(clip), "--json", str(out), "--no-flip",
                 "--cvvdp"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ColorVideoVDP" in err[0] and "[video]" in err[0], err
    assert not out.exists()
    assert main(["bench", "models", "--data", str(clip), "--models", "bicubic", "--cvvdp"]) == 2
    assert "[video]" in capsys.readouterr().err


def test_clip_video_scores_identical_frames_10_jod_and_flicker_lower():
    pytest.importorskip("pycvvdp", reason="cvvdp is not installed (the [video] extra)")
    from training.video_metric import ClipVideo, load_cvvdp
    metric = load_cvvdp()
    rng = np.random.default_rng(0)
    gt = [rng.random((36, 64, 3)).astype(np.float32) * 2 for _ in range(4)]
    scores = {}
    for name, change in (("same", lambda i, g: g), ("brighter", lambda i, g: g * 1.1),
                         ("flicker", lambda i, g: g + (0.3 if i % 2 else 0.0))):
        v = ClipVideo(24.0)
        for i, g in enumerate(gt):
            v.add(change(i, g), g)
        scores[name] = v.score(metric)
    assert scores["same"] == pytest.approx(10.0, abs=1e-4)
    assert 10.0 > scores["brighter"] > scores["flicker"] > 0, scores


def test_evaluate_and_bench_report_cvvdp_per_clip_with_the_display(clip, tmp_path, capsys):
    pytest.importorskip("pycvvdp", reason="cvvdp is not installed (the [video] extra)")
    out = tmp_path / "e.json"
    assert main(["evaluate", "--model", "demod-bilinear", "--data", str(clip), "--json", str(out), "--no-flip",
                 "--cvvdp"]) == 0
    res = json.loads(out.read_text())
    assert "standard_fhd" in res["cvvdp"]["display"] and "JOD" in res["cvvdp"]["unit"]
    (c,) = res["per_clip"]
    assert 0 < c["cvvdp"] <= 10 and res["mean"]["cvvdp"] == pytest.approx(c["cvvdp"])
    assert "ColorVideoVDP" in capsys.readouterr().out
    bench = tmp_path / "b"
    assert main(["bench", "models", "--data", str(clip), "--models", "bicubic,demod-bilinear", "--cvvdp",
                 "-o", str(bench)]) == 0
    rows = json.loads((bench / "bench_models.json").read_text())["rows"]
    assert [r["per_clip"][0]["cvvdp"] for r in rows] == [r["cvvdp"] for r in rows]
    assert rows[1]["cvvdp"] == pytest.approx(c["cvvdp"], abs=1e-3)
    assert rows[0]["cvvdp"] < rows[1]["cvvdp"]  # bicubic rings on HDR radiance; demod-bilinear does not
    assert "| cvvdp |" in (bench / "bench_models.md").read_text()
