"""Models: the torch warp against the numpy reference, baselines against closed forms, FuseSR switches, config."""

from pathlib import Path

import numpy as np
import pytest

from gbuffer_export import pixel_filter as pf

torch = pytest.importorskip("torch")
torch.set_num_threads(1)  # 2 threads on a shared 2-core machine can be 10x slower

from gbuffer_export.config import ConfigError  # noqa: E402
from gbuffer_export.conventions import backward_warp as np_warp  # noqa: E402
from training.config import ModelConfig, TrainConfig, config_from_dict, dict_to_toml, load_config  # noqa: E402
from training.models import MODELS, build_model  # noqa: E402
from training.models.base import backward_warp, history_offsets, upsample  # noqa: E402
from training.models.fusesr import FuseSR  # noqa: E402



def t(a):
    return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None].float()


def test_torch_warp_matches_numpy_reference():
    rng = np.random.default_rng(0)
    img = rng.random((13, 17, 3)).astype(np.float32)
    motion = (rng.random((13, 17, 2)) * 8 - 4).astype(np.float32)
    motion[0, 0] = (-30, 0)  # leaves the image
    ref, valid = np_warp(img, motion)
    out, v = backward_warp(t(img), t(motion))
    np.testing.assert_array_equal(v[0, 0].numpy().astype(bool), valid)
    np.testing.assert_allclose(out[0].numpy().transpose(1, 2, 0), ref, atol=1e-5)
    # chained motion t -> t-2
    m2 = (rng.random((13, 17, 2)) * 4 - 2).astype(np.float32)
    batch = {"lr/motion": torch.stack([t(np.zeros_like(m2))[0], t(m2)[0], t(motion)[0]])[None]}
    off1, off2 = (o[0].numpy().transpose(1, 2, 0) for o in history_offsets(batch, 2, use_jitter=False))
    np.testing.assert_array_equal(off1, motion)
    np.testing.assert_allclose(off2, motion + np_warp(m2, motion)[0], atol=1e-5)
    # with jitter: the offsets gain j_t - j_(t-k), and frame t-1's motion is read at the corrected offset
    j = torch.tensor([[[0.3, -0.1], [-0.2, 0.25], [0.1, 0.4]]])
    o1, o2 = (o[0].numpy().transpose(1, 2, 0) for o in history_offsets({**batch, "lr_jitter": j}, 2, True))
    d1, d2 = (j[0, 2] - j[0, 1]).numpy(), (j[0, 2] - j[0, 0]).numpy()
    np.testing.assert_allclose(o1, motion + d1, atol=1e-6)
    np.testing.assert_allclose(o2, motion + np_warp(m2, motion + d1)[0] + d2, atol=1e-5)


def make_batch(scale=4, h=6, w=8, frames=3, seed=0, hr_frames=1):
    g = torch.Generator().manual_seed(seed)
    H, W = h * scale, w * scale
    lr = lambda c: torch.rand(1, frames, c, h, w, generator=g)  # noqa: E731
    hr = lambda c: torch.rand(1, hr_frames, c, H, W, generator=g)  # noqa: E731
    depth = 1 + 5 * lr(1)
    depth[..., 0, :] = float("inf")  # background row
    hdepth = 1 + 5 * hr(1)
    hdepth[..., :scale, :] = float("inf")
    return {"lr/radiance": lr(3), "lr/irradiance": lr(3) * 2, "lr/depth": depth, "lr/normal": lr(3) - 0.5,
            "lr/motion": 2 * lr(2) - 1, "lr/motion_next": 2 * lr(2) - 1,
            "hr/fbeta_used": 0.05 + hr(3), "hr/emission": 0.1 * hr(3),
            "hr/depth": hdepth, "hr/normal": hr(3) - 0.5, "hr/albedo": hr(3), "hr/metallic": hr(1),
            "hr/roughness": hr(1), "hr/specular": 0.08 * hr(1),
            "depth_ref": torch.full((1, frames), 3.0), "lr_jitter": torch.rand(1, frames, 2, generator=g) - 0.5,
            "lr/fbeta_used": 0.05 + lr(3), "lr/fbeta": 0.05 + lr(3), "lr/albedo": lr(3),
            "hr/motion": 2 * hr(2) - 1}


