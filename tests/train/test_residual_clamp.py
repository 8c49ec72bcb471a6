"""The FuseSR family's ``residual_clamp = "lr-range"`` and ``"lr-guided"`` (training/models/fusesr.py, "Bounded
correction"): the clamp binds where the network leaves the LR range of its base's taps (lr-guided: of the taps of
the pixel's surface, none where there are none) and nowhere else, the fused torch stage does the same, the gradient
passes where it does not bind, and a trained model keeps the option through its checkpoint.
The fused path and the Triton kernels against the reference with the clamp on: tests/train/hr_stage_cases.py."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.errors import BlendSRError  # noqa: E402
from gbuffer_export.typed_table import ConfigError  # noqa: E402
from training.config import ModelConfig  # noqa: E402
from training.inference.export import example_inputs  # noqa: E402
from training.kernels import hr_stage  # noqa: E402
from training.kernels.spec import HRStage  # noqa: E402
from training.models import build_model  # noqa: E402
from training.models.base import current  # noqa: E402
from training.transforms import forward_transform  # noqa: E402
from tests.conftest import set_args  # noqa: E402


def _pair(name, **opts):
    """(clamped, unclamped) models with the same weights."""
    torch.manual_seed(0)
    on = build_model(ModelConfig.of(name, residual_clamp="lr-range", **opts), 4).eval()
    off = build_model(ModelConfig.of(name, **opts), 4).eval()
    off.load_state_dict(on.state_dict())
    return on, off


def _batch(model, size=(48, 32), seed=3):
    return {k: torch.from_numpy(v) for k, v in example_inputs(model, None, size, seed=seed).items()}


def _output(model, batch, y):
    """The model's output stage (residual base, ReLU, T^-1, clamp, remodulation) for a network output ``y``."""
    color = forward_transform(current(batch, model.color_key), model.transform)
    return model.output(y, color, batch, model.frame_jitter(batch))


def test_clamp_pins_a_runaway_output_to_a_flat_lr_input():
    """LR irradiance constant per channel: its range is one value, so a network output far above or below
    (+3 and -5 in the transformed space) comes out as exactly demod-jbu's output; without the option it does not."""
    on, off = _pair("fusesr-fast")
    batch = _batch(on)
    lr = batch["lr/irradiance"]
    batch["lr/irradiance"] = torch.tensor([0.3, 0.5, 0.7]).view(1, 1, 3, 1, 1).expand_as(lr).clone()
    jbu = build_model(ModelConfig.of("demod-jbu"), 4).eval()
    y = torch.full((1, 3, 32, 48), 3.0)
    y[..., 16:, :] = -5.0
    with torch.no_grad():
        want = jbu(batch)
        got, free = _output(on, batch, y), _output(off, batch, y)
    assert float((got - want).abs().max()) <= 1e-5 * float(want.abs().max())
    assert float((free - want).abs().amax(dim=(1, 2, 3))) > 1.0  # the unclamped output runs away


def _tap_range_numpy(lr: np.ndarray, s: int) -> tuple[np.ndarray, np.ndarray]:
    """Per HR pixel, min and max of the LR image (C, h, w) over its 4 bilinear taps (no jitter, borders clamped),
    by loops."""
    c, h, w = lr.shape
    lo, hi = np.empty((c, h * s, w * s), np.float32), np.empty((c, h * s, w * s), np.float32)
    for y in range(h * s):
        fy = int(np.floor((y + 0.5) / s - 0.5))
        ys = {min(max(fy, 0), h - 1), min(max(fy + 1, 0), h - 1)}
        for x in range(w * s):
            fx = int(np.floor((x + 0.5) / s - 0.5))
            xs = {min(max(fx, 0), w - 1), min(max(fx + 1, 0), w - 1)}
            taps = lr[:, sorted(ys)][:, :, sorted(xs)].reshape(c, -1)
            lo[:, y, x], hi[:, y, x] = taps.min(axis=1), taps.max(axis=1)
    return lo, hi


@pytest.mark.parametrize("margin", [0.0, 0.5])
def test_clamp_bounds_by_the_lr_taps_and_leaves_the_base_alone(margin):
    """Radiance model (no remodulation), no jitter, no classes: a network output of 0 is the guided base and passes
    unchanged (the base is a convex combination of the taps); +-50 comes out at the taps' max / min widened by
    ``margin`` of their width (numpy loops)."""
    on, off = _pair("fusesr-fast", demodulation=False, jitter=False, upsample_by_class=False,
                    residual_clamp_margin=margin)
    batch = _batch(on, size=(24, 16))
    zero = torch.zeros(1, 3, 16, 24)
    with torch.no_grad():
        assert torch.allclose(_output(on, batch, zero), _output(off, batch, zero), rtol=1e-6, atol=0)
        up, down = _output(on, batch, zero + 50.0), _output(on, batch, zero - 50.0)
    lo, hi = _tap_range_numpy(batch["lr/radiance"][0, -1].numpy(), 4)
    pad = margin * (hi - lo)
    np.testing.assert_allclose(up[0].numpy(), hi + pad, rtol=2e-5)
    np.testing.assert_allclose(down[0].numpy(), np.maximum(lo - pad, 0.0), rtol=2e-5, atol=1e-6)
    assert float((hi - lo).min()) >= 0 and float((hi - lo).max()) > 0.1  # the ranges are not trivial


