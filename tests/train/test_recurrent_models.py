"""What every recurrent model does the same way, parametrized over them (RDG-s, NSRD, NSRR-FEC, fourier-sr):
training with truncated windows and bit-identical resume, recurrent evaluation from the clip's start, ``upscale``
carrying the state, ONNX export with the state as explicit inputs over three frames, a ``bench models`` row.
Each model's own checks (parameter counts, masks, cache warping, the Fourier layers) stay in its file."""
import csv
import json
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)  # 2 threads on a shared 2-core machine can be 10x slower

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training.config import load_config  # noqa: E402
from training.models import build_model  # noqa: E402
from training.inference.frames import lead_in  # noqa: E402
from tests.conftest import set_args  # noqa: E402


SMALL = ["data.crop=8", "data.batch_size=2", "run.progress=false", "run.log_every=1", "run.amp=\"none\"",
         "data.window=3", "data.detach_every=2"]
RESUME = ["run.checkpoint_every=100", "optim.decay_steps=4", "data.prefetch=1"]


def _loss_rdg(r):
    return float(r["pixel"]) + 0.05 * float(r["fft"]) + float(r["temporal"])


def _loss_pixel_ssim_temporal(r):
    return float(r["pixel"]) + float(r["ssim"]) + float(r["temporal"])


#: per model: its settings (the losses its paper trains with), how the logged loss adds up (None: not checked), a
#: weight the last two steps must move, the count of state tensors, the parameter count of the trained config
#: (None: counted from the config), and whether the temporal term must be > 0.
CASES = {
    "rdg-s": dict(sets=["model.width=8", "loss.pixel=\"charbonnier\"", "loss.charbonnier_eps=1e-6",
                        "loss.ssim_weight=0.0", "loss.temporal_weight=1.0", "loss.temporal=\"difference\"",
                        "loss.fft_weight=0.05", "loss.fft=\"rfft\""],
                  total=_loss_rdg, moved="head.weight", states=4, params=None, temporal=False),
    "nsrd": dict(sets=["loss.ssim_weight=1.0", "loss.temporal_weight=1.0"],
                 total=_loss_pixel_ssim_temporal, moved="head.1.weight", states=11, params=None, temporal=True),
    "nsrr-fec": dict(sets=["loss.pixel_weight=0.0", "loss.ssim_weight=1.0"],
                     total=None, moved="unet.out.weight", states=4, params=558_999, temporal=False),
    "fourier-sr": dict(sets=["loss.ssim_weight=0.0", "loss.temporal_weight=0.3"],
                       total=None, moved="mlp.6.weight", states=2, params=531_883, temporal=True),
}
MODELS = list(CASES)


def n_params(m):
    return sum(p.numel() for p in m.parameters())


def small(name):
    return SMALL + CASES[name]["sets"] + [f"model.name=\"{name}\""]


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """Four frames (a training window of 3, the export's 3 frames, a lead-in before frames 3 and 4), LR 12 x 8."""
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 5), hr_size=(48, 32), scale=4,
                               jitter=True)


@pytest.fixture(scope="module", params=MODELS)
def name(request):
    return request.param


@pytest.fixture(scope="module")
def checkpoint(name, clip, tmp_path_factory):
    """One training step of ``name`` on the clip."""
    from training.train import train
    cfg = load_config(None, small(name) + ["run.max_steps=1"])
    cfg.data.clips = [str(clip)]
    run = tmp_path_factory.mktemp("run")
    train(cfg, run)
    return run / "checkpoints" / "last.pt"


def _manual(model, clip, frames):
    """SR of ``frames`` (consecutive, from the clip's first) by stepping the model by hand: the state reset at the
    clip's first frame and carried."""
    from training.inference.loading import ClipFrames, model_inputs
    src = ClipFrames(clip, eps=model.demod_eps)
    out, state = {}, None
    with torch.no_grad():
        for f in frames:
            inp = model_inputs(model, src, f)
            b = {k: torch.from_numpy(v) for k, v in inp.items() if k in model.module.needs()}
            sr, state = model.module.step(b, state)
            out[f] = sr[0].permute(1, 2, 0).numpy()
    return out


