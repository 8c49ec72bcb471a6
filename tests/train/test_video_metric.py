"""Issue 57 item 8: ColorVideoVDP per clip in ``evaluate`` and ``bench models`` (the ``video`` extra), and one line
naming the extra when it is missing."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.extras import installed  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


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


def _needs_cvvdp():
    if not installed("pycvvdp"):
        pytest.skip("cvvdp is not installed (the [video] extra, part of [dev])")


def _untonemap(d: np.ndarray) -> np.ndarray:
    """Linear radiance whose evaluation tonemap (sRGB OETF of Reinhard) is ``d`` (display values in [0, 1))."""
    v = np.where(d <= 0.04045, d / 12.92, ((d + 0.055) / 1.055) ** 2.4)
    return (v / (1 - v)).astype(np.float32)


def test_identical_clip_scores_10_jod_and_a_brightness_flicker_far_below_a_steady_offset():
    """A still shot (a ramp, 12 frames at 24 fps): the ground truth scores 10 JOD; a result 0.04 brighter on every
    frame and one alternately 0.04 brighter and darker (every 2 frames: 6 Hz) have the same tonemapped error in every
    pixel of every frame, so the same per-frame PSNR; the flicker is what a viewer objects to, and the metric says
    so."""
    _needs_cvvdp()
    from training.metrics import psnr_tm
    from training.video_metric import ClipVideo, load_cvvdp
    metric = load_cvvdp()  # through the project's loader: torchvision without its C extension imports
    ramp = np.linspace(0.2, 0.8, 64, dtype=np.float32)
    gt_d = np.broadcast_to(ramp[None, :, None], (36, 64, 3))
    gt = _untonemap(gt_d)
    scores, psnrs = {}, {}
    for name, sign in (("same", lambda i: 0), ("steady", lambda i: 1), ("flicker", lambda i: (-1) ** (i // 2))):
        video = ClipVideo(24.0)
        for i in range(12):
            sr = _untonemap(gt_d + 0.04 * sign(i))
            video.add(sr, gt)
            psnrs.setdefault(name, []).append(psnr_tm(sr, gt))
        scores[name] = video.score(metric)
    assert scores["same"] == pytest.approx(10.0, abs=1e-4)
    assert np.ptp(psnrs["steady"] + psnrs["flicker"]) < 0.01, psnrs  # every frame ~28 dB in both
    assert 10.0 > scores["steady"] > 9.0 and scores["flicker"] < scores["steady"] - 3.0, scores


def test_cvvdp_loads_offline_in_a_fresh_process_and_torchvisions_operators_stay_absent(tmp_path):
    """A fresh interpreter with every socket refused: the metric loads (torchvision imported through the project's
    loader, its missing operators defined once, logged at debug level) and scores without any download; where
    torchvision's C extension does not load for this torch, calling its nms still raises (no kernel was made up)."""
    _needs_cvvdp()
    script = tmp_path / "offline.py"
    script.write_text("""
import json, logging, socket, sys
def refuse(*a, **k):
    raise OSError("network refused by the test")
socket.socket.connect = socket.socket.connect_ex = socket.create_connection = socket.getaddrinfo = refuse
records = []
handler = logging.Handler(); handler.emit = records.append
logging.getLogger("training.video_metric").addHandler(handler)
logging.getLogger("training.video_metric").setLevel(logging.DEBUG)
import numpy as np, torch
from training.video_metric import ClipVideo, load_cvvdp
metric = load_cvvdp(); load_cvvdp()
video = ClipVideo(24.0)
for i in range(3):
    g = np.full((16, 16, 3), 0.5 + 0.1 * i, np.float32)
    video.add(g, g)
import torchvision
try:
    torchvision.ops.nms(torch.rand(3, 4), torch.rand(3), 0.5)
    nms = "runs"
except RuntimeError as exc:
    nms = str(exc).splitlines()[0]
print(json.dumps({"jod": video.score(metric), "has_ops": torchvision.extension._has_ops(), "nms": nms,
                  "logged": [r.getMessage() for r in records]}))
""")
    env = {**os.environ, "PYTHONPATH": str(REPO), "HF_HUB_OFFLINE": "0"}  # a download would be tried, and refused
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["jod"] == pytest.approx(10.0, abs=1e-4)
    if out["has_ops"]:  # torchvision built for this torch: nothing defined, its nms works
        assert out["logged"] == [] and out["nms"] == "runs", out
    else:
        assert len(out["logged"]) == 1 and "does not load for torch" in out["logged"][0], out
        assert "Couldn't load custom C++ ops" in out["nms"], out


def test_evaluate_and_bench_report_cvvdp_per_clip_with_the_display(clip, tmp_path, capsys):
    _needs_cvvdp()
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
