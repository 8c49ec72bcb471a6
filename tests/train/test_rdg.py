"""RDG / RDG-s and the recurrent path: parameter counts, CycleFC against the deformable-sampling definition, the
warp's motion per level, window batches, truncated backprop. State carried and reset, training, resume, evaluation,
upscale, ONNX and ``bench models`` of every recurrent model: tests/train/test_recurrent_models.py."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)  # 2 threads on a shared 2-core machine can be 10x slower

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training.config import ModelConfig  # noqa: E402
from training.models import build_model  # noqa: E402
from training.models import rdg as rdg_mod  # noqa: E402
from training.models.window import frame_slice  # noqa: E402



@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 6), hr_size=(64, 36), scale=4,
                               jitter=True)


def make_batch(scale=4, h=6, w=8, frames=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    lr = lambda c: torch.rand(1, frames, c, h, w, generator=g)  # noqa: E731
    depth = 1 + 5 * lr(1)
    depth[..., 0, :] = float("inf")  # background row
    return {"lr/radiance": 3 * lr(3), "lr/normal": lr(3) - 0.5, "lr/fbeta": lr(3), "lr/depth": depth,
            "lr/motion": 2 * lr(2) - 1, "depth_ref": torch.full((1, frames), 3.0),
            "lr_jitter": torch.rand(1, frames, 2, generator=g) - 0.5}


def n_params(m):
    return sum(p.numel() for p in m.parameters())


def test_parameter_counts_equal_the_authors():
    # without the jitter channels exactly the published counts; jitter adds 2 input channels to the 3x3 shallow conv
    assert n_params(build_model(ModelConfig(name="rdg", jitter=False), 4)) == 1_473_600
    assert n_params(build_model(ModelConfig(name="rdg-s", jitter=False), 4)) == 303_680
    assert n_params(build_model(ModelConfig(name="rdg"), 4)) == 1_473_600 + 2 * 9 * 36
    assert n_params(build_model(ModelConfig(name="rdg-s"), 4)) == 303_680 + 2 * 9 * 16
    # scale changes only the head (3 s^2 output channels)
    assert n_params(build_model(ModelConfig(name="rdg-s", jitter=False), 2)) == 303_680 - 16 * 9 * 36 - 36


@pytest.mark.parametrize("k,axis", [(7, "h"), (7, "v")])
def test_cyclefc_is_deformable_sampling_with_the_cyclemlp_offsets(k, axis):
    """Eq. 1 of the paper written as a loop: out[:, o, i, j] = b_o + sum_c w_oc x[c, i + di(c), j + dj(c)] (0 outside),
    with the authors' offsets (c + k // 2) mod k - k // 2 along the sampling axis."""
    torch.manual_seed(0)
    c, h, w = 10, 5, 9
    m = rdg_mod.CycleFC(c, k, axis)
    x = torch.randn(2, c, h, w)
    ref = torch.zeros(2, c, h, w)
    wt = m.weight[:, :, 0, 0].detach()
    for ch in range(c):
        s = (ch + k // 2) % k - k // 2
        di, dj = (0, s) if axis == "h" else (s, 0)
        shifted = torch.zeros(2, h, w)
        for i in range(h):
            for j in range(w):
                if 0 <= i + di < h and 0 <= j + dj < w:
                    shifted[:, i, j] = x[:, ch, i + di, j + dj]
        ref += wt[:, ch].view(1, c, 1, 1) * shifted[:, None]
    ref += m.bias.detach().view(1, c, 1, 1)
    torch.testing.assert_close(m(x).detach(), ref, atol=1e-5, rtol=1e-5)


def test_warp_uses_the_current_frames_motion_scaled_per_level_plus_the_jitter_difference(monkeypatch):
    model = build_model(ModelConfig(name="rdg-s"), 4).eval()
    batch = make_batch(h=8, w=8)
    seen = []
    real = rdg_mod.backward_warp

    def spy(x, motion):
        seen.append(motion.clone())
        return real(x, motion)
    with torch.no_grad():
        _, s0 = model.step(frame_slice(batch, 0), None)
        assert not seen  # no warp at a clip's first frame
        monkeypatch.setattr(rdg_mod, "backward_warp", spy)
        model.step(frame_slice(batch, 1), s0)
    full = batch["lr/motion"][:, 1] + (batch["lr_jitter"][:, 1] - batch["lr_jitter"][:, 0]).view(1, 2, 1, 1)
    assert [tuple(m.shape[-2:]) for m in seen] == [(2, 2), (4, 4), (8, 8)]
    torch.testing.assert_close(seen[2], full)
    for m, r in zip(seen[:2], (4, 2)):
        torch.testing.assert_close(m, torch.nn.functional.interpolate(full, size=m.shape[-2:], mode="bilinear") / r)


@pytest.mark.parametrize("drop", ["normal", "brdf", "depth", "motion"])
def test_ablation_switches_remove_a_gbuffer(drop):
    keep = [g for g in rdg_mod.GBUFFERS if g != drop]
    model = build_model(ModelConfig.of(name="rdg-s", gbuffers=keep), 4).eval()
    key = {"normal": "lr/normal", "brdf": "lr/fbeta", "depth": "lr/depth", "motion": "lr/motion"}[drop]
    assert key not in model.needs()
    batch = make_batch()
    other = dict(batch)
    other[key] = batch[key] * 2 + 1
    with torch.no_grad():
        torch.testing.assert_close(model(batch), model(other))
    full = build_model(ModelConfig(name="rdg-s"), 4).eval()
    with torch.no_grad():
        assert not torch.allclose(full(batch), full(other))
    assert n_params(model) == n_params(full)


def test_losses_difference_and_rfft_match_closed_forms():
    from training.losses import difference_loss, fft_loss
    g = torch.Generator().manual_seed(0)
    a, b, c, d = (torch.rand(1, 3, 8, 6, generator=g) for _ in range(4))
    ref = (((a - b) - (c - d)) ** 2).mean()
    torch.testing.assert_close(difference_loss(a, b, c, d), ref)
    fa, fb = np.fft.rfft2(a.numpy()), np.fft.rfft2(c.numpy())
    ref = np.mean(np.abs(np.stack([(fa - fb).real, (fa - fb).imag])))
    assert float(fft_loss(a, c, "rfft")) == pytest.approx(ref, rel=1e-5)


def test_window_batches_hold_a_target_for_every_frame(clip):
    from training.cache import ClipCache
    from training.data import BatchSpec, TrainSampler
    model = build_model(ModelConfig(name="rdg-s"), 4)
    spec = BatchSpec.for_model(model, temporal=True, window=4, crop=8)
    assert spec.lr_window == spec.hr_window == 4 and "hr/motion" in spec.hr_keys
    cache = ClipCache(clip).ensure(spec.cache_keys)
    sampler = TrainSampler([cache], spec, 2, seed=0)
    batch, samples = sampler.batch(0)
    assert batch["hr/radiance"].shape == (2, 4, 3, 32, 32) and batch["lr/radiance"].shape == (2, 4, 3, 8, 8)
    assert batch["lr_jitter"].shape == (2, 4, 2)
    for s in samples:
        assert s.frames == list(range(s.frames[0], s.frames[0] + 4))
    frames = cache.frames
    for i, s in enumerate(samples):  # frame t's target is that frame's HR radiance (no augmentation here)
        pos = frames.index(s.frames[-1])
        hr = np.asarray(cache.array("hr/radiance")[pos - 3: pos + 1], np.float32)
        assert not (s.aug.flip_x or s.aug.flip_y or s.aug.transpose) and s.aug.exposure == 1.0
        x0, y0 = 4 * s.x0, 4 * s.y0
        np.testing.assert_array_equal(batch["hr/radiance"][i], hr[:, y0:y0 + 32, x0:x0 + 32].transpose(0, 3, 1, 2))


def test_window_applies_to_recurrent_models_only(clip, tmp_path):
    rc = main(["train", "--model", "fusesr-l", "--data", str(clip), "-o", str(tmp_path / "r"), "--max-steps", "1",
               "--set", "data.window=3", "--set", "run.progress=false"])
    assert rc == 2


def test_truncated_backprop_equals_full_backprop_when_the_chunk_covers_the_window():
    """detach_every >= T: one backward of the mean loss; detach_every = 1: no gradient crosses frames."""
    from training.config import LossConfig
    from training.losses import Criterion
    from training.recurrent import StepWrapper, window_losses
    torch.manual_seed(0)
    model = build_model(ModelConfig.of(name="rdg-s", width=8), 4)
    batch = make_batch(frames=3)
    batch["hr/radiance"] = torch.rand(1, 3, 3, 24, 32)
    crit = Criterion(LossConfig(ssim_weight=0.0, pixel="charbonnier"))
    from contextlib import nullcontext

    def grads(detach_every):
        model.zero_grad()
        loss, _, _ = window_losses(StepWrapper(model), crit, batch, detach_every, lambda x: x.backward(), False,
                                   nullcontext)
        return loss, [p.grad.clone() for p in model.parameters() if p.grad is not None]
    loss_full, g_full = grads(3)
    model.zero_grad()
    ref = 0.0
    state = None
    for t in range(3):
        sr, state = model.step(frame_slice(batch, t), state)
        ref = ref + crit(sr, batch["hr/radiance"][:, t])[0] / 3
    ref.backward()
    g_ref = [p.grad.clone() for p in model.parameters() if p.grad is not None]
    assert float(loss_full) == pytest.approx(float(ref.detach()), rel=1e-6)
    for a, b in zip(g_full, g_ref):
        torch.testing.assert_close(a, b)
    loss_1, g_1 = grads(1)
    assert float(loss_1) == pytest.approx(float(ref.detach()), rel=1e-6)  # same forward values, other gradients
    assert any(not torch.allclose(a, b) for a, b in zip(g_1, g_full))


def test_demodulated_rdg_remodulates_with_the_hr_fbeta():
    cfg = ModelConfig.of(name="rdg-s", demod=True, remod_filter="NONE")
    model = build_model(cfg, 4).eval()
    assert {"lr/irradiance", "hr/fbeta_used", "hr/emission"} <= set(model.needs())
    assert "lr/radiance" not in model.needs()
    batch = make_batch()
    batch["lr/irradiance"] = batch.pop("lr/radiance")
    g = torch.Generator().manual_seed(1)
    batch["hr/fbeta_used"] = 0.1 + torch.rand(1, 3, 3, 24, 32, generator=g)
    batch["hr/emission"] = torch.zeros(1, 3, 3, 24, 32)
    with torch.no_grad():
        out = model(batch)
        other = dict(batch, **{"hr/fbeta_used": 2 * batch["hr/fbeta_used"],
                               "hr/emission": torch.full((1, 3, 3, 24, 32), 0.5)})
        torch.testing.assert_close(model(other), 2 * out + 0.5)
