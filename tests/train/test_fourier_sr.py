"""fourier-sr: the authors' layer sizes, Eq. 2 against a per-pixel evaluation, any scale (integer or not), the
jittered sub-pixel offsets, the state (never remodulated), evaluation at a scale never trained on, ONNX export with
the scale as an input. State carried and reset, training, bit-identical resume, recurrent evaluation,
upscale, the 3-frame ONNX check and ``bench models``: tests/train/test_recurrent_models.py."""
import json
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)  # 2 threads on a shared 2-core machine can be 10x slower

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training.config import ModelConfig  # noqa: E402
from training.models import build_model  # noqa: E402
from training.models import fourier_sr as fsr  # noqa: E402
from training.transforms import inverse_transform  # noqa: E402
from tests.conftest import set_args  # noqa: E402


SMALL = ["data.crop=8", "data.batch_size=2", "run.progress=false", "run.log_every=1", "run.amp=\"none\"",
         "data.window=3", "data.detach_every=2", "loss.ssim_weight=0.0", "loss.temporal_weight=0.3",
         "run.checkpoint_every=100", "optim.decay_steps=4", "data.prefetch=1"]


def make_batch(h=6, w=8, scale=2.0, frames=2, seed=0, with_scale=True):
    """Random inputs of every key fourier-sr reads, HR = round(LR x scale)."""
    g = torch.Generator().manual_seed(seed)
    big_h, big_w = round(h * scale), round(w * scale)
    lr = lambda c: torch.rand(1, frames, c, h, w, generator=g)  # noqa: E731
    hr = lambda c: torch.rand(1, frames, c, big_h, big_w, generator=g)  # noqa: E731
    depth, hdepth = 1 + 5 * lr(1), 1 + 5 * hr(1)
    depth[..., 0, :] = float("inf")
    hdepth[..., :2, :] = float("inf")
    batch = {"lr/irradiance": 2 * lr(3), "lr/depth": depth, "lr/normal": lr(3) - 0.5, "lr/albedo": lr(3),
             "hr/depth": hdepth, "hr/normal": hr(3) - 0.5, "hr/albedo": hr(3), "hr/motion": 2 * hr(2) - 1,
             "hr/fbeta_used": 0.05 + hr(3), "hr/emission": 0.1 * hr(3), "depth_ref": torch.full((1, frames), 3.0),
             "lr_jitter": torch.rand(1, frames, 2, generator=g) - 0.5}
    if with_scale:
        batch["scale"] = torch.tensor([float(scale)])
    return batch


def model_at(scale=2, seed=0, **kw):
    torch.manual_seed(seed)
    return build_model(ModelConfig(name="fourier-sr", **kw), scale).eval()


def n_params(m):
    return sum(p.numel() for p in m.parameters())


def test_parameter_count_is_the_authors_at_every_scale():
    """Sizes of the authors' OursNet (lr_hidc = hr_hidc = 32, mlpc = 64, pixel shuffle on), counted by hand."""
    m = model_at(2)
    parts = {name: n_params(c) for name, c in m.named_children()}
    assert parts == {"lr_extractor": 896 + 13872 + 20784 + 27712,           # 3-32-48-48-64 3x3
                     "hr_extractor": 18496 + 3 * 2 * 36928 + 2 * 36928,     # 32->64, 3 double residual, 2 dilated
                     "temporal": 2 * (9248 + 289) + (4624 + 289),           # gated 32-32-32-16
                     "fusion": 46144 + 27696 + 5196,                        # 80-64-48-12
                     "coef": 18496, "freq": 18496, "mlp": 3 * 4160 + 780, "hf_conv": 1308, "last": 84}
    assert n_params(m) == 531883 == n_params(model_at(4)) == n_params(model_at(2.5))
    assert m.phase.numel() == 32  # P(r): one weight per frequency pair, no bias
    with pytest.raises(ValueError, match="any scale >= 1"):
        build_model(ModelConfig(name="fourier-sr"), 0)