@pytest.mark.heavy
def test_train_logs_per_frame_losses_and_memory_and_resumes_bit_identically(name, clip, tmp_path):
    from training.checkpoint import load_checkpoint
    from training.train import train
    case = CASES[name]
    straight = tmp_path / "straight"
    assert main(["train", "--model", name, "--data", str(clip), "-o", str(straight), "--max-steps", "4",
                 *set_args(small(name) + RESUME)]) == 0
    rows = list(csv.DictReader(open(straight / "log.csv")))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4]
    for r in rows:
        assert math.isfinite(float(r["loss"])) and float(r["mem_mb"]) > 0
        if case["total"] is not None:
            assert float(r["loss"]) == pytest.approx(case["total"](r), rel=1e-4)
        if case["temporal"]:
            assert float(r["temporal"]) > 0
    summary = json.loads((straight / "summary.json").read_text())
    assert summary["peak_mem_mb"] == max(float(r["mem_mb"]) for r in rows)
    assert summary["window"] == 3 and summary["params"] == n_params(
        build_model(load_config(straight / "config.toml").model, 4))
    if case["params"] is not None:
        assert summary["params"] == case["params"]
    split = tmp_path / "split"
    cfg = load_config(None, small(name) + RESUME + ["run.max_steps=4"])
    cfg.data.clips = [str(clip)]
    assert train(cfg, split, stop_at=2)["step"] == 2
    half = load_checkpoint(split / "checkpoints" / "last.pt")
    assert main(["train", "-o", str(split), "--resume"]) == 0
    a = load_checkpoint(straight / "checkpoints" / "last.pt")
    b = load_checkpoint(split / "checkpoints" / "last.pt")
    assert a["step"] == b["step"] == 4
    for k, v in a["model"].items():  # parameters and any running statistics (NSRD's BatchNorm)
        assert torch.equal(v, b["model"][k]), k
    assert not torch.equal(half["model"][case["moved"]], a["model"][case["moved"]])  # steps 3 and 4 moved it


def test_evaluation_runs_the_clip_in_order_from_its_start(clip, checkpoint):
    from training import metrics
    from training.evaluate import EvalOptions, evaluate_model
    from training.inference.loading import ClipFrames, load_model
    model = load_model(str(checkpoint), 4)
    ref = _manual(model, clip, [1, 2, 3, 4])
    src = ClipFrames(clip)
    for frames in ([1, 2, 3, 4], [3, 4]):  # scored frames starting later: the earlier ones run first
        res = evaluate_model(model, [clip], EvalOptions(frames={str(clip): frames}, flip=False, warmup=1))
        assert [r["frame"] for r in res["per_frame"]] == frames
        for row in res["per_frame"]:
            gt = src.read(row["frame"], "hr/radiance")
            assert row["psnr"] == pytest.approx(metrics.psnr_tm(ref[row["frame"]], gt), abs=1e-4)


def test_lead_in_is_the_run_of_frames_before_the_first_scored_one():
    assert lead_in([1, 2, 3, 5, 6], 6) == [5] and lead_in([1, 2, 3], 1) == []


def test_upscale_carries_the_state_and_a_jump_reruns_from_the_clip_start(clip, checkpoint, tmp_path):
    from training.inference.loading import ClipFrames, load_model, upscale_frame
    model = load_model(str(checkpoint), 4)
    ref = _manual(model, clip, [1, 2, 3, 4])
    src = ClipFrames(clip)
    np.testing.assert_allclose(upscale_frame(model, src, 4)["sr"], ref[4], atol=1e-5)  # a jump
    for f in (1, 2, 3):  # in order
        np.testing.assert_allclose(upscale_frame(model, src, f)["sr"], ref[f], atol=1e-5)
    assert main(["upscale", "--checkpoint", str(checkpoint), "--clip", str(clip), "-o", str(tmp_path / "up")]) == 0


