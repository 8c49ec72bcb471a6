"""Evaluation, inference API, upscale, ONNX export and the model benchmark, checked against direct computations."""
import json

import colour
import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)  # 2 threads on a shared 2-core machine can be 10x slower

from gbuffer_export import demod as np_demod  # noqa: E402
from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.clip import open_clip  # noqa: E402
from gbuffer_export.conventions import backward_warp  # noqa: E402
from gbuffer_export.exr import read_exr  # noqa: E402
from gbuffer_export.regions import material_regions, pixel_regions  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training.config import load_config  # noqa: E402
from training.models import MODELS  # noqa: E402



@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 5), hr_size=(64, 36), scale=4)


@pytest.fixture(scope="module")
def checkpoint(clip, tmp_path_factory):
    from training.train import train
    cfg = load_config(None, ["model.name=\"fusesr-l\"", "data.crop=8", "data.batch_size=2", "run.max_steps=1",
                             "run.progress=false", "model.width=16", "model.blocks=1"])
    cfg.data.clips = [str(clip)]
    run = tmp_path_factory.mktemp("run")
    train(cfg, run)
    return run / "checkpoints" / "last.pt"


# Independent reference: the tonemap (sRGB encoding from colour-science) and PSNR written out here in numpy.
def tm(x):
    x = np.maximum(x.astype(np.float64), 0)
    return colour.cctf_encoding(x / (1 + x), function="sRGB")


def psnr(a, b, peak=1.0):
    return 10 * np.log10(peak ** 2 / np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))


def bicubic_np(lr):
    t = torch.from_numpy(lr.transpose(2, 0, 1))[None]
    up = torch.nn.functional.interpolate(t, scale_factor=4, mode="bicubic", align_corners=False).clamp(min=0)
    return up[0].numpy().transpose(1, 2, 0)


