"""NSRR and NSRR-FEC: parameter counts, zero upsampling at the jittered positions, Y'CbCr, accumulative warping and
the feature cache (each cached map warped once per frame), base NSRR training and ONNX. NSRR-FEC state carried and
reset, training, resume, recurrent evaluation, ONNX with the cache as explicit state and ``bench models``:
tests/train/test_recurrent_models.py."""
import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)  # 2 threads on a shared 2-core machine can be 10x slower

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training.config import ModelConfig, load_config  # noqa: E402
from training.models import build_model  # noqa: E402
from training.models import nsrr_fec as nsrr_mod  # noqa: E402
from training.models.window import frame_slice  # noqa: E402
from tests.conftest import set_args  # noqa: E402


REPO = Path(__file__).resolve().parents[2]
SMALL = ["data.crop=8", "data.batch_size=2", "run.progress=false", "run.log_every=1", "run.amp=\"none\"",
         "data.window=3", "data.detach_every=2", "loss.pixel_weight=0.0", "loss.ssim_weight=1.0",
         "model.name=\"nsrr-fec\""]


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 7), hr_size=(64, 40), scale=4,
                               jitter=True)


def make_batch(scale=4, h=6, w=8, frames=5, seed=0, motion=None):
    g = torch.Generator().manual_seed(seed)
    lr = lambda c: torch.rand(1, frames, c, h, w, generator=g)  # noqa: E731
    hr = lambda c: torch.rand(1, frames, c, h * scale, w * scale, generator=g)  # noqa: E731
    depth = 1 + 5 * lr(1)
    depth[..., 0, :] = float("inf")  # background row
    mv = 2 * lr(2) - 1 if motion is None else torch.tensor(motion, dtype=torch.float32).view(1, 1, 2, 1, 1).expand(
        1, frames, 2, h, w).clone()
    return {"lr/radiance": 3 * lr(3), "lr/depth": depth, "lr/motion": mv, "depth_ref": torch.full((1, frames), 3.0),
            "lr_jitter": torch.rand(1, frames, 2, generator=g) - 0.5, "hr/albedo": hr(3), "hr/metallic": hr(1),
            "hr/normal": hr(3) - 0.5, "hr/roughness": hr(1), "hr/specular": 0.08 * hr(1)}


def n_params(m):
    return sum(p.numel() for p in m.parameters())


def conv_params(cin, cout):
    return cin * cout * 9 + cout


def test_parameter_counts():
    # base NSRR: the count other papers report (one feature extractor for all five frames)
    for scale in (2, 4):
        assert n_params(build_model(ModelConfig(name="nsrr"), scale)) == 535_023
    # the enhancement: a 9 -> 32 -> 32 -> 8 G-buffer extractor and 17 more input channels of the first U-Net conv
    extra = conv_params(9, 32) + conv_params(32, 32) + conv_params(32, 8) + 17 * 64 * 9
    assert extra == 23_976
    assert n_params(build_model(ModelConfig(name="nsrr-fec"), 4)) == 535_023 + extra == 558_999
    # the parts of the base count
    m = build_model(ModelConfig(name="nsrr"), 4)
    assert n_params(m.features) == 12_744 and n_params(m.reweight) == 16_196 and n_params(m.unet) == 506_083


def test_history_out_of_range_is_a_clear_error(clip, tmp_path):
    with pytest.raises(ValueError, match="model.history 0"):
        build_model(ModelConfig(name="nsrr", history=0), 4)
    assert main(["train", "--model", "nsrr", "--data", str(clip), "-o", str(tmp_path / "r"), "--max-steps", "1",
                 "--set", "model.history=0", "--set", "run.progress=false"]) == 2


