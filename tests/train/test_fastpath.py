"""The inference fast path against the fp32 eager reference (CPU), and the fusesr-fast model."""
import copy
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)  # 2 threads on a shared 2-core machine can be 10x slower

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training.config import ModelConfig, load_config  # noqa: E402
from training.inference.export import example_inputs  # noqa: E402
from training.inference.fastpath import channels_last_batch, fold_batchnorm, forward, prepare_inference  # noqa: E402
from training.models import MODELS, build_model  # noqa: E402
from training.models import fast_ops  # noqa: E402
from training.models.base import separable_filter, upsample_by_class  # noqa: E402
from training.models.guided import upsample_guided  # noqa: E402


#: max |fast - reference| / max |reference| allowed per precision (fp32: float rounding of reordered sums)
TOL = {"none": 2e-6, "bf16": 2e-2, "fp16": 4e-3}


def _randomise_batchnorm(model):
    g = torch.Generator().manual_seed(1)
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.copy_(0.4 * torch.rand(m.num_features, generator=g) - 0.2)
            m.running_var.copy_(0.5 + 1.5 * torch.rand(m.num_features, generator=g))
            m.weight.data.copy_(0.5 + torch.rand(m.num_features, generator=g))
            m.bias.data.copy_(0.2 * torch.rand(m.num_features, generator=g) - 0.1)


def _cases():
    for name in MODELS:
        norms = ("none", "batch") if name in ("fusesr", "fusesr-fast") else ("none",)
        for norm in norms:
            yield name, norm


@pytest.mark.parametrize("name,norm", list(_cases()))
def test_every_fast_path_matches_the_fp32_eager_reference(name, norm):
    torch.manual_seed(0)
    ref = build_model(ModelConfig.of(name, **({} if norm == "none" else {"norm": norm})), 4)
    _randomise_batchnorm(ref)
    ref.eval()
    batch = {k: torch.from_numpy(v) for k, v in example_inputs(ref, None, (64, 48), seed=2).items()}
    with torch.inference_mode():
        want = ref(batch)
    peak = float(want.abs().max())
    assert peak > 0
    for precision in ("none", "bf16", "fp16"):
        for channels_last in (False, True):
            fast = prepare_inference(copy.deepcopy(ref), precision=precision, channels_last=channels_last)
            assert fast.module.fast_ops
            with torch.inference_mode():
                got = forward(fast, batch)
            assert got.dtype == torch.float32 and got.shape == want.shape
            err = float((got - want).abs().max()) / peak
            assert err <= TOL[precision], (precision, channels_last, err)
            if precision != "none" and MODELS[name].learned:  # the autocast really ran in low precision
                assert err > 1e-6


def test_batchnorm_folding_removes_every_batchnorm_and_keeps_the_output():
    for name in ("fusesr", "fusesr-fast"):
        model = build_model(ModelConfig.of(name=name, norm="batch"), 4)
        _randomise_batchnorm(model)
        model.eval()
        n_bn = sum(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())
        batch = {k: torch.from_numpy(v) for k, v in example_inputs(model, None, (32, 32), seed=1).items()}
        with torch.no_grad():
            want = model(batch)
            assert fold_batchnorm(model) == n_bn > 0
            assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())
            torch.testing.assert_close(model(batch), want, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="eval"):
        fold_batchnorm(build_model(ModelConfig.of(name="fusesr-fast", norm="batch"), 4).train())


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