def _guided_range_numpy(lr, g_lr, g_hr, s):
    """Per HR pixel, min and max of the LR image (C, h, w) over those of its 4 bilinear taps (no jitter, borders
    clamped) whose guide (G, h, w) lies within exp(-d^2 / 2) >= 0.5 of the pixel's (G, H, W); NaN where none does.
    By loops."""
    c, h, w = lr.shape
    lo, hi = np.full((2, c, h * s, w * s), np.nan, np.float32)
    for y in range(h * s):
        fy = int(np.floor((y + 0.5) / s - 0.5))
        for x in range(w * s):
            fx = int(np.floor((x + 0.5) / s - 0.5))
            taps = [(min(max(fy + a, 0), h - 1), min(max(fx + b, 0), w - 1)) for a in (0, 1) for b in (0, 1)]
            near = [lr[:, i, j] for i, j in taps if np.exp(-0.5 * ((g_lr[:, i, j] - g_hr[:, y, x]) ** 2).sum()) >= 0.5]
            if near:
                lo[:, y, x], hi[:, y, x] = np.min(near, axis=0), np.max(near, axis=0)
    return lo, hi


def test_guided_clamp_bounds_by_the_taps_of_the_pixels_surface_and_leaves_other_pixels_free():
    """``lr-guided``, radiance model, no jitter or classes: +-50 come out at the max / min of the similar taps
    (numpy loops over the guides), and unchanged, as without the clamp, where no tap is similar; both kinds occur."""
    from training.models.guided import guide_features
    torch.manual_seed(0)
    opts = dict(demodulation=False, jitter=False, upsample_by_class=False, guide_sigma_depth=2.0,
                guide_sigma_normal=1.0)
    on = build_model(ModelConfig.of("fusesr-fast", residual_clamp="lr-guided", **opts), 4).eval()
    off = build_model(ModelConfig.of("fusesr-fast", **opts), 4).eval()
    batch = _batch(on, size=(24, 16))
    zero = torch.zeros(1, 3, 16, 24)
    with torch.no_grad():
        up, down = _output(on, batch, zero + 50.0), _output(on, batch, zero - 50.0)
        free_up, free_down = _output(off, batch, zero + 50.0), _output(off, batch, zero - 50.0)
    g_lr, g_hr = (guide_features(current(batch, f"{lv}/depth"), current(batch, f"{lv}/normal"), 2.0, 1.0)[0].numpy()
                  for lv in ("lr", "hr"))
    lo, hi = _guided_range_numpy(batch["lr/radiance"][0, -1].numpy(), g_lr, g_hr, 4)
    open_ = np.isnan(lo)
    assert 0.05 < open_[0].mean() < 0.95, open_[0].mean()
    np.testing.assert_allclose(up[0].numpy()[~open_], hi[~open_], rtol=2e-5, atol=1e-6)  # log1p's round trip
    np.testing.assert_allclose(down[0].numpy()[~open_], np.maximum(lo[~open_], 0.0), rtol=2e-5, atol=1e-6)
    np.testing.assert_allclose(up[0].numpy()[open_], free_up[0].numpy()[open_], rtol=1e-6)
    np.testing.assert_allclose(down[0].numpy()[open_], free_down[0].numpy()[open_], rtol=1e-6, atol=1e-7)


def test_fused_torch_stage_clamp_binds_and_the_triton_spec_round_trips():
    """The fused stage with ``clamp`` differs from it without on inputs whose network output leaves the range (so
    the interpreter comparisons of hr_stage_cases.py compare a clamp that binds); the kernel's flat parameter list
    keeps the clamp."""
    from tests.train.hr_stage_cases import SPECS, _inputs
    spec = next(s for s in SPECS if s.clamp is not None and s.by_class)
    t = _inputs(1, 3, 5, spec.scale, False, True)
    t = t._replace(net=t.net * 4.0)
    got = hr_stage.hr_stage_torch(spec, t)
    free = hr_stage.hr_stage_torch(HRStage(**{**spec.__dict__, "clamp": None}), t)
    assert float((got - free).abs().max()) > 0.1 * float(free.abs().max())
    pytest.importorskip("triton")
    from training.kernels.hr_triton import _spec_of, _spec_params
    for s in SPECS:
        assert _spec_of(_spec_params(s)) == s