@pytest.mark.parametrize("name", list(MODELS))
@pytest.mark.parametrize("scale", [4, 8])
def test_every_model_maps_lr_to_hr(name, scale):
    model = build_model(ModelConfig(name=name), scale).eval()
    batch = make_batch(scale)
    with torch.no_grad():
        out = model(batch)
    assert out.shape == (1, 3, 6 * scale, 8 * scale) and torch.isfinite(out).all()
    assert set(model.needs()) <= set(batch)
    assert MODELS[name].learned == any(True for _ in model.parameters())


def _np(x):
    return x[0].permute(1, 2, 0).detach().numpy()


def test_demod_bilinear_is_remodulation_of_upsampled_irradiance():
    batch = make_batch()
    batch["lr/irradiance"][:] = 0.7  # constant irradiance: bilinear keeps it, so SR = K * (0.7 F_HR + E_HR)
    point = 0.7 * batch["hr/fbeta_used"][:, -1] + batch["hr/emission"][:, -1]
    out = build_model(ModelConfig(name="demod-bilinear", remod_filter="NONE"), 4)(batch)
    torch.testing.assert_close(out, point)
    out = build_model(ModelConfig(name="demod-bilinear"), 4)(batch)  # default: Blackman-Harris 1.5 px
    np.testing.assert_allclose(_np(out), pf.convolve(_np(point), pf.weights_1d("BLACKMAN_HARRIS", 1.5)),
                               rtol=1e-5, atol=1e-6)


def test_fusesr_remodulates_point_samples_then_applies_the_reference_filter():
    batch = make_batch()
    torch.manual_seed(0)
    plain = build_model(ModelConfig(name="fusesr", remod_filter="NONE"), 4).eval()
    filtered = build_model(ModelConfig(name="fusesr", remod_filter="GAUSSIAN", remod_filter_px=1.5), 4).eval()
    filtered.load_state_dict(plain.state_dict())  # the kernel is not a parameter: old checkpoints load
    with torch.no_grad():
        a, b = plain(batch), filtered(batch)
    np.testing.assert_allclose(_np(b), pf.convolve(_np(a), pf.weights_1d("GAUSSIAN", 1.5)), rtol=1e-4, atol=1e-5)
    nodemod = build_model(ModelConfig.of(name="fusesr", demodulation=False), 4)
    assert nodemod.remod_filter_mismatch({"render": {"hr": {"pixel_filter": "BOX", "filter_width_px": 1}}}, "c") \
        is None  # radiance models are not remodulated
    msg = plain.remod_filter_mismatch({}, "c")
    assert msg is None  # NONE never complains
    msg = filtered.remod_filter_mismatch({"render": {"hr": {"pixel_filter": "BLACKMAN_HARRIS",
                                                            "filter_width_px": 1.5}}}, "clipdir")
    assert msg.startswith("clipdir: the ground truth was rendered with the BLACKMAN_HARRIS 1.5 px")


def test_bicubic_is_clamped_and_bilinear_preserves_constants():
    batch = make_batch()
    batch["lr/radiance"][:] = 0.0
    batch["lr/radiance"][..., 2, 3] = 5.0  # a spike: bicubic rings negative, clamped at 0
    batch["lr_jitter"][:] = 0.0
    out = build_model(ModelConfig(name="bicubic"), 4)(batch)
    raw = torch.nn.functional.interpolate(batch["lr/radiance"][:, -1], scale_factor=4, mode="bicubic")
    assert raw.min() < 0 and out.min() == 0
    torch.testing.assert_close(out, raw.clamp(min=0), atol=1e-5, rtol=1e-5)
    batch["lr/radiance"][:] = 0.25
    assert torch.allclose(build_model(ModelConfig(name="bilinear"), 4)(batch), torch.full((1, 3, 24, 32), 0.25))