@pytest.mark.parametrize("taps", [(0.11859148, 0.76281703, 0.11859148), (0.05, 0.2, 0.5, 0.2, 0.05), (1.0,)])
def test_shift_filter_is_the_separable_convolution(taps):
    x = torch.rand(2, 3, 9, 13, generator=_gen())
    got = fast_ops.shift_filter(x, taps)
    torch.testing.assert_close(got, separable_filter(x, torch.tensor(taps)), rtol=1e-6, atol=1e-6)
    cl = fast_ops.shift_filter(x.contiguous(memory_format=torch.channels_last), taps)
    torch.testing.assert_close(cl, got, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("batch", [1, 3])
def test_fast_upsampling_by_class_and_guided_match_the_references(batch):
    g = _gen(batch)
    s, h, w = 4, 7, 9
    x = torch.rand(batch, 3, h, w, generator=g)
    lm = (torch.rand(batch, 1, h, w, generator=g) > 0.3).float()
    hm = (torch.rand(batch, 1, h * s, w * s, generator=g) > 0.3).float()
    j = torch.rand(batch, 2, generator=g) - 0.5
    for jit in (j, None):
        torch.testing.assert_close(fast_ops.upsample_by_class(x, lm, hm, s, jit), upsample_by_class(x, lm, hm, s, jit),
                                   rtol=1e-6, atol=1e-6)
        lg, hg = torch.randn(batch, 4, h, w, generator=g), torch.randn(batch, 4, h * s, w * s, generator=g)
        fb = torch.rand(batch, 3, h * s, w * s, generator=g)
        for cls in ((lm, hm), None):
            want = upsample_guided(x, lg, hg, s, fb, jit, cls)
            torch.testing.assert_close(fast_ops.upsample_guided(x, lg, hg, s, fb, jit, cls), want,
                                       rtol=1e-5, atol=1e-6)
    # the batch-1 index_select shortcut and the gather used under tracing give the same rows
    idx = torch.tensor([[2, 0, 1, 1]])
    torch.testing.assert_close(fast_ops.take(x[:1], 3, idx), torch.gather(x[:1], 3, idx.view(1, 1, 1, 4).expand(
        1, 3, h, 4)))


def test_channels_last_batch_keeps_values_and_lays_frames_out_nhwc():
    b = {"lr/x": torch.rand(1, 2, 3, 5, 6), "depth_ref": torch.rand(1, 2), "lr/depth": torch.rand(1, 2, 1, 5, 6)}
    out = channels_last_batch(b)
    for k in b:
        assert torch.equal(out[k], b[k])
    assert out["lr/x"][:, -1].is_contiguous(memory_format=torch.channels_last)


@pytest.mark.heavy
def test_torch_compile_of_the_fast_path_matches_the_reference():
    """inductor (C++ on the CPU) fuses the guided upsampling's gathers and the remodulation: same output."""
    ref = build_model(ModelConfig(name="demod-jbu"), 4).eval()
    batch = {k: torch.from_numpy(v) for k, v in example_inputs(ref, None, (32, 16), seed=5).items()}
    fast = prepare_inference(copy.deepcopy(ref), compile=True)
    with torch.inference_mode():
        torch.testing.assert_close(forward(fast, batch), ref(batch), rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------------------------------------ fusesr-fast
def test_fusesr_fast_has_the_authors_layer_sizes_and_parameter_count():
    m = build_model(ModelConfig(name="fusesr-fast"), 4)
    assert m.history == 0 and "lr/motion" not in m.needs() and "hr/albedo" not in m.needs()
    assert m.encoder.shallow[0].in_channels == 7 and m.encoder.shallow[0].out_channels == 32
    pw = [mod.pointwise.out_channels for mod in m.encoder.main if hasattr(mod, "pointwise")]
    assert pw == [16, 12, 12, 16]
    assert len(m.blocks) == 6 and all(b.depthwise.groups == 32 == b.depthwise.in_channels for b in m.blocks)
    assert m.fuse_in[0].in_channels == 32 + 3 * 16 + 2 and m.head.in_channels == 64 and m.head.out_channels == 48
    count = lambda mod: sum(p.numel() for p in mod.parameters())  # noqa: E731
    assert count(m) == 68188
    # the authors' configuration (BatchNorm, no jitter channels): their 68 108
    assert count(build_model(ModelConfig.of(name="fusesr-fast", norm="batch", jitter=False), 4)) == 68108
    light = build_model(ModelConfig(name="fusesr-l"), 4)
    assert count(light) > 3.9 * count(m)
    with pytest.raises(ValueError, match="history"):
        build_model(ModelConfig(name="fusesr-fast", history=2), 4)


def test_fusesr_fast_macs_per_pixel_about_4300():
    from torch.utils.flop_counter import FlopCounterMode
    m = build_model(ModelConfig.of(name="fusesr-fast", remod_filter="NONE", guided_upsample=False), 4).eval()
    batch = {k: torch.from_numpy(v) for k, v in example_inputs(m, None, (64, 32)).items()}
    counter = FlopCounterMode(display=False)
    with torch.no_grad(), counter:
        m(batch)
    # per LR pixel 2016 + 1688 (separable encoder) + 4608 + 23616 (fusion, 82 channels in) + 7872 + 27648; / 16,
    # plus the HR refinement's 81
    assert counter.get_total_flops() / 2 / (64 * 32) == pytest.approx((2016 + 1688 + 4608 + 23616 + 7872 + 27648)
                                                                      / 16 + 81)


def test_fusesr_fast_trains_evaluates_and_exports(tmp_path):
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)
    run = tmp_path / "run"
    rc = main(["train", "--model", "fusesr-fast", "--data", str(clip), "-o", str(run), "--max-steps", "2",
               "--set", "data.crop=8", "--set", "data.batch_size=2", "--set", "run.progress=false",
               "--set", "run.amp=\"none\"", "--set", "model.norm=\"batch\""])
    assert rc == 0
    summary = json.loads((run / "summary.json").read_text())
    assert summary["model"] == "fusesr-fast" and summary["step"] == 2 and summary["params"] == 68684
    ck = run / "checkpoints" / "last.pt"
    assert main(["evaluate", "--checkpoint", str(ck), "--data", str(clip), "--json", str(tmp_path / "e.json"),
                 "--no-flip", "--warmup", "0"]) == 0
    ev = json.loads((tmp_path / "e.json").read_text())
    assert np.isfinite(ev["mean"]["psnr"]) and ev["mean"]["frames"] == 3
    onnx = tmp_path / "f.onnx"
    assert main(["export", "--checkpoint", str(ck), "--onnx", str(onnx), "--hr-size", "32x16"]) == 0
    rep = json.loads(onnx.with_suffix(".onnx.json").read_text())
    assert rep["match"] and rep["output_shape"] == [1, 3, 16, 32]
    cfg = load_config(run / "config.toml")
    assert cfg.model.name == "fusesr-fast"


# ------------------------------------------------------------------------------------------------ training loader
def test_worker_loader_gives_the_same_training_as_the_prefetch_thread(tmp_path):
    from training.train import train
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)
    digests = []
    for workers in (0, 2):
        cfg = load_config(None, ["model.name=\"fusesr-fast\"", "data.crop=8", "data.batch_size=2", "run.max_steps=4",
                                 "run.progress=false", "run.amp=\"none\"", f"data.workers={workers}"])
        cfg.data.clips = [str(clip)]
        summary = train(cfg, tmp_path / f"run{workers}")
        digests.append(summary["param_digest"])
        assert summary["workers"] == workers and summary["gpu_max_memory_mb"] is None
        assert summary["samples_per_s"] == pytest.approx(2 * summary["steps_per_s"])
        assert 0 <= summary["data_fraction"] <= 1 and summary["max_rss_mb"] > 0
    assert digests[0] == digests[1]


