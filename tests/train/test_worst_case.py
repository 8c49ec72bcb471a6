"""The worst case beside the means (docs/evaluation.md, "The worst case"): the per-clip margin over demod-jbu and
its minimum, the share of the squared error in the worst 1 % of pixels, artifact pixels; ``bench models`` leaves
out a model whose buffers a clip lacks. On synthetic clips, checked against direct computations."""
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)  # 2 threads on a shared 2-core machine can be 10x slower

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.conventions import ALL_BUFFERS  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training import metrics  # noqa: E402

pytestmark = pytest.mark.torch


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    root = tmp_path_factory.mktemp("wc")
    return [make_synthetic_clip(root / "a", frames=range(1, 4), hr_size=(64, 36), scale=4),
            make_synthetic_clip(root / "b", frames=range(1, 3), hr_size=(64, 36), scale=4, jitter=True)]


def test_worst_share_and_artifact_pixels_by_hand():
    sq = np.zeros((10, 20))
    sq[0, 0], sq[0, 1], sq[5, 5] = 6.0, 3.0, 1.0  # 200 pixels: the worst 1 % is the 2 largest
    assert metrics.worst_share(sq) == pytest.approx(0.9)
    assert metrics.worst_share(sq, 0.005) == pytest.approx(0.6)  # at least one pixel
    assert metrics.worst_share(np.zeros((4, 4))) is None
    gt = np.zeros((2, 3, 3), np.float32)
    sr = gt.copy()
    sr[0, 0] = [1.0, 0.0, 0.0]      # one channel off by T(1) = 0.735: the error is the largest channel's
    sr[0, 1] = [0.05, 0.05, 0.05]   # T(0.05) = 0.22: under the threshold
    sr[1, 2] = [1.0, 1.0, 1.0]
    err = metrics.pixel_error(sr, gt)
    assert err[0, 0] == pytest.approx(float(metrics.tonemapped(np.ones((1, 1, 3), np.float32))[0, 0, 0, 0]))
    assert err[0, 1] < metrics.ARTIFACT_ERROR < err[0, 0]
    base_ok = metrics.baseline_good(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.06]]))  # the baseline fails at (1, 2)
    assert metrics.artifact_mask(err, base_ok).tolist() == [[True, False, False], [False, False, False]]


def _per_frame_by_hand(spec, clip):
    """{frame: (PSNR, pixel error)} of ``spec`` on every frame of ``clip`` through the inference API."""
    from training.inference.loading import ClipFrames, load_model, upscale_frame
    model, src = load_model(spec, 4), ClipFrames(clip)
    out = {}
    for f in src.frames:
        r = upscale_frame(model, src, f)
        out[f] = (metrics.psnr_tm(r["sr"], r["reference"]), metrics.pixel_error(r["sr"], r["reference"]),
                  metrics.worst_share(metrics.squared_error(r["sr"], r["reference"])))
    return out


def test_evaluate_reports_margin_worst_share_and_artifact_pixels(clips):
    from training.evaluate import EvalOptions, evaluate_model
    from training.inference.loading import load_model
    res = evaluate_model(load_model("bicubic", 4), [str(c) for c in clips], EvalOptions(flip=False, warmup=0))
    assert res["worst_case"] == {"baseline": "demod-jbu", "worst_fraction": 0.01, "artifact_error": 0.25,
                                 "artifact_baseline_error": 0.05}
    margins = []
    n_art = pixels = 0
    for c, summary in zip(clips, res["per_clip"]):
        mine, base = _per_frame_by_hand("bicubic", c), _per_frame_by_hand("demod-jbu", c)
        margin = np.mean([mine[f][0] for f in mine]) - np.mean([base[f][0] for f in base])
        arts = sum(int(((mine[f][1] > 0.25) & (base[f][1] < 0.05)).sum()) for f in mine)
        assert summary["clip"] == str(c) and summary["frames"] == len(mine)
        assert summary["margin"] == pytest.approx(margin, abs=1e-6)
        assert summary["artifact_pixels"] == arts
        assert summary["worst_share"] == pytest.approx(np.mean([mine[f][2] for f in mine]), rel=1e-6)
        margins.append(margin)
        n_art += arts
        pixels += len(mine) * 64 * 36
    m = res["mean"]
    assert m["margin_min"] == pytest.approx(min(margins), abs=1e-6) and m["margin_min"] < 0  # bicubic loses
    assert m["margin_min_clip"] == str(clips[int(np.argmin(margins))])
    assert m["artifact_pixels"] == n_art > 0 and m["artifact_fraction"] == pytest.approx(n_art / pixels)
    assert 0.01 < m["worst_share"] < 1
    row = res["per_frame"][0]
    assert row["baseline_psnr"] == pytest.approx(_per_frame_by_hand("demod-jbu", clips[0])[1][0], abs=1e-9)
    # the baseline against itself: no margin, no artifact pixel
    same = evaluate_model(load_model("demod-jbu", 4), [str(clips[0])], EvalOptions(flip=False, warmup=0))
    assert same["mean"]["margin"] == 0 and same["mean"]["artifact_pixels"] == 0
    # without a baseline the worst share stays, the margin and artifact pixels are None
    off = evaluate_model(load_model("bicubic", 4), [str(clips[0])], EvalOptions(flip=False, warmup=0, baseline=None))
    assert off["mean"]["margin"] is None and off["mean"]["artifact_pixels"] is None
    assert off["mean"]["worst_share"] == pytest.approx(res["per_clip"][0]["worst_share"])