def _changes_output(model, batch, key, frame_index):
    with torch.no_grad():
        a = model(batch)
        b2 = {k: v.clone() for k, v in batch.items()}
        b2[key][:, frame_index] += 0.5
        b = model(b2)
    return not torch.allclose(a, b)


def test_fusesr_reads_history_and_hr_gbuffers_and_the_switches_remove_them():
    torch.manual_seed(0)
    batch = make_batch()
    full = FuseSR(4, upsample_by_class=False, guided_upsample=False).eval()
    assert full.history == 2 and full.window == 3
    assert _changes_output(full, batch, "lr/irradiance", 0)      # history frame t-2
    assert _changes_output(full, batch, "hr/albedo", -1)         # HR G-buffer branch
    no_hr = FuseSR(4, hr_gbuffer=False).eval()
    assert "hr/albedo" not in no_hr.needs() and "hr/fbeta_used" in no_hr.needs()
    assert not {"hr/depth", "hr/normal"} & set(no_hr.needs())  # no guided base without the HR G-buffers
    assert not _changes_output(no_hr, batch, "hr/albedo", -1)
    no_demod = FuseSR(4, demodulation=False).eval()
    assert "lr/radiance" in no_demod.needs() and "lr/irradiance" not in no_demod.needs()
    assert not _changes_output(no_demod, batch, "lr/irradiance", -1)
    plain = FuseSR(4, demodulation=False, hr_gbuffer=False).eval()
    assert not any(k.startswith("hr/") for k in plain.needs())
    assert _changes_output(full, batch, "lr_jitter", -1)          # the current frame's jitter
    assert _changes_output(full, batch, "lr_jitter", 0)           # history alignment
    no_jit = FuseSR(4, jitter=False).eval()
    assert "lr_jitter" not in no_jit.needs() and not _changes_output(no_jit, batch, "lr_jitter", -1)
    # residual head: with the last convolution zeroed the output is the bilinear upsampling of T(L_D) remodulated
    from training.transforms import forward_transform, inverse_transform
    with torch.no_grad():
        full.refine.weight.zero_()
        full.refine.bias.zero_()
        up = upsample(forward_transform(batch["lr/irradiance"][:, -1], "log1p"), 4, "bilinear",
                      batch["lr_jitter"][:, -1])
        expect = inverse_transform(up.clamp(min=0), "log1p") * batch["hr/fbeta_used"][:, -1] \
            + batch["hr/emission"][:, -1]  # point samples, then the ground truth's pixel filter
        np.testing.assert_allclose(_np(full(batch)), pf.convolve(_np(expect), pf.weights_1d("BLACKMAN_HARRIS", 1.5)),
                                   rtol=1e-5, atol=1e-5)
    authors = FuseSR(4, residual=False, remod_filter="NONE").eval()
    with torch.no_grad():
        authors.refine.weight.zero_()
        authors.refine.bias.zero_()
        assert torch.equal(authors(batch), batch["hr/emission"][:, -1])  # L_D = 0: only the emission is left
    # demodulation on: the output is remodulated by the HR F_beta (zero F_beta and emission -> zero output)
    b0 = {k: v.clone() for k, v in batch.items()}
    b0["hr/fbeta_used"][:] = 0
    b0["hr/emission"][:] = 0
    with torch.no_grad():
        assert torch.equal(no_hr(b0), torch.zeros(1, 3, 24, 32))


def test_fusesr_light_has_no_history_and_depthwise_separable_fusion():
    light = build_model(ModelConfig(name="fusesr-l"), 4).eval()
    full = build_model(ModelConfig(name="fusesr"), 4)
    assert light.history == 0 and "lr/motion" not in light.needs()
    assert not _changes_output(light, make_batch(), "lr/irradiance", 0)
    dw = [m for m in light.blocks.modules() if isinstance(m, torch.nn.Conv2d) and m.groups > 1]
    assert len(dw) == 2 * 6 and all(m.groups == m.in_channels == 64 for m in dw)
    n_light = sum(p.numel() for p in light.parameters())
    n_full = sum(p.numel() for p in full.parameters())
    assert n_light < 0.2 * n_full
    # the authors' layer sizes: encoder 7 -> 64, 6 residual blocks of 128 channels, 10-channel HR branch
    assert full.encoder.shallow[0].in_channels == 7 and full.encoder.shallow[0].out_channels == 64
    assert len(full.blocks) == 6 and full.blocks[0].conv1.in_channels == 128
    assert full.hr_branch[0].in_channels == 10 * 16