def test_evaluate_json_matches_direct_computation(clip, tmp_path):
    from pytorch_msssim import ssim
    out = tmp_path / "bicubic.json"
    assert main(["evaluate", "--model", "bicubic", "--data", str(clip), "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert {"model", "transform", "device", "mean", "per_frame"} <= set(res)
    assert res["model"] == "bicubic" and "cpu" in res["device"] and "reinhard" in res["transform"]
    keys = {"psnr", "ssim", "psnr_hdr", "flip", "tpsnr", "warp_error", "ms_per_frame"}
    assert keys <= set(res["mean"])
    assert [r["frame"] for r in res["per_frame"]] == [1, 2, 3, 4]
    c = open_clip(clip)
    prev = None
    for row in res["per_frame"]:
        assert keys | {"clip", "frame"} <= set(row)
        f = row["frame"]
        gt = c.read(f, "hr/radiance")
        sr = bicubic_np(c.read(f, "lr/radiance"))
        assert row["psnr"] == pytest.approx(psnr(tm(sr), tm(gt)), abs=1e-3)
        assert row["psnr_hdr"] == pytest.approx(psnr(sr, gt), abs=1e-3)
        a = torch.from_numpy(tm(sr).astype(np.float32).transpose(2, 0, 1))[None]
        b = torch.from_numpy(tm(gt).astype(np.float32).transpose(2, 0, 1))[None]
        assert row["ssim"] == pytest.approx(float(ssim(a, b, data_range=1.0)), abs=1e-4)
        assert 0 < row["flip"] < 1 and row["ms_per_frame"] > 0
        regions = pixel_regions(c.read(f, "hr/flags"), c.read(f, "hr/depth"))
        sq = ((tm(sr) - tm(gt)) ** 2).mean(-1)
        assert sum(v["fraction"] for v in row["regions"].values()) == pytest.approx(1.0)
        for name, m in regions.items():
            assert row["regions"][name]["fraction"] == pytest.approx(m.mean())
            assert row["regions"][name]["err_share"] == pytest.approx(sq[m].sum() / sq.sum(), abs=1e-4)
            assert row["regions"][name]["psnr"] == pytest.approx(psnr(tm(sr)[m], tm(gt)[m]), abs=1e-3)
        materials = material_regions(c.read(f, "hr/flags"), c.read(f, "hr/roughness"))
        assert materials["background"].any() and materials["rough"].any()  # the synthetic clip: sky and roughness 0.5
        for name, m in materials.items():
            assert row["materials"][name]["fraction"] == pytest.approx(m.mean())
            if m.any():
                assert row["materials"][name]["psnr"] == pytest.approx(psnr(tm(sr)[m], tm(gt)[m]), abs=1e-3)
            else:
                assert row["materials"][name]["psnr"] is None and row["materials"][name]["err_share"] == 0
        if prev is None:
            assert row["tpsnr"] is None and row["warp_error"] is None
        else:
            psr, pgt = prev
            assert row["tpsnr"] == pytest.approx(psnr(tm(sr) - tm(psr), tm(gt) - tm(pgt)), abs=1e-3)
            w, v = backward_warp(tm(psr), c.read(f, "hr/motion").astype(np.float64))
            assert row["warp_error"] == pytest.approx(np.abs(tm(sr) - w)[v].mean(), rel=1e-4)
        prev = (sr, gt)
    assert res["mean"]["psnr"] == pytest.approx(np.mean([r["psnr"] for r in res["per_frame"]]))
    assert res["mean"]["regions"]["silhouette"]["psnr"] == \
        pytest.approx(np.mean([r["regions"]["silhouette"]["psnr"] for r in res["per_frame"]]))
    assert res["mean"]["materials"]["rough"]["psnr"] == \
        pytest.approx(np.mean([r["materials"]["rough"]["psnr"] for r in res["per_frame"]]))
    assert res["mean"]["ms_per_frame"] == pytest.approx(np.median([r["ms_per_frame"] for r in res["per_frame"]]))


def test_delta_e_itp_is_optional_and_scored_per_frame(clip, tmp_path):
    from training.metrics import delta_e_itp
    out = tmp_path / "itp.json"
    assert main(["evaluate", "--model", "bicubic", "--data", str(clip), "--json", str(out), "--no-flip",
                 "--frames", "2:3", "--delta-e-itp"]) == 0
    res = json.loads(out.read_text())
    assert res["itp_white_nits"] == 203.0
    c = open_clip(clip)
    for row in res["per_frame"]:
        sr = bicubic_np(c.read(row["frame"], "lr/radiance"))
        assert row["delta_e_itp"] == pytest.approx(delta_e_itp(sr, c.read(row["frame"], "hr/radiance")), rel=1e-3)
    assert res["mean"]["delta_e_itp"] == pytest.approx(np.mean([r["delta_e_itp"] for r in res["per_frame"]]))
    assert main(["evaluate", "--model", "bicubic", "--data", str(clip), "--json", str(out), "--no-flip",
                 "--frames", "2:2"]) == 0
    res = json.loads(out.read_text())
    assert res["mean"]["delta_e_itp"] is None and res["itp_white_nits"] is None


def test_flip_matches_the_evaluator_and_survives_its_exit():
    import flip_evaluator
    from training.flip_worker import FlipRunner
    rng = np.random.default_rng(0)
    ref = (rng.random((36, 64, 3)) * 2).astype(np.float32)
    test = ref * 1.1
    runner = FlipRunner()
    try:
        direct = flip_evaluator.evaluate(ref, test, "HDR", applyMagma=False)[1]
        assert runner(ref, test) == pytest.approx(direct, rel=1e-6)
        assert runner(np.zeros_like(ref), test) is None  # all-black reference: guarded
        tiny = np.full_like(ref, 1e-9)  # makes flip-evaluator call exit() (collapsed exposure range)
        assert runner(tiny, tiny) is None and "flip-evaluator exited" in runner.failures
        assert runner(ref, test) == pytest.approx(direct, rel=1e-6)  # a fresh worker takes over
    finally:
        runner.close()


def test_demod_bilinear_beats_bilinear_on_the_exactly_diffuse_clip(clip, tmp_path):
    res = {}
    for m in ("bilinear", "demod-bilinear"):
        out = tmp_path / f"{m}.json"
        assert main(["evaluate", "--model", m, "--data", str(clip), "--json", str(out), "--no-flip"]) == 0
        res[m] = json.loads(out.read_text())["mean"]
    assert res["demod-bilinear"]["psnr"] > res["bilinear"]["psnr"] + 0.5
    assert res["demod-bilinear"]["ssim"] > res["bilinear"]["ssim"] + 0.1
    assert res["bilinear"]["flip"] is None


def test_evaluate_sets_a_non_learned_models_configuration(clip, checkpoint, tmp_path, capsys):
    """--set model.KEY=VALUE: demod-jbu with guide tolerances so wide that every neighbour counts is demod-bilinear;
    bad keys, values and checkpoints are refused with one line."""
    res = {}
    for name, m, sets in (("db", "demod-bilinear", []), ("jbu", "demod-jbu", []),
                          ("wide", "demod-jbu", ["--set", "model.guide_sigma_depth=100",
                                                 "--set", "model.guide_sigma_normal=100"])):
        out = tmp_path / f"{name}.json"
        assert main(["evaluate", "--model", m, "--data", str(clip), "--json", str(out), "--no-flip", *sets]) == 0
        res[name] = json.loads(out.read_text())["mean"]["psnr"]
    assert res["wide"] == pytest.approx(res["db"], abs=0.01) and res["jbu"] != pytest.approx(res["db"], abs=0.01)
    for args, msg in ((["--model", "demod-jbu", "--set", "model.guide_sigma_depth=0"], "guide_sigma_depth"),
                      (["--model", "demod-jbu", "--set", "data.crop=8"], "only model.KEY=VALUE"),
                      (["--checkpoint", str(checkpoint), "--set", "model.guide_sigma_depth=1"], "fixed")):
        assert main(["evaluate", *args, "--data", str(clip), "--json", str(tmp_path / "x.json"), "--no-flip"]) != 0
        assert msg in capsys.readouterr().err


def _bilinear_by_class(irr_lr, fbu_lr, fbu_hr, s):
    """numpy/interpolate reference of base.upsample_by_class for an un-jittered clip (H x W x 3 arrays)."""
    def interp(a):
        t = torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None].double()
        return torch.nn.functional.interpolate(t, scale_factor=s, mode="bilinear")[0].numpy().transpose(1, 2, 0)
    m_lr = (fbu_lr != 1.0).any(-1, keepdims=True).astype(np.float64)
    m_hr = (fbu_hr != 1.0).any(-1, keepdims=True)
    out = interp(irr_lr)
    for ml, mh in ((m_lr, m_hr), (1.0 - m_lr, ~m_hr)):
        num, den = interp(irr_lr * ml), interp(ml)
        out = np.where((den > 1e-6) & mh, num / np.maximum(den, 1e-6), out)
    return out.astype(np.float32)


def test_upscale_frame_api_and_upscale_command(clip, checkpoint, tmp_path):
    from training.inference.loading import load_model, upscale_frame
    c = open_clip(clip)
    model = load_model("demod-bilinear", 4)
    out = upscale_frame(model, clip, 3)
    assert set(out) == {"sr", "bilinear", "ms", "reference"} and out["sr"].shape == (36, 64, 3)
    assert out["sr"].dtype == np.float32 and out["ms"] > 0
    np.testing.assert_array_equal(out["reference"], c.read(3, "hr/radiance"))
    irr, fbu_lr = np_demod.demodulate(c.read(3, "lr/radiance"), c.read(3, "lr/emission"), c.read(3, "lr/fbeta"),
                                      c.read(3, "lr/flags"))
    _, fbu = np_demod.demodulate(c.read(3, "hr/radiance"), c.read(3, "hr/emission"), c.read(3, "hr/fbeta"),
                                 c.read(3, "hr/flags"))
    up = _bilinear_by_class(irr, fbu_lr, fbu, 4)
    np.testing.assert_allclose(out["sr"], up * fbu + c.read(3, "hr/emission"), rtol=1e-5, atol=1e-6)
    bil = torch.nn.functional.interpolate(torch.from_numpy(c.read(3, "lr/radiance").transpose(2, 0, 1))[None],
                                          scale_factor=4, mode="bilinear")[0].numpy().transpose(1, 2, 0)
    np.testing.assert_allclose(out["bilinear"], bil, rtol=1e-5, atol=1e-6)  # un-jittered clip: plain bilinear
    with pytest.raises(ValueError, match="checkpoint"):
        load_model("fusesr", 4)
    with pytest.raises(ValueError, match="scale 4, not 8"):
        load_model(str(checkpoint), 8)
    learned = load_model(str(checkpoint), 4)
    r1 = upscale_frame(learned, clip, 1)  # first frame: no history needed for fusesr-l
    assert np.isfinite(r1["sr"]).all() and r1["sr"].min() >= 0
    outdir = tmp_path / "up"
    assert main(["upscale", "--checkpoint", str(checkpoint), "--clip", str(clip), "-o", str(outdir),
                 "--frames", "1:2"]) == 0
    np.testing.assert_allclose(read_exr(outdir / "000001.exr", ("R", "G", "B")), r1["sr"], rtol=1e-6, atol=1e-7)
    assert json.loads((outdir / "upscale.json").read_text())["frames"] == [1, 2]


def test_no_model_reads_the_ground_truth(clip, checkpoint):
    from training.inference.loading import ClipFrames, load_model, model_inputs, run_model
    src = ClipFrames(clip)
    for spec in ["bilinear", "bicubic", "demod-bilinear", str(checkpoint)]:
        model = load_model(spec, 4)
        assert "hr/radiance" not in model.module.needs()
        inputs = model_inputs(model, src, 2)
        a, _ = run_model(model, inputs)
        inputs["hr/radiance"] = np.full_like(inputs["hr/radiance"], 123.0)
        b, _ = run_model(model, inputs)
        np.testing.assert_array_equal(a, b)


def test_onnx_export_matches_torch_at_another_size(clip, checkpoint, tmp_path):
    import onnxruntime as ort
    from training.inference.export import example_inputs
    from training.inference.loading import load_model, run_model
    path = tmp_path / "m.onnx"
    assert main(["export", "--checkpoint", str(checkpoint), "--onnx", str(path), "--clip", str(clip)]) == 0
    report = json.loads(path.with_suffix(".onnx.json").read_text())
    assert report["match"] and report["max_abs_diff"] < 1e-4
    model = load_model(str(checkpoint), 4)
    inputs = example_inputs(model, None, (64, 32), seed=3)  # dynamic height/width
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(["sr"], {k.replace("/", "_"): v for k, v in inputs.items()})[0]
    ref, _ = run_model(model, inputs)
    assert got.shape == (1, 3, 32, 64)
    np.testing.assert_allclose(got[0].transpose(1, 2, 0), ref, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("name", ["demod-bilinear", "demod-jbu"])
def test_onnx_export_of_a_model_that_remodulates_through_the_pixel_filter(name, tmp_path):
    """The default REFERENCE filter (Blackman-Harris 1.5 px) runs after remodulation; its convolution must export
    with dynamic shapes (it did not before session 5). Checked again at another size."""
    import onnxruntime as ort
    from training.inference.export import example_inputs
    from training.inference.loading import load_model, run_model
    path = tmp_path / "m.onnx"
    assert main(["export", "--model", name, "--onnx", str(path), "--hr-size", "64x32"]) == 0
    model = load_model(name, 4)
    assert model.module.remod_kernel is not None
    assert json.loads(path.with_suffix(".onnx.json").read_text())["match"]
    inputs = example_inputs(model, None, (96, 48), seed=4)
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(
        ["sr"], {k.replace("/", "_"): v for k, v in inputs.items()})[0]
    np.testing.assert_allclose(got[0].transpose(1, 2, 0), run_model(model, inputs)[0], rtol=1e-4, atol=1e-4)


def test_bench_models_table_macs_and_pareto_plot(clip, checkpoint, tmp_path):
    import argparse

    from training import bench
    from training.commands import bench_models
    from training.inference.loading import ClipFrames, load_model, model_inputs
    p = argparse.ArgumentParser()
    bench_models.add_arguments(p)
    out = tmp_path / "bench"
    args = p.parse_args(["--data", str(clip), "--models", f"bilinear,demod-bilinear,fusesr-l:{checkpoint}",
                         "-o", str(out), "--frames", "1:2", "--warmup", "1"])
    assert bench_models.run(args) == 0
    rows = json.loads((out / "bench_models.json").read_text())["rows"]
    assert [r["model"] for r in rows] == ["bilinear", "demod-bilinear", f"fusesr-l ({checkpoint.parents[1].name})"]
    assert (out / "pareto.png").stat().st_size > 1000 and (out / "bench_models.csv").is_file()
    assert rows[0]["params"] == 0 and rows[0]["macs_per_px"] == 0
    # MACs per HR pixel of the learned model, counted independently from the convolution layers
    model = load_model(str(checkpoint), 4)
    total = []

    def hook(mod, inp, outp):
        total.append(outp.numel() * mod.in_channels // mod.groups * mod.kernel_size[0] * mod.kernel_size[1])
    hs = [m.register_forward_hook(hook) for m in model.module.modules() if isinstance(m, torch.nn.Conv2d)]
    inputs = model_inputs(model, ClipFrames(clip), 1)
    with torch.no_grad():
        model.module({k: torch.from_numpy(v) for k, v in inputs.items() if k in model.module.needs()})
    for h in hs:
        h.remove()
    assert rows[2]["macs_per_px"] == pytest.approx(sum(total) / (64 * 36), rel=1e-6)
    assert bench.pareto_front([(1, 10), (2, 9), (3, 12), (0.5, 8)]) == [3, 0, 2]
    with pytest.raises(ValueError, match="learned"):
        bench.parse_models("fusesr")
    # two runs whose model folders share a name keep two rows (labelled by path); one model twice is an error
    a, b = "runs/a/fusesr/checkpoints/last.pt", "runs/b/fusesr/checkpoints/last.pt"
    assert bench.parse_models(f"fusesr:{a},fusesr:{b},fusesr:{a}?residual_clamp=none") == [
        (f"fusesr ({a})", a), (f"fusesr ({b})", b), ("fusesr (fusesr?residual_clamp=none)", f"{a}?residual_clamp=none")]
    with pytest.raises(ValueError, match="given twice"):
        bench.parse_models(f"demod-jbu,fusesr:{a},demod-jbu")


def test_models_table_is_listed(capsys):
    assert main(["train", "--list-models"]) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in MODELS)


def test_training_demo_writes_table_plot_and_side_by_side(tmp_path, monkeypatch):
    from training import pretrained
    from training.commands.demo import _prepare_run, run_training_demo
    from training.release import release
    a = make_synthetic_clip(tmp_path / "train", frames=range(1, 4), hr_size=(48, 32), scale=4)
    b = make_synthetic_clip(tmp_path / "test", frames=range(1, 3), hr_size=(48, 32), scale=4)
    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", tmp_path / "weights")  # no shipped weights: train from scratch
    s = run_training_demo([a], [b], tmp_path / "demo", steps=3, model="fusesr-l", threads=1)
    assert s["train"]["step"] == 3 and s["train"]["stopped_by"] == "max_steps" and s["train"]["elapsed_s"] > 0
    assert s["train"]["threads"] == 1 and torch.get_num_threads() == 1
    assert [r["model"] for r in s["bench"]] == ["bilinear", "bicubic", "demod-bilinear", "demod-jbu",
                                                "fusesr-l (3 steps)"]
    for f in ("pareto.png", "side_by_side.png", "bench/bench_models.md"):
        assert (tmp_path / "demo" / f).stat().st_size > 100
    # a finished run is scored as it is
    again = run_training_demo([a], [b], tmp_path / "demo", steps=3, model="fusesr-l", threads=1)
    assert again["train"] == s["train"]
    assert [r["psnr"] for r in again["bench"]] == [r["psnr"] for r in s["bench"]]
    run = tmp_path / "demo" / "run_fusesr_l"
    (run / "summary.json").unlink()  # as if stopped after its last checkpoint
    assert _prepare_run(run, "", 3) is True  # same weights, no more steps than the budget: continues
    resumed = run_training_demo([a], [b], tmp_path / "demo", steps=3, model="fusesr-l", threads=1)
    assert resumed["train"]["step"] == 3 and [r["psnr"] for r in resumed["bench"]] == [r["psnr"] for r in s["bench"]]
    # a larger budget continues the run from its checkpoint (step 3 is not trained again)
    more = run_training_demo([a], [b], tmp_path / "demo", steps=5, model="fusesr-l", threads=1)
    assert more["train"]["step"] == 5 and more["bench"][-1]["model"] == "fusesr-l (5 steps)"
    assert (run / "checkpoints" / "step_00000003.pt").is_file()
    # a budget below the steps run starts anew
    assert _prepare_run(run, "", 4) is False and not (run / "checkpoints").exists()
    fewer = run_training_demo([a], [b], tmp_path / "demo", steps=4, model="fusesr-l", threads=1)
    assert fewer["train"]["step"] == 4 and fewer["bench"][-1]["model"] == "fusesr-l (4 steps)"
    # with shipped weights the demo scores them and fine-tunes one of them
    release(tmp_path / "demo" / "run_fusesr_l" / "checkpoints" / "last.pt",
            tmp_path / "weights" / "fusesr_l_x4.safetensors", {"model": "fusesr-l"})
    ft = run_training_demo([a], [b], tmp_path / "demo2", steps=2, model="fusesr-l", threads=1)
    assert [r["model"] for r in ft["bench"]] == ["bilinear", "bicubic", "demod-bilinear", "demod-jbu",
                                                 "pretrained:fusesr-l", "fusesr-l (fine-tuned 2 steps)"]
    assert ft["pretrained"] == ["pretrained:fusesr-l"] and (tmp_path / "demo2" / "side_by_side.png").is_file()


_DEMO_SCRIPT = """
import sys
from pathlib import Path
from training import pretrained
from training.commands.demo import run_training_demo
pretrained.WEIGHTS_DIR = Path(sys.argv[4])
run_training_demo([sys.argv[1]], [sys.argv[2]], sys.argv[3], steps=100000, model="fusesr-l", threads=1)
"""


def test_training_demo_stopped_by_sigterm_records_the_steps_run_and_a_rerun_continues(tmp_path, monkeypatch):
    """Issue 57 item 3: SIGTERM stops the fine-tune within seconds; its summary records the steps it ran (not its
    budget), it is not scored and not taken for done; the next run continues from its checkpoint."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from tests.conftest import ENV, REPO
    from training import pretrained
    from training.commands.demo import run_training_demo
    a = make_synthetic_clip(tmp_path / "train", frames=range(1, 4), hr_size=(48, 32), scale=4)
    b = make_synthetic_clip(tmp_path / "test", frames=range(1, 3), hr_size=(48, 32), scale=4)
    out, run = tmp_path / "demo", tmp_path / "demo" / "run_fusesr_l"
    proc = subprocess.Popen([sys.executable, "-c", _DEMO_SCRIPT, str(a), str(b), str(out), str(tmp_path / "w")],
                            cwd=REPO, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 300
        while not (run / "log.csv").is_file() or len((run / "log.csv").read_text().splitlines()) < 2:
            assert proc.poll() is None and time.monotonic() < deadline, proc.stdout.read() if proc.poll() else ""
            time.sleep(0.2)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=120)
        stopped_in = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
    log = proc.stdout.read()
    # at the next step, not at the budget's end (100,000 steps): a bound loose enough for a loaded 2-core machine
    assert proc.returncode != 0 and stopped_in < 60, (proc.returncode, stopped_in, log[-2000:])
    assert "FineTuneStopped" in log and "not scored" in log, log[-2000:]
    summary = json.loads((run / "summary.json").read_text())
    ran = summary["step"]
    assert summary["stopped_by"] == "signal" and 5 <= ran < 100000 and summary["max_steps"] == 100000
    assert not (out / "bench").exists() and not (out / "pareto.png").exists()  # nothing scored
    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", tmp_path / "w")
    cont = run_training_demo([a], [b], out, steps=ran + 2, model="fusesr-l", threads=1)
    assert cont["train"]["step"] == ran + 2 and cont["train"]["stopped_by"] == "max_steps"
    assert cont["bench"][-1]["model"] == f"fusesr-l ({ran + 2} steps)"
    rows = [r for r in (run / "log.csv").read_text().splitlines()[1:] if r]
    steps_logged = [int(r.split(",")[0]) for r in rows]
    assert steps_logged == sorted(set(steps_logged)), "the rerun trained steps again instead of continuing"


def test_clips_without_optional_buffers_and_missing_required_ones(tmp_path):
    from gbuffer_export.clip import ClipError
    from training.inference.loading import load_model, upscale_frame
    bufs = ("radiance", "albedo", "depth", "fbeta", "motion")  # no emission, no flags, no normal
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 3), hr_size=(64, 36), scale=4, buffers=bufs)
    out = upscale_frame(load_model("demod-bilinear", 4), clip, 2)
    c = open_clip(clip)
    irr, fbu_lr = np_demod.demodulate(c.read(2, "lr/radiance"), None, c.read(2, "lr/fbeta"))
    fb = np.clip(c.read(2, "hr/fbeta"), 0.01, None)  # no flags: the background is divided like any pixel
    up = _bilinear_by_class(irr, fbu_lr, fb, 4)  # (by its F_beta of 1, so the classes still hold)
    np.testing.assert_allclose(out["sr"], up * fb, rtol=1e-5, atol=1e-6)
    assert main(["evaluate", "--model", "bilinear", "--data", str(clip), "--json", str(tmp_path / "b.json")]) == 0
    from training.config import ModelConfig
    from training.inference.loading import ClipFrames, model_inputs
    from training.models import build_model
    with pytest.raises(ClipError, match="lacks 'lr/normal'"):
        model_inputs(build_model(ModelConfig(name="fusesr"), 4), ClipFrames(clip), 2)
    assert main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(tmp_path / "r"),
                 "--set", "data.crop=4"]) == 2


def test_group_means_average_frames_per_clip_or_per_scene():
    from training.evaluate import group_means
    rows = [{"clip": "/d/clips/a-00", "psnr": 30.0, "ssim": 0.9, "tpsnr": None},
            {"clip": "/d/clips/a-00", "psnr": 32.0, "ssim": 0.8, "tpsnr": 28.0},
            {"clip": "/d/clips/a-01", "psnr": 20.0, "ssim": 0.5, "tpsnr": 22.0}]
    per_clip = group_means({"per_frame": rows})
    assert per_clip == {"a-00": {"psnr": 31.0, "ssim": pytest.approx(0.85), "tpsnr": 28.0},
                        "a-01": {"psnr": 20.0, "ssim": 0.5, "tpsnr": 22.0}}
    per_scene = group_means({"per_frame": rows}, lambda c: c.split("-")[0], metrics=("psnr",))
    assert per_scene == {"a": {"psnr": pytest.approx(82.0 / 3)}}  # frames weigh equally, not clips
