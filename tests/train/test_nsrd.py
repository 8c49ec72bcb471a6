"""NSRD (training/models/nsrd.py): parameter counts, the dual-motion-vector mask against the numpy core, the warps
(accumulated LR motion with jitter, HR motion times the scale), remodulation, ONNX export at scales 2 and 4 run at
another size. State carried and reset, training, resume, evaluation, the 3-frame ONNX check and ``bench models``:
tests/train/test_recurrent_models.py."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)  # 2 threads on a shared 2-core machine can be 10x slower

from gbuffer_export import disocclusion as np_disocclusion  # noqa: E402
from training.config import ModelConfig  # noqa: E402
from training.models import build_model  # noqa: E402
from training.models import nsrd as nsrd_mod  # noqa: E402
from training.models.resample import upsample  # noqa: E402
from training.models.window import frame_slice  # noqa: E402



def make_batch(scale=4, h=6, w=8, frames=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    lr = lambda c: torch.rand(1, frames, c, h, w, generator=g)  # noqa: E731
    hr = lambda c: torch.rand(1, frames, c, h * scale, w * scale, generator=g)  # noqa: E731
    depth = 1 + 5 * lr(1)
    depth[..., 0, :] = float("inf")  # background row
    # a panning camera (one motion per frame) and forward motion leading back, except on an occluder's pixels
    pan = 2 * torch.rand(1, frames + 1, 2, 1, 1, generator=g) - 1
    motion = pan[:, :frames].expand(-1, -1, -1, h, w).clone()
    motion_next = -pan[:, 1:].expand(-1, -1, -1, h, w).clone()
    motion_next[..., 0, 2:4, 2:5] += 2.0
    return {"lr/irradiance": 3 * lr(3), "lr/normal": lr(3) - 0.5, "lr/depth": depth, "lr/motion": motion,
            "lr/motion_next": motion_next, "depth_ref": torch.full((1, frames), 3.0),
            "hr/fbeta_used": 0.1 + hr(3), "hr/emission": 0.1 * hr(3),
            "lr_jitter": torch.rand(1, frames, 2, generator=g) - 0.5}


def n_params(m):
    return sum(p.numel() for p in m.parameters())


def test_parameter_counts_equal_the_authors_code():
    assert n_params(build_model(ModelConfig(name="nsrd", jitter=False), 4)) == 1_610_852
    assert n_params(build_model(ModelConfig(name="nsrd"), 4)) == 1_610_852 + 2 * 9 * 32  # jitter channels
    # scale changes the previous-output conv (3 s^2 -> 32) and the last conv (32 -> 3 s^2)
    assert n_params(build_model(ModelConfig(name="nsrd", jitter=False), 2)) == 1_610_852 - 2 * 36 * 9 * 32 - 36


def test_mask_is_the_numpy_cores_dual_motion_vector_mask():
    rng = np.random.default_rng(0)
    h, w = 11, 14
    motion = np.broadcast_to([1.3, -0.7], (h, w, 2)).copy()  # a panning camera: consistent where mn = -motion
    mn = -motion + np.where(rng.random((h, w, 1)) < 0.15, rng.uniform(-1, 1, (h, w, 2)), 0.0)  # occluders
    j, jp = (0.2, -0.3), (-0.4, 0.1)
    ref = np_disocclusion.from_motion(motion, mn, jitter=j, jitter_prev=jp)
    t = lambda a: torch.from_numpy(a.transpose(2, 0, 1)[None].astype(np.float32))  # noqa: E731
    off = t(motion) + torch.tensor([j[0] - jp[0], j[1] - jp[1]]).view(1, 2, 1, 1)
    got = nsrd_mod.disocclusion(t(motion), t(mn), off)[0, 0].numpy().astype(bool)
    assert 0.2 < ref.mean() < 0.9
    np.testing.assert_array_equal(got, ref)
    assert nsrd_mod.TOL_PX == np_disocclusion.TOL_PX


def test_warps_masks_and_hr_motion(monkeypatch):
    """Frame t-1 is warped with motion + jitter difference, frame t-2 with the accumulated motion; the previous HR
    output with the LR motion upsampled at the jittered positions times the scale; masks are all 1 at a clip's start
    and the dual-motion-vector mask afterwards."""
    model = build_model(ModelConfig(name="nsrd"), 4).eval()
    batch = make_batch()
    warps, masks = [], []
    real_warp, real_gate = nsrd_mod.backward_warp, model.previous_conv.forward
    monkeypatch.setattr(nsrd_mod, "backward_warp", lambda x, m: (warps.append((x.shape[1], m.clone())),
                                                                  real_warp(x, m))[1])
    monkeypatch.setattr(model.previous_conv, "forward", lambda x: (masks.append(x[:, -1:].clone()), real_gate(x))[1])
    with torch.no_grad():
        _, s0 = model.step(frame_slice(batch, 0), None)
        assert all(bool((m == 1).all()) for m in masks)
        warps.clear(), masks.clear()
        model.step(frame_slice(batch, 1), s0)
    m, j = batch["lr/motion"][:, 1], batch["lr_jitter"][:, 1]
    off1 = m + (j - batch["lr_jitter"][:, 0]).view(1, 2, 1, 1)
    lr_feats = [mo for c, mo in warps if c == nsrd_mod.IN_CH]
    torch.testing.assert_close(lr_feats[0], off1)
    assert len(lr_feats) == 2 and not torch.allclose(lr_feats[1], off1)  # t-2: accumulated along the chain
    hr = [mo for c, mo in warps if c == 3]
    torch.testing.assert_close(hr[0], upsample(m, 4, "bilinear", j) * 4)
    want = nsrd_mod.disocclusion(m, batch["lr/motion_next"][:, 0], off1)
    torch.testing.assert_close(masks[0], want)
    assert 0 < float(want.mean()) < 1
    torch.testing.assert_close(masks[1], torch.maximum(want, real_warp(torch.ones_like(want), off1)[0]))


def test_output_is_remodulated_with_the_hr_fbeta_and_emission():
    model = build_model(ModelConfig(name="nsrd", remod_filter="NONE"), 4).eval()
    batch = make_batch()
    other = dict(batch, **{"hr/fbeta_used": 2 * batch["hr/fbeta_used"],
                           "hr/emission": torch.full_like(batch["hr/emission"], 0.5)})
    with torch.no_grad():
        out = model(batch)
        torch.testing.assert_close(model(other), 2 * (out - batch["hr/emission"][:, -1]) + 0.5)


@pytest.mark.parametrize("transform", ["log1p", "none"])
def test_zero_initialised_residual_head_is_demod_bilinear(transform):
    """residual + zero_init_head: a fresh network's every frame is demod-bilinear's (the base, a deviation)."""
    batch = make_batch()
    batch["lr/fbeta_used"] = torch.ones_like(batch["lr/irradiance"])
    batch["lr/fbeta_used"][..., 0, 1:3, 2:5] = 0.3  # a few demodulated pixels beside F_used = 1 ones (by class)
    batch["hr/fbeta_used"][..., 0, :8, :] = 1.0
    cfg = ModelConfig.of("nsrd", residual=True, zero_init_head=True, input_transform=transform)
    model = build_model(cfg, 4).eval()
    base = build_model(ModelConfig.of("demod-bilinear"), 4).eval()
    assert set(base.needs()) <= set(model.needs())
    assert n_params(model) == 1_610_852 + 2 * 9 * 32  # the option adds no parameter
    state = None
    with torch.no_grad():
        for i in range(batch["lr/irradiance"].shape[1]):
            cur = frame_slice(batch, i)
            sr, state = model.step(cur, state)
            want = base(cur)
            if transform == "none":
                assert torch.equal(sr, want)
            else:  # exp(log(1 + x)) - 1 rounds
                torch.testing.assert_close(sr, want, rtol=2e-6, atol=1e-6)
    with pytest.raises(Exception, match="zero_init_head"):
        ModelConfig.of("nsrd", zero_init_head=True)


@pytest.mark.parametrize("scale,residual", [(2, False), (4, False), (4, True)])
def test_onnx_export_at_scales_2_and_4_runs_at_another_size(scale, residual, tmp_path):
    """Untrained weights, random inputs: exported at an LR size that needs no padding (8 x 8), checked over 3 frames,
    then run at an odd LR size (10 x 7, padded inside the graph) against torch with the state carried."""
    import onnxruntime as ort
    from training.inference.export import example_inputs, export_onnx
    from training.inference.model import InferenceModel
    torch.manual_seed(0)
    model = build_model(ModelConfig.of("nsrd", residual=residual), scale).eval()
    report = export_onnx(InferenceModel(model), tmp_path / "m.onnx", hr_size=(scale * 8, scale * 8))
    assert report["match"] and report["frames_checked"] == 3
    sess = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    state, reset = None, np.ones(1, np.float32)
    feed_state = [np.zeros(s, np.float32) for s in model.state_shapes(7, 10)]
    for seed in (1, 2):
        inp = {k: v for k, v in example_inputs(model, None, (scale * 10, scale * 7), seed=seed).items()
               if k in model.needs()}
        with torch.no_grad():
            ref, state = model.step({k: torch.from_numpy(v) for k, v in inp.items()}, state)
        outs = sess.run(None, {**{k.replace("/", "_"): v for k, v in inp.items()},
                               **{f"state_{i}": s for i, s in enumerate(feed_state)}, "reset": reset})
        assert outs[0].shape == (1, 3, 7 * scale, 10 * scale)
        np.testing.assert_allclose(outs[0], ref.numpy(), atol=1e-4 * float(np.abs(ref.numpy()).max()) + 1e-5)
        feed_state, reset = outs[1:], np.zeros(1, np.float32)