def test_config_rejects_unknown_keys_and_bad_values(tmp_path):
    with pytest.raises(ConfigError, match="unknown key data.crops"):
        config_from_dict({"data": {"crops": 3}})
    with pytest.raises(ConfigError, match=r"unknown section \[train\]"):
        config_from_dict({"train": {}})
    with pytest.raises(ConfigError, match="data.crop: expected an integer"):
        config_from_dict({"data": {"crop": "big"}})
    with pytest.raises(ConfigError, match="model.name 'esrgan'"):
        config_from_dict({"model": {"name": "esrgan"}})
    with pytest.raises(ConfigError, match="vgg_weights"):
        config_from_dict({"loss": {"perceptual_weight": 0.5}})
    with pytest.raises(ConfigError, match="loss.space"):
        load_config(None, ["loss.space=srgb"])
    with pytest.raises(ConfigError, match="data.reflectance_range"):
        load_config(None, ["data.reflectance_range=[2.0, 0.5]"])
    with pytest.raises(ConfigError, match="data.exposure_range"):
        load_config(None, ["data.exposure_range=[1.0]"])
    p = tmp_path / "c.toml"
    p.write_text('[data]\ncrop = 32\nexposure_range = [1, 3]\n[optim]\nlr = 1e-3\n')
    cfg = load_config(p, ["data.crop=48", "run.amp=bf16", "model.name=fusesr-l"])
    assert cfg.data.crop == 48 and cfg.data.exposure_range == [1.0, 3.0] and cfg.optim.lr == 1e-3
    assert cfg.run.amp == "bf16" and cfg.model.name == "fusesr-l"
    back = tmp_path / "back.toml"
    back.write_text(cfg.to_toml())
    assert load_config(back).to_dict() == cfg.to_dict()
    assert dict_to_toml({"a": {"s": 'x"y'}}) == '[a]\ns = "x\\"y"\n'
    assert TrainConfig().validate().model.name == "fusesr"
    example = Path(__file__).resolve().parents[2] / "examples" / "train_config.toml"
    assert load_config(example).data.val_frames == 8