def test_onnx_export_carries_the_state_over_three_frames(name, clip, checkpoint, tmp_path):
    path = tmp_path / "m.onnx"
    assert main(["export", "--checkpoint", str(checkpoint), "--onnx", str(path), "--clip", str(clip)]) == 0
    report = json.loads(path.with_suffix(".onnx.json").read_text())
    assert report["recurrent"] and report["frames_checked"] == 3 and report["match"], report
    assert len(report["max_abs_diff_per_frame"]) == 3
    assert set(report["state"]) == {f"state_{i}" for i in range(CASES[name]["states"])}
    if name == "nsrd":
        assert "lr_motion_next" in report["inputs"]
    if name == "nsrr-fec":  # the feature cache as state; the HR G-buffers as inputs
        assert report["state"] == {f"state_{i}": [1, 12, 32, 48] for i in range(4)}
        assert {"hr_albedo", "hr_metallic", "hr_normal", "hr_roughness", "hr_specular"} <= set(report["inputs"])
        assert report["inputs"]["hr_metallic"] == [1, 1, 1, 32, 48]


def test_bench_models_row(name, clip, checkpoint, tmp_path):
    from training.bench import BenchOptions, benchmark, load_models
    from training.inference.loading import load_model
    flip = name == "nsrr-fec"  # FLIP (the slow metric) and a baseline row beside the checkpoint, each for one model
    baseline = [("bicubic", "bicubic")] if name == "rdg-s" else []
    res = benchmark(load_models([(f"{name} (x)", str(checkpoint)), *baseline], 4), [str(clip)], tmp_path / "b",
                    BenchOptions(flip=flip, warmup=0, log=lambda m: None))
    row = res["rows"][0]
    assert row["params"] == n_params(load_model(str(checkpoint), 4).module)
    assert row["params"] == n_params(build_model(load_config(None, small(name)).model, 4))
    if CASES[name]["params"] is not None:
        assert row["params"] == CASES[name]["params"]
    assert row["macs_per_px"] > 0
    for key in ("psnr", "ssim", "tpsnr", "warp_error") + (("flip",) if flip else ()):
        assert row[key] is not None, key


def frames_batch(model, h, w, frames=3):
    """``frames`` frames of random plausible inputs (``training.inference.export.example_inputs``, one seed a frame), LR h x w."""
    from training.inference.export import example_inputs
    per = [example_inputs(model, None, (w * model.scale, h * model.scale), seed=s) for s in range(frames)]
    return {k: torch.from_numpy(np.concatenate([p[k] for p in per], 1) if per[0][k].ndim >= 2 else per[0][k])
            for k in per[0]}


@pytest.mark.parametrize("model_name", MODELS + ["rdg"])  # full-size RDG: only here (cheap untrained)
def test_state_is_carried_and_reset_is_a_clip_start(model_name):
    from training.config import ModelConfig
    from training.models.window import frame_slice
    torch.manual_seed(0)
    model = build_model(ModelConfig(name=model_name), 4).eval()
    h, w = (5, 7) if model_name == "nsrd" else (6, 8)  # NSRD: not a multiple of 4, the U-Net's padding
    batch = frames_batch(model, h, w)
    with torch.no_grad():
        sr0, s0 = model.step(frame_slice(batch, 0), None)
        sr1, s1 = model.step(frame_slice(batch, 1), s0)
        fresh1, _ = model.step(frame_slice(batch, 1), None)
        sr2, _ = model.step(frame_slice(batch, 2), s1)
        torch.testing.assert_close(model(batch), sr2)  # forward = every frame from a reset state, the last SR
        assert not torch.allclose(sr1, fresh1)  # the state matters
        # reset = 1 ignores whatever state is passed; reset = 0 uses it
        junk = [torch.randn_like(s) for s in s0]
        r1, _ = model.step(frame_slice(batch, 1), junk, torch.ones(1))
        r0, _ = model.step(frame_slice(batch, 1), s0, torch.zeros(1))
    torch.testing.assert_close(r1, fresh1)
    torch.testing.assert_close(r0, sr1)
    size = (4 * h, 4 * w) if model_name == "fourier-sr" else (h, w)  # fourier-sr's state is at the HR size
    assert [tuple(s.shape) for s in s0] == model.state_shapes(*size)
    assert sr0.shape == (1, 3, 4 * h, 4 * w) and torch.isfinite(sr0).all()
    if model_name in ("rdg", "rdg-s"):
        torch.testing.assert_close(s0[3], batch["lr_jitter"][:, 0])  # the state carries the frame's jitter