def test_gradient_passes_where_the_clamp_does_not_bind():
    """Piecewise the identity: d out / d y is the unclamped model's where the clamp leaves the value alone and 0
    where it binds, and both kinds of pixel occur."""
    on, off = _pair("fusesr-l", remod_filter="NONE")  # no pixel filter: each output pixel reads its own y
    batch = _batch(on, size=(32, 16))
    y = (torch.randn(1, 3, 16, 32, generator=torch.Generator().manual_seed(1)) * 0.5).requires_grad_(True)
    g_on, = torch.autograd.grad(_output(on, batch, y).sum(), y)
    y2 = y.detach().clone().requires_grad_(True)
    g_off, = torch.autograd.grad(_output(off, batch, y2).sum(), y2)
    with torch.no_grad():
        same = torch.isclose(_output(on, batch, y), _output(off, batch, y), rtol=1e-6, atol=0)
    bound = ~same
    assert 0 < int(bound.sum()) < bound.numel()
    free = same & (g_off.abs() > 0)
    assert int(free.sum()) > 0 and torch.allclose(g_on[free], g_off[free], rtol=1e-5, atol=1e-7)
    assert float(g_on[bound].abs().max()) == 0.0


def test_the_option_needs_the_residual_head():
    with pytest.raises(ConfigError, match=r"model.fusesr.residual_clamp needs model.fusesr.residual = true"):
        ModelConfig.of("fusesr", residual_clamp="lr-range", residual=False)
    with pytest.raises(ConfigError, match="choose one of none, lr-range, lr-guided"):
        ModelConfig.of("fusesr-l", residual_clamp="taa")
    with pytest.raises(ConfigError, match=r"lr-guided\" needs model.fusesr-fast.guided_upsample = true"):
        ModelConfig.of("fusesr-fast", residual_clamp="lr-guided", guided_upsample=False)


def test_trained_with_the_clamp_it_loads_with_it_and_a_checkpoint_takes_only_inference_options(tmp_path):
    """A few training steps with the option on (the loss is finite, the weights move), the checkpoint keeps it,
    ``load_model`` builds it so, and CK?residual_clamp=none / --set turn it off; a weight-shaping key is refused."""
    from gbuffer_export.cli import main
    from gbuffer_export.synthetic import make_synthetic_clip
    from training.checkpoint import load_checkpoint
    from training.inference.loading import load_model
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)
    run = tmp_path / "run"
    sets = ["data.crop=8", "data.batch_size=2", "run.progress=false", "run.amp=\"none\"", "run.threads=0",
            "model.fusesr-l.width=8", "model.fusesr-l.blocks=1", "model.history=0",
            "model.fusesr-l.residual_clamp=\"lr-range\"", "model.fusesr-l.residual_clamp_margin=0.25"]
    assert main(["train", "--model", "fusesr-l", "--data", str(clip), "-o", str(run), "--max-steps", "2",
                 *set_args(sets)]) == 0
    ck_path = run / "checkpoints" / "last.pt"
    ck = load_checkpoint(ck_path)
    assert ck["config"]["model"]["fusesr-l"]["residual_clamp"] == "lr-range" and ck["step"] == 2
    model = load_model(str(ck_path), 4, fast=False)
    assert model.module.clamp == 0.25
    assert load_model(f"{ck_path}?residual_clamp=none", 4, fast=False).module.clamp is None
    assert load_model(str(ck_path), 4, ["model.fusesr-l.residual_clamp_margin=1.5"], fast=False).module.clamp == 1.5
    with pytest.raises(BlendSRError, match="configuration is fixed except its inference options"):
        load_model(f"{ck_path}?width=16", 4)
    with pytest.raises(BlendSRError, match="expected MODEL\\?KEY=VALUE"):
        load_model(f"{ck_path}?lr-range", 4)
    from training.bench import load_models, parse_models  # NAME:CHECKPOINT?KEY=VALUE, as bench models reads
    rows = load_models(parse_models(f"fusesr-l:{ck_path},fusesr-l:{ck_path}?residual_clamp=none"), 4, fast=False)
    assert [r[0] for r in rows] == ["fusesr-l (run)", "fusesr-l (run?residual_clamp=none)"]
    assert rows[0][1].module.clamp == 0.25 and rows[1][1].module.clamp is None


def test_guided_clamp_exports_to_onnx_and_matches_torch(tmp_path):
    """A shipped network run with ``lr-guided`` (``CK?KEY=VALUE`` on the command line) exports (the ONNX trace reads
    the shapes as tensors) and
    onnxruntime matches torch on a jittered synthetic clip."""
    import json

    from gbuffer_export.cli import main
    from gbuffer_export.synthetic import make_synthetic_clip
    from training import pretrained
    pytest.importorskip("onnxruntime")
    if not (pretrained.WEIGHTS_DIR / pretrained.PRETRAINED["fusesr-fast"]).is_file():
        pytest.skip("fusesr-fast not shipped")
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 3), hr_size=(64, 36), scale=4, jitter=True)
    onnx = tmp_path / "m.onnx"
    assert main(["export", "--checkpoint", "pretrained:fusesr-fast?residual_clamp=lr-guided", "--onnx", str(onnx),
                 "--clip", str(clip)]) == 0
    assert json.loads((tmp_path / "m.onnx.json").read_text())["match"]