@pytest.mark.parametrize("mode", ["bilinear", "bicubic"])
def test_jittered_upsampling_moves_the_samples_to_their_jittered_positions(mode):
    x = torch.rand(2, 3, 6, 8, generator=torch.Generator().manual_seed(1))
    plain = torch.nn.functional.interpolate(x, scale_factor=4, mode=mode, align_corners=False)
    torch.testing.assert_close(upsample(x, 4, mode, torch.zeros(2, 2)), plain, atol=1e-5, rtol=1e-5)
    # LR samples taken 0.25 LR px = 1 HR px right of / 0.5 LR px = 2 HR px below their centres: the image moves
    # right by 1 and down by 2 HR pixels (away from the clamped borders)
    j = torch.tensor([[0.25, 0.5], [0.25, 0.5]])
    torch.testing.assert_close(upsample(x, 4, mode, j)[..., 8:-8, 8:-8], plain[..., 6:-10, 7:-9], atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("name", ["bilinear", "bicubic", "demod-bilinear", "fusesr"])
def test_model_jitter_false_ignores_a_batch_jitter(name):
    batch = make_batch()
    model = build_model(ModelConfig(name=name, jitter=False), 4).eval()
    assert "lr_jitter" not in model.needs()
    with torch.no_grad():
        torch.testing.assert_close(model(batch), model({**batch, "lr_jitter": batch["lr_jitter"] + 0.3}))


def test_fusesr_hr_guide_reads_the_hr_gbuffers_at_full_resolution():
    """model.hr_guide: the refinement sees the HR G-buffers directly; with the LR-side HR branch zeroed, one HR depth
    pixel still changes the output, and only within the refinement's 5x5 footprint (two 3x3 convs)."""
    from training.config import ConfigError
    torch.manual_seed(0)
    batch = make_batch()
    guided = FuseSR(4, hr_guide=True, remod_filter="NONE").eval()
    plain = FuseSR(4, remod_filter="NONE").eval()
    assert not plain.hr_guide and guided.hr_guide
    assert sum(p.numel() for p in guided.parameters()) - sum(p.numel() for p in plain.parameters()) == \
        (13 * 16 * 9 + 16) + (16 * 3 * 9 + 3) - (3 * 3 * 9 + 3)
    with torch.no_grad():
        for p in guided.hr_branch.parameters():
            p.zero_()
        a = guided(batch)
        b2 = {k: v.clone() for k, v in batch.items()}
        b2["hr/depth"][:, -1, :, 10, 12] *= 3.0
        diff = (guided(b2) - a).abs().amax(dim=(0, 1))
    assert diff[10, 12] > 0
    far = torch.ones_like(diff, dtype=torch.bool)
    far[8:13, 10:15] = False
    assert diff[far].max() == 0
    with pytest.raises(ConfigError, match="model.fusesr.hr_guide needs model.fusesr.hr_gbuffer"):
        ModelConfig.of(name="fusesr", hr_guide=True, hr_gbuffer=False)


def test_upsample_by_class_never_mixes_demodulated_and_unit_fbeta_pixels():
    """LR L_D constant a on demodulated pixels and b where F_used = 1: every HR pixel with a same-class LR neighbour
    gets exactly its class's constant (plain bilinear mixes them at the borders), the others the plain value; with
    one class everywhere it is plain bilinear. Checked with jitter, at 4x."""
    from training.models.base import demodulated_mask, upsample_by_class
    g = torch.Generator().manual_seed(3)
    h, w, s = 6, 8, 4
    f_lr = torch.where(torch.rand(1, 1, h, w, generator=g) < 0.4, 1.0, 0.3).expand(-1, 3, -1, -1).clone()
    f_hr = torch.where(torch.rand(1, 1, h * s, w * s, generator=g) < 0.4, 1.0, 0.3).expand(-1, 3, -1, -1).clone()
    m_lr, m_hr = demodulated_mask(f_lr), demodulated_mask(f_hr)
    a, b = 20.0, 1.0  # an irradiance 20x a radiance
    x = (a * m_lr + b * (1 - m_lr)).expand(-1, 3, -1, -1)
    j = torch.tensor([[0.2, -0.3]])
    out = upsample_by_class(x, m_lr, m_hr, s, j)
    plain = upsample(x, s, "bilinear", j)
    for m_l, m_h, value in ((m_lr, m_hr, a), (1 - m_lr, 1 - m_hr, b)):
        reach = upsample(m_l, s, "bilinear", j) > 1e-6  # the bilinear footprint holds a pixel of this class
        sel = (reach & (m_h > 0.5)).expand_as(out)
        assert sel.any()
        torch.testing.assert_close(out[sel], torch.full_like(out[sel], value))
        orphan = (~reach & (m_h > 0.5)).expand_as(out)
        torch.testing.assert_close(out[orphan], plain[orphan])
    assert ((plain - a).abs() > 1).logical_and((plain - b).abs() > 1).any()  # plain bilinear does mix
    one = torch.ones_like(m_lr)
    torch.testing.assert_close(upsample_by_class(x, one, torch.ones_like(m_hr), s, j), plain)


def test_demod_bilinear_and_fusesr_residual_upsample_by_class():
    """demod-bilinear = K * (upsample_by_class(L_D) F_used + E); FuseSR's residual path (refine zeroed) the same."""
    from training.models.base import demodulated_mask, upsample_by_class
    batch = make_batch()
    batch["lr/fbeta_used"][..., 0, :] = 1.0  # background row (depth +inf) and HR rows above 4 px: F_used = 1
    batch["hr/fbeta_used"][..., :4, :] = 1.0
    masks = demodulated_mask(batch["lr/fbeta_used"][:, -1]), demodulated_mask(batch["hr/fbeta_used"][:, -1])
    j = batch["lr_jitter"][:, -1]
    db = build_model(ModelConfig(name="demod-bilinear", remod_filter="NONE"), 4).eval()
    assert "lr/fbeta_used" in db.needs()
    up = upsample_by_class(batch["lr/irradiance"][:, -1], *masks, 4, j)
    torch.testing.assert_close(db(batch), up * batch["hr/fbeta_used"][:, -1] + batch["hr/emission"][:, -1])
    old = build_model(ModelConfig(name="demod-bilinear", remod_filter="NONE", upsample_by_class=False), 4).eval()
    assert "lr/fbeta_used" not in old.needs() and not torch.allclose(old(batch), db(batch))
    from training.transforms import forward_transform, inverse_transform
    net = FuseSR(4, remod_filter="NONE", guided_upsample=False).eval()
    with torch.no_grad():
        net.refine.weight.zero_()
        net.refine.bias.zero_()
        up = upsample_by_class(forward_transform(batch["lr/irradiance"][:, -1], "log1p"), *masks, 4, j)
        expect = inverse_transform(up.clamp(min=0), "log1p") * batch["hr/fbeta_used"][:, -1] \
            + batch["hr/emission"][:, -1]
        torch.testing.assert_close(net(batch), expect, rtol=1e-5, atol=1e-5)


def _guided_reference(x, g_lr, g_hr, s, j, c_lr, c_hr, floor, fallback):
    """Per-pixel numpy loop of the joint bilateral upsampling (guided module doc): (C, h, w) arrays in, (C, H, W)."""
    c, h, w = x.shape
    out = np.empty((c, h * s, w * s))
    for yy in range(h * s):
        for xx in range(w * s):
            u, v = (xx + 0.5) / s - 0.5 - j[0], (yy + 0.5) / s - 0.5 - j[1]
            num, den = np.zeros(c), 0.0
            for iy in (int(np.floor(v)), int(np.floor(v)) + 1):
                for ix in (int(np.floor(u)), int(np.floor(u)) + 1):
                    bil = max(0.0, 1 - abs(u - ix)) * max(0.0, 1 - abs(v - iy))
                    cy, cx = min(max(iy, 0), h - 1), min(max(ix, 0), w - 1)
                    rng = np.exp(-0.5 * np.sum((g_lr[:, cy, cx] - g_hr[:, yy, xx]) ** 2))
                    same = c_lr[cy, cx] == c_hr[yy, xx]
                    num += bil * rng * same * x[:, cy, cx]
                    den += bil * rng * same
            out[:, yy, xx] = num / den if den >= floor else fallback[:, yy, xx]
    return out


def test_upsample_guided_matches_a_per_pixel_reference():
    from training.models.guided import guide_features, upsample_guided
    g = torch.Generator().manual_seed(5)
    h, w, s = 5, 7, 4
    x = torch.rand(1, 3, h, w, generator=g) * 10
    depth_lr, depth_hr = 1 + 4 * torch.rand(1, 1, h, w, generator=g), 1 + 4 * torch.rand(1, 1, h * s, w * s, generator=g)
    depth_lr[..., 0, 0] = float("inf")
    n_lr, n_hr = torch.rand(1, 3, h, w, generator=g) - 0.5, torch.rand(1, 3, h * s, w * s, generator=g) - 0.5
    g_lr, g_hr = guide_features(depth_lr, n_lr, 0.5, 0.6), guide_features(depth_hr, n_hr, 0.5, 0.6)
    assert g_lr[0, 0, 0, 0] == pytest.approx(np.log(1e6) / 0.5)  # background depth clamped, not inf
    c_lr = (torch.rand(1, 1, h, w, generator=g) < 0.7).float()
    c_hr = (torch.rand(1, 1, h * s, w * s, generator=g) < 0.7).float()
    fallback = torch.full((1, 3, h * s, w * s), -1.0)
    j = torch.tensor([[0.3, -0.45]])
    out = upsample_guided(x, g_lr, g_hr, s, fallback, j, (c_lr, c_hr), floor=1e-3)
    ref = _guided_reference(x[0].double().numpy(), g_lr[0].double().numpy(), g_hr[0].double().numpy(), s,
                            (0.3, -0.45), c_lr[0, 0].numpy(), c_hr[0, 0].numpy(), 1e-3, fallback[0].numpy())
    np.testing.assert_allclose(out[0].numpy(), ref, rtol=2e-4, atol=2e-4)
    assert (ref == -1).any() and (ref != -1).any()  # both the weighted and the fallback branch are exercised


def test_upsample_guided_is_bilinear_on_one_surface_and_keeps_a_depth_edge_sharp():
    """Same guide everywhere: exactly the (jittered) bilinear upsampling. Two surfaces (depth 1 | 8, shading 1 | 5)
    meeting at an LR pixel border: every HR pixel gets its own surface's value; bilinear blurs the edge."""
    from training.models.guided import guide_features, upsample_guided
    h, w, s = 4, 6, 4
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 3, h, w, generator=g)
    j = torch.tensor([[0.25, -0.1], [-0.4, 0.3]])
    flat = torch.zeros(2, 4, h, w), torch.zeros(2, 4, h * s, w * s)
    torch.testing.assert_close(upsample_guided(x, *flat, s, torch.zeros(2, 3, h * s, w * s), j),
                               upsample(x, s, "bilinear", j))
    d_lr = torch.where(torch.arange(w) < 3, 1.0, 8.0).expand(1, 1, h, w)
    d_hr = torch.where(torch.arange(w * s) < 3 * s, 1.0, 8.0).expand(1, 1, h * s, w * s)
    n_lr, n_hr = torch.zeros(1, 3, h, w), torch.zeros(1, 3, h * s, w * s)
    shade = torch.where(torch.arange(w) < 3, 1.0, 5.0).expand(1, 3, h, w)
    plain = upsample(shade, s, "bilinear")
    out = upsample_guided(shade, guide_features(d_lr, n_lr, 0.1, 0.3), guide_features(d_hr, n_hr, 0.1, 0.3), s, plain)
    torch.testing.assert_close(out, torch.where(torch.arange(w * s) < 3 * s, 1.0, 5.0).expand(1, 3, h * s, w * s))
    assert ((plain > 1.01) & (plain < 4.99)).any()