def test_hffm_is_eq2_evaluated_per_pixel_with_the_jittered_offset():
    """The MLP's input equals F_i(x*) [cos(pi (F_G . 2(x - x*) + w / s)), sin(...)] computed pixel by pixel."""
    m = model_at(2)
    g = torch.Generator().manual_seed(3)
    h, w, big_h, big_w, s = 3, 4, 8, 10, 2.5   # half HR 4 x 5
    amp, feat = torch.randn(1, 32, h, w, generator=g), torch.randn(1, 32, big_h // 2, big_w // 2, generator=g)
    scale, jit = torch.tensor([s]), torch.tensor([[0.3, -0.2]])
    qx, qy = fsr.lr_positions(big_w // 2, 2, scale, jit[:, 0]), fsr.lr_positions(big_h // 2, 2, scale, jit[:, 1])
    seen = {}
    m.mlp.register_forward_hook(lambda mod, inp, out: seen.update(x=inp[0]))  # returns None: output kept
    with torch.no_grad():
        m.hffm(amp, feat, qx, qy, scale)
        coef, freq = m.coef(amp)[0], m.freq(feat)[0]
    for yy in range(big_h // 2):
        for xx in range(big_w // 2):
            ux = (2 * xx + 1) / s - 0.3    # half-HR pixel centre on the LR sampling grid: (2 (k + 0.5) / s) - jitter
            uy = (2 * yy + 1) / s + 0.2
            ix, iy = min(max(math.floor(ux), 0), w - 1), min(max(math.floor(uy), 0), h - 1)
            dx, dy = 2 * (ux - ix - 0.5), 2 * (uy - iy - 0.5)
            f = freq[:, yy, xx].view(32, 2)
            arg = f[:, 0] * dx + f[:, 1] * dy + m.phase.detach() / s
            want = coef[:, iy, ix] * torch.cat([torch.cos(math.pi * arg), torch.sin(math.pi * arg)])
            torch.testing.assert_close(seen["x"][0, :, yy, xx], want, rtol=1e-5, atol=1e-5)


def test_hffm_depends_on_the_sub_pixel_offset_and_on_one_over_the_scale():
    m = model_at(2)
    g = torch.Generator().manual_seed(4)
    amp, feat = torch.randn(1, 32, 4, 4, generator=g), torch.randn(1, 32, 4, 4, generator=g)
    qx = qy = torch.tensor([[0.5, 1.5, 2.5, 3.5]])  # every position at an LR sample: offset 0
    with torch.no_grad():
        base = m.hffm(amp, feat, qx, qy, torch.tensor([2.0]))
        moved = m.hffm(amp, feat, qx + 0.3, qy, torch.tensor([2.0]))     # same nearest samples, offset 0.3
        rescaled = m.hffm(amp, feat, qx, qy, torch.tensor([3.0]))        # same positions, phase w / 3
        m.phase.zero_()
        no_phase_2 = m.hffm(amp, feat, qx, qy, torch.tensor([2.0]))
        no_phase_3 = m.hffm(amp, feat, qx, qy, torch.tensor([3.0]))
    assert (moved - base).abs().max() > 1e-3
    assert (rescaled - base).abs().max() > 1e-3
    torch.testing.assert_close(no_phase_2, no_phase_3)  # the scale enters the HFFM through the phase only


def test_nearest_sample_and_offset_follow_the_lr_jitter():
    """At scale 2 the half-HR centre k + 0.5 (LR pixels) sits on LR sample k without jitter; with jitter j the
    sample was taken at k + 0.5 + j, so the offset is -j; beyond half a pixel the nearest sample is the next one."""
    s = torch.tensor([2.0])
    for j in (0.0, 0.25, -0.4):
        p = fsr.lr_positions(5, 2, s, torch.tensor([j]))
        centre, off = fsr.nearest_offsets(p, 5)
        np.testing.assert_allclose(off.numpy(), np.full((1, 5), -j), atol=1e-6)
        np.testing.assert_allclose(centre.numpy(), np.arange(5)[None] + 0.5)
    p = fsr.lr_positions(5, 2, s, torch.tensor([0.7]))  # sample of pixel k at k + 1.2: x = k + 0.5 is nearer k - 1
    centre, off = fsr.nearest_offsets(p, 5)
    np.testing.assert_allclose(centre.numpy()[0, 1:], np.arange(4) + 0.5)
    np.testing.assert_allclose(off.numpy()[0, 1:], 0.3, atol=1e-6)


@pytest.mark.parametrize("scale", [2, 2.5, 3, 4])
def test_any_scale_maps_lr_to_hr_and_the_state_has_the_hr_size(scale):
    m = model_at(2)
    batch = make_batch(6, 8, scale)   # 2.5: HR 15 x 20 (an odd height)
    big_h, big_w = round(6 * scale), round(8 * scale)
    with torch.no_grad():
        sr, state = m.step({k: (v[:, :1] if v.dim() >= 2 else v) for k, v in batch.items()})
        sr2, state2 = m.step({k: (v[:, 1:] if v.dim() >= 2 else v) for k, v in batch.items()}, state)
        whole = m(batch)
    assert sr.shape == sr2.shape == (1, 3, big_h, big_w) and torch.isfinite(sr2).all()
    assert [tuple(x.shape) for x in state2] == m.state_shapes(big_h, big_w)
    torch.testing.assert_close(whole, sr2)
    if float(scale).is_integer():  # today's batches have no "scale": the size ratio gives the same result
        with torch.no_grad():
            torch.testing.assert_close(m({k: v for k, v in batch.items() if k != "scale"}), whole)


def test_the_state_is_the_demodulated_prediction_and_hr_radiance_is_never_read():
    """The authors remodulate the output in place, so their state is radiance; here it stays T(L_D^HR): the SR is
    its remodulation, and neither HR F_beta nor the ground truth (even where the albedo is 0) changes it."""
    m = model_at(2, remod_filter="NONE")
    batch = make_batch(6, 8, 2)
    batch["hr/albedo"][..., :4, :] = 0.0
    batch["hr/radiance"] = torch.rand_like(batch["hr/fbeta_used"])
    with torch.no_grad():
        sr, state = m.step(batch)
        want = inverse_transform(state[0], "log1p") * batch["hr/fbeta_used"][:, -1] + batch["hr/emission"][:, -1]
        torch.testing.assert_close(sr, want)
        other = dict(batch, **{"hr/fbeta_used": batch["hr/fbeta_used"] * 2, "hr/radiance": batch["hr/radiance"] + 1})
        sr_b, state_b = m.step(other)
    torch.testing.assert_close(state_b[0], state[0])
    torch.testing.assert_close(sr_b - batch["hr/emission"][:, -1], 2 * (sr - batch["hr/emission"][:, -1]))


def test_temporal_masks_and_reset():
    """Eq. 7-10 on a static scene with zero motion are 0; the ONNX reset input gives the first-frame output."""
    cur = torch.rand(1, 7, 5, 6)
    cur[:, 1:4] /= cur[:, 1:4].norm(dim=1, keepdim=True)
    assert fsr.temporal_masks(cur, cur).abs().max() < 1e-6
    flipped = cur.clone()
    flipped[:, 1:4] *= -1
    torch.testing.assert_close(fsr.temporal_masks(cur, flipped)[:, 1], torch.ones(1, 5, 6))
    m = model_at(2)
    batch = make_batch(6, 8, 2, frames=1)
    with torch.no_grad():
        first, state = m.step(batch)
        again, _ = m.step(batch, state, torch.ones(1))
        carried, _ = m.step(batch, state, torch.zeros(1))
    torch.testing.assert_close(again, first)
    assert (carried - first).abs().max() > 1e-6


def test_spatial_mask_thresholds_are_options():
    hr = torch.zeros(1, 7, 2, 2)
    hr[:, 3] = 1.0  # normal +Z
    up = hr.clone()
    up[:, 0, 0, 0] = 0.02                      # depth off by 0.02
    up[:, 4:7, 0, 1] = 0.2                     # albedo off by 0.2
    up[:, 1, 1, 0], up[:, 3, 1, 0] = 1.0, 1.0  # 45 degrees: cosine 0.707
    mask = fsr.spatial_mask(hr, up, fsr.FourierSROptions())
    assert mask[0, 0].tolist() == [[1.0, 1.0], [1.0, 0.0]]
    loose = fsr.FourierSROptions(mask_depth=0.05, mask_albedo=0.3, mask_normal=0.5)
    assert fsr.spatial_mask(hr, up, loose).sum() == 0
    assert fsr.FourierSR(2).opts == fsr.FourierSROptions()
    assert fsr.FourierSR(2, mask_depth=0.02).opts.mask_depth == 0.02


# ------------------------------------------------------------------------------------------ training and the rest
@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    root = tmp_path_factory.mktemp("fsr")
    return {2: make_synthetic_clip(root / "x2", frames=range(1, 6), hr_size=(32, 24), scale=2, jitter=True),
            4: make_synthetic_clip(root / "x4", frames=range(1, 4), hr_size=(64, 36), scale=4, jitter=True)}


@pytest.fixture(scope="module")
def trained(clips, tmp_path_factory):
    """A checkpoint trained (2 steps) at scale 2. Training and bit-identical resume: tests/train/test_recurrent_models.py."""
    from training.checkpoint import load_checkpoint
    run = tmp_path_factory.mktemp("runs") / "x2"
    assert main(["train", "--model", "fourier-sr", "--data", str(clips[2]), "-o", str(run), "--max-steps", "2",
                 *set_args(SMALL)]) == 0
    ck = run / "checkpoints" / "last.pt"
    assert load_checkpoint(ck)["scale"] == 2
    return ck


def test_evaluates_at_a_scale_it_never_trained_on(trained, clips, tmp_path):
    from training.inference.loading import load_model
    ck = trained
    out = tmp_path / "x4.json"
    assert main(["evaluate", "--checkpoint", str(ck), "--data", str(clips[4]), "--json", str(out), "--no-flip",
                 "--warmup", "0"]) == 0
    res = json.loads(out.read_text())
    assert res["scale"] == 4 and res["mean"]["frames"] == 3 and math.isfinite(res["mean"]["psnr"])
    model = load_model(str(ck), 4)  # the scale-2 weights at scale 4
    assert model.module.scale == 4 and model.n_params == 531883


def test_onnx_export_takes_the_scale_as_an_input_and_matches_torch_at_two_scales(tmp_path):
    import onnxruntime as ort

    from training.inference.export import export_onnx
    from training.inference.model import InferenceModel
    m = model_at(2)
    path = tmp_path / "fsr.onnx"
    report = export_onnx(InferenceModel(m), path, hr_size=(32, 24))
    assert report["match"] and report["recurrent"] and "scale" in report["inputs"]
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [i.name for i in sess.get_inputs()]
    assert names[-1] == "reset" and "scale" in names
    keys = [k for k in m.needs()] + ["scale"]
    for scale, (h, w) in ((2, (12, 16)), (3, (8, 10))):
        batch = make_batch(h, w, scale, frames=2, seed=scale)
        state, feed = None, [np.zeros((1, 3, h * scale, w * scale), np.float32),
                             np.zeros((1, 7, h * scale, w * scale), np.float32)]
        reset = np.ones(1, np.float32)
        for t in range(2):
            sub = {k: (v[:, t:t + 1] if v.dim() >= 2 else v) for k, v in batch.items()}
            with torch.no_grad():
                want, state = m.step(sub, state)
            inputs = {k.replace("/", "_"): sub[k].numpy() for k in keys}
            got = sess.run(None, {**inputs, "state_0": feed[0], "state_1": feed[1], "reset": reset})
            assert got[0].shape == (1, 3, h * scale, w * scale)
            np.testing.assert_allclose(got[0], want.numpy(), rtol=1e-4, atol=1e-4 * float(want.abs().max()))
            feed, reset = got[1:], np.zeros(1, np.float32)


def test_the_trainers_temporal_term_is_not_a_second_l1():
    """The authors warp SR_t-1 on both sides ((SR_t - W(SR_t-1)) - (GT_t - W(SR_t-1)) = SR_t - GT_t); BlendSR's
    ``warped`` term warps GT_t-1 for the target, so an error constant in time costs nothing there."""
    from training.losses import temporal_loss
    g = torch.Generator().manual_seed(5)
    gt_prev, gt = torch.rand(1, 3, 8, 8, generator=g), torch.rand(1, 3, 8, 8, generator=g)
    motion = torch.zeros(1, 2, 8, 8)
    assert float(temporal_loss(gt + 0.2, gt_prev + 0.2, gt, gt_prev, motion)) < 1e-6
    assert float((gt + 0.2 - gt).abs().mean()) == pytest.approx(0.2)


def test_the_example_configuration_builds_fourier_sr():
    from pathlib import Path

    from training.config import load_config
    cfg = load_config(Path(__file__).parents[2] / "examples" / "fourier_sr_config.toml", [])
    assert cfg.model.name == "fourier-sr" and cfg.data.window == 8 and cfg.loss.temporal == "warped"
    assert n_params(build_model(cfg.model, 4)) == 531883


@pytest.mark.parametrize("scale,lr", [(2, 40), (4, 20)])
def test_macs_per_hr_pixel_are_the_weights_at_their_resolutions(scale, lr):
    """Torch's flop counter against the weights: LR convolutions count 1 / s^2 per HR pixel, half-HR ones 1 / 4, the
    last 3x3 conv 1 (docs/models/fourier_sr.md quotes these)."""
    from torch.utils.flop_counter import FlopCounterMode
    m = model_at(2, remod_filter="NONE")

    def weights(mod):
        return sum(p.numel() for n, p in mod.named_parameters() if n.endswith("weight"))
    half = sum(weights(getattr(m, n)) for n in ("hr_extractor", "temporal", "fusion", "freq", "mlp", "hf_conv"))
    want = (weights(m.lr_extractor) + weights(m.coef)) / scale ** 2 + half / 4 + weights(m.last)
    counter = FlopCounterMode(display=False)
    with torch.no_grad(), counter:
        m(make_batch(lr, lr, scale, frames=1))
    assert counter.get_total_flops() / 2 / (lr * scale) ** 2 == pytest.approx(want, rel=1e-9)
    print(f"fourier-sr x{scale}: {want:.0f} MACs per HR pixel")