# ------------------------------------------------------------------------------------------------ bench models
def test_bench_models_speed_mode_on_random_inputs(tmp_path):
    import argparse

    from training.commands import bench_models
    p = argparse.ArgumentParser()
    bench_models.add_arguments(p)
    out = tmp_path / "speed"
    args = p.parse_args(["--models", "bilinear,demod-jbu,fusesr-fast", "--size", "64x32", "--device", "cpu",
                         "--precision", "none,bf16", "--repeats", "2", "--warmup", "1", "--eager-reference",
                         "--peak-tflops", "0.5", "--bandwidth-gbs", "10", "-o", str(out)])
    assert bench_models.run(args) == 0
    res = json.loads((out / "bench_speed.json").read_text())
    assert res["size"] == [64, 32] and res["scale"] == 4 and res["peaks"]["fp32"]["tflops"] == 0.5
    rows = res["rows"]
    assert [(r["model"], r["variant"]) for r in rows[:3]] == [("bilinear", v) for v in
                                                             ("fp32 eager reference", "fp32", "bf16")]
    fast = next(r for r in rows if r["model"] == "fusesr-fast" and r["variant"] == "fp32")
    assert fast["params"] == 68188 and 4000 < fast["macs_per_px"] < 4500
    for r in rows:  # roofline: max(2 MACs / peak, bytes / bandwidth), ratio = measured / roofline
        want = 1000 * max(2 * r["gmacs"] * 1e9 / 0.5e12, r["mbytes"] * 1e6 / 10e9)
        assert r["roofline_ms"] == pytest.approx(want) and r["ratio"] == pytest.approx(r["ms"] / want)
        assert r["ms"] > 0 and r["ms_min"] <= r["ms"]
    md = (out / "bench_speed.md").read_text()
    assert "| fusesr-fast | 68188 |" in md and "fp32 eager reference ms" in md
    with pytest.raises(ValueError, match="--size"):
        bench_models.run(p.parse_args(["--size", "63x32", "--models", "bilinear", "-o", str(out)]))
    with pytest.raises(ValueError, match="--precision"):
        bench_models.run(p.parse_args(["--precision", "fp8", "--models", "bilinear", "-o", str(out)]))