def test_evaluate_command_prints_and_writes_the_worst_case(clips, tmp_path, capsys):
    out = tmp_path / "e.json"
    assert main(["evaluate", "--model", "bilinear", "--data", str(clips[0]), "--json", str(out), "--no-flip",
                 "--warmup", "0", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    res = json.loads(out.read_text())
    assert "worst case: margin over demod-jbu" in printed and f"{res['mean']['margin_min']:+.2f} dB" in printed
    assert len(res["per_clip"]) == 1 and res["per_clip"][0]["margin"] == pytest.approx(res["mean"]["margin"])


def test_bench_models_leaves_out_a_model_whose_buffers_a_clip_lacks(clips, tmp_path):
    """pretrained:nsrd reads lr/motion_next: on a clip rendered without it the row is left out with a note."""
    import argparse

    from training import pretrained
    from training.commands import bench_models
    if not (pretrained.WEIGHTS_DIR / pretrained.PRETRAINED["nsrd"]).is_file():
        pytest.skip("pretrained:nsrd not shipped")
    clip = make_synthetic_clip(tmp_path / "no_next", frames=range(1, 3), hr_size=(64, 36), scale=4,
                               buffers=[b for b in ALL_BUFFERS if b != "motion_next"])
    p = argparse.ArgumentParser()
    bench_models.add_arguments(p)
    out = tmp_path / "b"
    assert bench_models.run(p.parse_args(["--data", str(clip), "--models", "pretrained:nsrd,bilinear,demod-jbu",
                                          "--warmup", "0", "--no-progress", "-o", str(out)])) == 0
    res = json.loads((out / "bench_models.json").read_text())
    assert [r["model"] for r in res["rows"]] == ["bilinear", "demod-jbu"]
    assert res["left_out"] == [f"left out pretrained:nsrd: {clip} lacks lr/motion_next, which it reads"]
    assert res["left_out"][0] in (out / "bench_models.md").read_text()
    bil, jbu = res["rows"]
    assert jbu["margin"] == 0 and jbu["artifact_fraction"] == 0
    assert bil["margin"] == pytest.approx(bil["psnr"] - jbu["psnr"], abs=1e-9) and bil["margin_min"] == bil["margin"]
    assert bil["margin_min_clip"] == str(clip) and [c["margin"] for c in bil["per_clip"]] == [bil["margin"]]
    with pytest.raises(ValueError, match="no model could be scored"):
        bench_models.run(p.parse_args(["--data", str(clip), "--models", "pretrained:nsrd", "--warmup", "0",
                                       "--no-progress"]))


def test_worst_case_refuses_an_unknown_model_in_one_line(tmp_path, capsys):
    import importlib.util

    from tests.conftest import REPO
    spec = importlib.util.spec_from_file_location("worst_case", REPO / "benchmarks" / "worst_case.py")
    wc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(wc)
    assert wc.main([str(tmp_path), "--split", "val", "--models", "demod-jbu,nope:x"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown model 'nope'" in err[0], err
    assert wc.main([str(tmp_path), "--split", "val", "--models", "demod-jbu"]) == 2  # not a dataset
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path) in err[0] and "not a BlendSR dataset" in err[0], err


def test_worst_case_loads_every_model_before_it_scores_any(clips, tmp_path, monkeypatch):
    """A missing checkpoint listed after other models used to fail only after they were scored (minutes on a real
    split); now every model loads first."""
    import importlib.util

    import training.evaluate
    from tests.conftest import REPO
    spec = importlib.util.spec_from_file_location("worst_case", REPO / "benchmarks" / "worst_case.py")
    wc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(wc)

    def never(*a, **k):
        raise AssertionError("a model was scored before every model loaded")
    monkeypatch.setattr(training.evaluate, "evaluate_model", never)
    missing = tmp_path / "run" / "checkpoints" / "last.pt"
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        wc.score([("demod-jbu", "demod-jbu"), ("fusesr-l (run)", str(missing))], {"objects": [str(c) for c in clips]})