def test_demod_jbu_and_fusesr_guided_residual():
    """demod-jbu = demod-bilinear with the guided upsampling; FuseSR's residual base (refine zeroed) is the same
    guided upsampling of T(L_D), its HR depth moves the output, and without the HR G-buffers it is not read."""
    from training.models.base import demodulated_mask, upsample_by_class
    from training.models.guided import guide_features, upsample_guided
    from training.transforms import forward_transform, inverse_transform
    batch = make_batch()
    batch["lr/fbeta_used"][..., 0, :] = 1.0
    batch["hr/fbeta_used"][..., :4, :] = 1.0
    cur = {k: v[:, -1] for k, v in batch.items() if k != "depth_ref"}
    masks = demodulated_mask(cur["lr/fbeta_used"]), demodulated_mask(cur["hr/fbeta_used"])
    guides = [guide_features(cur[f"{lv}/depth"], cur[f"{lv}/normal"], 0.1, 0.3) for lv in ("lr", "hr")]
    j = cur["lr_jitter"]

    def jbu(x):
        return upsample_guided(x, *guides, 4, upsample_by_class(x, *masks, 4, j), j, masks)

    model = build_model(ModelConfig(name="demod-jbu", remod_filter="NONE"), 4).eval()
    assert {"hr/depth", "hr/normal", "lr/depth", "lr/normal"} <= set(model.needs())
    expect = jbu(cur["lr/irradiance"]) * cur["hr/fbeta_used"] + cur["hr/emission"]
    torch.testing.assert_close(model(batch), expect)
    db = build_model(ModelConfig(name="demod-bilinear", remod_filter="NONE"), 4).eval()
    assert "hr/depth" not in db.needs() and not torch.allclose(db(batch), expect)
    net = FuseSR(4, remod_filter="NONE").eval()
    assert net.guided and "hr/normal" in net.needs()
    with torch.no_grad():
        net.refine.weight.zero_()
        net.refine.bias.zero_()
        net.hr_branch[0].weight.zero_()
        up = jbu(forward_transform(cur["lr/irradiance"], "log1p"))
        expect = inverse_transform(up.clamp(min=0), "log1p") * cur["hr/fbeta_used"] + cur["hr/emission"]
        torch.testing.assert_close(net(batch), expect, rtol=1e-5, atol=1e-5)
    net.refine.bias.data.fill_(0.1)
    assert _changes_output(net, batch, "hr/depth", -1)  # through the guided base alone (HR branch zeroed)
    no_guide = FuseSR(4, guided_upsample=False)
    assert not no_guide.guided and "hr/normal" in no_guide.needs()  # still read by the HR branch
    no_hr = FuseSR(4, hr_gbuffer=False)
    assert not no_hr.guided
    authors = FuseSR(4, residual=False)  # no residual base to guide
    assert not authors.guided and "lr/normal" in authors.needs() and "lr/fbeta_used" not in authors.needs()