# ------------------------------------------------------------------------------------------------ on a GPU
cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@cuda
@pytest.mark.parametrize("name", list(MODELS))
def test_cuda_fast_path_bf16_compiled_matches_the_cpu_fp32_reference(name):
    """On a GPU: channels-last, bf16 autocast and torch.compile (reduce-overhead: CUDA graphs) against the fp32
    eager reference computed on the CPU."""
    ref = build_model(ModelConfig(name=name), 4).eval()
    inputs = example_inputs(ref, None, (128, 64), seed=3)
    with torch.inference_mode():
        want = ref({k: torch.from_numpy(v) for k, v in inputs.items()})
    dev = torch.device("cuda")
    batch = {k: torch.from_numpy(v).to(dev) for k, v in inputs.items()}
    for precision, comp, tol in (("none", False, 1e-3), ("bf16", False, 2e-2), ("bf16", True, 2e-2)):
        fast = prepare_inference(copy.deepcopy(ref), dev, precision, compile=comp)
        with torch.inference_mode():
            for _ in range(3):  # CUDA-graph warm-up and replay
                got = forward(fast, batch).cpu()
        err = float((got - want).abs().max() / want.abs().max())
        assert err <= tol, (precision, comp, err)


@cuda
def test_bench_models_speed_mode_on_cuda(tmp_path):
    from training.bench import SpeedOptions, load_models, speed_benchmark
    models = load_models([("demod-jbu", "demod-jbu"), ("fusesr-fast", "fusesr-fast")], 4, fast=False)
    res = speed_benchmark([(label, m.to("cuda")) for label, m in models], tmp_path, SpeedOptions(
        size=(256, 128), precisions=("none", "bf16"), compiles=(False, True), warmup=2, repeats=3,
        log=lambda m: None))
    assert "CUDA events" in res["timing"] and len(res["rows"]) == 8
    assert all(r["ms"] > 0 and r["roofline_ms"] > 0 for r in res["rows"])


def test_bench_models_on_a_clip_adds_the_roofline_columns(tmp_path):
    import argparse

    from training.commands import bench_models
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 3), hr_size=(64, 36), scale=4)
    p = argparse.ArgumentParser()
    bench_models.add_arguments(p)
    out = tmp_path / "b"
    assert bench_models.run(p.parse_args(["--data", str(clip), "--models", "demod-bilinear", "--precision", "bf16",
                                          "--warmup", "0", "--peak-tflops", "1", "--bandwidth-gbs", "2",
                                          "-o", str(out)])) == 0
    res = json.loads((out / "bench_models.json").read_text())
    row = res["rows"][0]
    assert res["peaks"]["bf16"]["gbs"] == 2.0
    assert row["roofline_ms"] > 0 and row["ratio"] == pytest.approx(row["ms_per_frame"] / row["roofline_ms"])
    with pytest.raises(ValueError, match="one --precision"):
        bench_models.run(p.parse_args(["--data", str(clip), "--precision", "none,bf16", "-o", str(out)]))