@pytest.mark.parametrize("scale", [2, 4])
def test_zero_upsampling_puts_each_sample_at_its_jittered_hr_pixel(scale):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 4, 5, generator=g) + 0.1
    j = torch.tensor([[0.3, -0.45], [-0.2, 0.1]])
    y = nsrr_mod.zero_upsample(x, scale, j)
    ref = torch.zeros(2, 3, 4 * scale, 5 * scale)
    for b in range(2):
        for p in range(4):
            for q in range(5):  # sample of LR pixel (p, q) taken at ((q + 0.5 + jx), (p + 0.5 + jy)) LR pixels
                hx = int(np.floor((q + 0.5 + float(j[b, 0])) * scale))
                hy = int(np.floor((p + 0.5 + float(j[b, 1])) * scale))
                ref[b, :, hy, hx] = x[b, :, p, q]
    torch.testing.assert_close(y, ref)
    centre = nsrr_mod.zero_upsample(x, scale, None)  # no jitter: the pixel that holds the LR centre
    assert torch.equal(centre[:, :, scale // 2::scale, scale // 2::scale], x)
    assert int((centre != 0).sum()) == x.numel()


def test_current_frame_enters_in_bt709_ycbcr_and_leaves_through_its_inverse():
    to_ycbcr, to_rgb = nsrr_mod.ycbcr_matrices()
    np.testing.assert_allclose(to_ycbcr[0], [0.2126, 0.7152, 0.0722], atol=1e-12)  # BT.709 luma
    np.testing.assert_allclose(to_rgb @ to_ycbcr, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(to_ycbcr @ [1.0, 1.0, 1.0], [1.0, 0.0, 0.0], atol=1e-12)  # grey: no chroma
    model = build_model(ModelConfig(name="nsrr"), 4)
    batch = make_batch()
    rgbd = model.rgbd(batch, 0, ycbcr=True)
    t = torch.log1p(batch["lr/radiance"][:, -1])  # the input transform first, then the matrix
    y = 0.2126 * t[:, 0] + 0.7152 * t[:, 1] + 0.0722 * t[:, 2]
    torch.testing.assert_close(rgbd[:, 0], y, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(model.rgbd(batch, 1, ycbcr=False)[:, :3], torch.log1p(batch["lr/radiance"][:, -2]),
                               atol=1e-6, rtol=1e-6)


def _shift_x(f, k):
    """f sampled k HR pixels to the right (backward warp by +k px in x), 0 beyond the border."""
    out = torch.zeros_like(f)
    if k < f.shape[-1]:
        out[..., : f.shape[-1] - k] = f[..., k:]
    return out


def _capture(model, monkeypatch):
    seen = {}
    real = model.reconstruct

    def spy(cur, prev, batch):
        seen["cur"], seen["prev"] = cur, prev
        return real(cur, prev, batch)
    monkeypatch.setattr(model, "reconstruct", spy)
    return seen


def test_nsrr_warps_frame_t_minus_k_k_times(monkeypatch):
    """A pure translation of 1 HR pixel per frame: history frame t-k arrives shifted by k pixels."""
    model = build_model(ModelConfig(name="nsrr"), 4).eval()
    batch = make_batch(motion=(0.25, 0.0))  # LR motion 1/4 px = 1 HR px
    seen = _capture(model, monkeypatch)
    with torch.no_grad():
        model(batch)
        for k in range(1, 5):
            own = model.frame_features(batch, k, ycbcr=False)
            torch.testing.assert_close(seen["prev"][k - 1], _shift_x(own, k), atol=1e-5, rtol=1e-5)


def test_cache_maps_are_warped_once_per_frame(monkeypatch):
    """The cache after frame t holds [F_t, F_(t-1) .. F_(t-3)] in frame t's screen space: with a translation of
    1 HR pixel per frame the map of frame t-k used at frame t is F_(t-k) shifted by exactly k pixels (a second warp
    per frame would shift it by 2k), and every step warps exactly ``history`` maps."""
    model = build_model(ModelConfig(name="nsrr-fec"), 4).eval()
    batch = make_batch(frames=6, motion=(0.25, 0.0))
    calls = []
    real = nsrr_mod.backward_warp

    def counting(x, m):
        calls.append(x)
        return real(x, m)
    monkeypatch.setattr(nsrr_mod, "backward_warp", counting)
    seen = _capture(model, monkeypatch)
    own = []
    state = None
    with torch.no_grad():
        for t in range(6):
            sub = frame_slice(batch, t)
            own.append(model.frame_features(sub, 0, ycbcr=True))
            calls.clear()
            _, new = model.step(sub, state)
            assert len(calls) == (0 if state is None else 4)
            if state is not None:
                assert all(c is s for c, s in zip(calls, state))  # the cached maps themselves, once each
            torch.testing.assert_close(new[0], own[t])
            for k in range(1, 5):  # before frame k the history is the oldest frame's features
                src = max(t - k, 0)
                torch.testing.assert_close(seen["prev"][k - 1], _shift_x(own[src], t - src), atol=1e-5, rtol=1e-5)
            state = new


def test_gbuffers_enter_the_enhanced_model_only():
    batch = make_batch(frames=1)
    other = dict(batch, **{"hr/roughness": 1 - batch["hr/roughness"], "hr/albedo": batch["hr/albedo"] * 0.5})
    torch.manual_seed(0)
    fec = build_model(ModelConfig(name="nsrr-fec"), 4).eval()
    base = build_model(ModelConfig(name="nsrr"), 4).eval()
    assert not any(k.startswith("hr/") for k in base.needs())
    with torch.no_grad():
        assert not torch.allclose(fec(batch), fec(other))
        torch.testing.assert_close(base(batch), base(other))


def test_scale_2_pads_the_hr_frame_for_the_unet():
    batch = make_batch(scale=2, h=5, w=7, frames=2)
    for name in ("nsrr", "nsrr-fec"):
        with torch.no_grad():
            out = build_model(ModelConfig(name=name), 2).eval()(batch)
        assert out.shape == (1, 3, 10, 14) and torch.isfinite(out).all()


def test_example_config_is_the_papers_setting():
    cfg = load_config(REPO / "examples" / "nsrr_fec_config.toml")
    assert cfg.model.name == "nsrr-fec" and cfg.loss.pixel_weight == 0 and cfg.loss.ssim_weight == 1.0
    assert cfg.loss.perceptual_weight == 0 and cfg.optim.lr == 1e-4 and cfg.data.batch_size == 16
    assert cfg.data.crop * 4 == 512
    raw = tomllib.loads((REPO / "examples" / "nsrr_fec_config.toml").read_text())
    assert set(raw) == {"data", "model", "loss", "optim", "run"}


def test_base_nsrr_trains_on_five_frame_windows(clip, tmp_path):
    out = tmp_path / "base"
    assert main(["train", "--model", "nsrr", "--data", str(clip), "-o", str(out), "--max-steps", "2",
                 *set_args([s for s in SMALL if not s.startswith(("data.window", "data.detach", "model.name"))])]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["params"] == 535_023 and summary["window"] is None


def test_base_nsrr_exports_to_onnx(tmp_path):
    from training.inference.export import export_onnx
    from training.inference.model import InferenceModel
    model = build_model(ModelConfig(name="nsrr"), 4).eval()
    report = export_onnx(InferenceModel(model), tmp_path / "nsrr.onnx", hr_size=(32, 24))
    assert report["match"] and report["inputs"]["lr_radiance"] == [1, 5, 3, 6, 8]