def test_guide_sigmas_are_validated():
    with pytest.raises(ConfigError, match="guide_sigma_depth"):
        ModelConfig.of(guide_sigma_depth=0.0)
    with pytest.raises(ConfigError, match="guide_sigma_normal"):
        ModelConfig.of(guide_sigma_normal=float("nan"))


@pytest.mark.parametrize("hr_guide", [False, True])
def test_zero_init_refine_starts_exactly_at_the_residual_base(hr_guide):
    """model.zero_init_refine: a fresh FuseSR equals the same network with its last conv zeroed by hand (the
    residual base, remodulated), and the last conv still gets a gradient."""
    batch = make_batch()
    torch.manual_seed(0)
    net = FuseSR(4, zero_init_refine=True, hr_guide=hr_guide)
    torch.manual_seed(0)
    ref = FuseSR(4, hr_guide=hr_guide)
    last = ref.refine[-1] if hr_guide else ref.refine
    with torch.no_grad():
        assert last.weight.abs().sum() > 0
        last.weight.zero_()
        last.bias.zero_()
        torch.testing.assert_close(net.eval()(batch), ref.eval()(batch))
    out = net.train()(batch)
    out.mean().backward()
    grad = (net.refine[-1] if hr_guide else net.refine).weight.grad
    assert grad is not None and grad.abs().sum() > 0


@pytest.mark.parametrize("name", list(MODELS))
def test_a_model_is_built_by_keyword_with_the_configurations_defaults(name):
    """Every class names its row; built with no keys it holds exactly the default configuration (one place for
    defaults: ModelConfig and training.models.options), and build_model passes a configuration's keys through."""
    from training.models import model_class, model_keys
    cls = model_class(name)
    assert cls.NAME == name
    scale = 2 if cls.SCALES is None else 4
    bare = cls(scale)
    assert bare.config.to_dict() == ModelConfig.of(name).to_dict()
    assert bare.by_class and bare.use_jitter  # the [model] table's defaults (an old fallback said by_class False)
    assert bare.config.remod_filter == "REFERENCE" and bare.remod_taps is not None
    cfg = ModelConfig.of(name, jitter=False, remod_filter="NONE")
    built = build_model(cfg, scale)
    assert built.config.to_dict() == cfg.to_dict() and model_keys(cfg)["jitter"] is False
    assert not built.use_jitter and built.remod_kernel is None
    with pytest.raises(ConfigError, match=f"model {name}: no key 'no_such_key'"):
        cls(scale, no_such_key=1)


def test_fusesr_fast_reads_fusesrs_switches_through_one_class():
    from training.models.fusesr import FuseSRFrame
    from training.models.fusesr_fast import FuseSRFast
    fast, full = FuseSRFast(4, hr_gbuffer=False, demodulation=False), FuseSR(4, hr_gbuffer=False, demodulation=False)
    for m in (fast, full):
        assert isinstance(m, FuseSRFrame) and not m.use_hr and not m.demod and not m.guided
        assert m.color_key == "lr/radiance" and "hr/fbeta_used" not in m.needs()
