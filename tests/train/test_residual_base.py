"""The residual base (``[model.<name>] residual`` / ``zero_init_head``; ``SRModel.demod_base``, not in the papers) of
rdg, rdg-s, nsrr, nsrr-fec and fourier-sr: a fresh zero-initialised network outputs exactly ``demod-bilinear`` on
every frame (fourier-sr at an integer and a non-integer scale), the option reads the base's keys, adds no parameter,
and the option combinations are checked. NSRD's own test: tests/train/test_nsrd.py."""
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.typed_table import ConfigError  # noqa: E402
from training.config import ModelConfig  # noqa: E402
from training.models import build_model  # noqa: E402
from training.models.window import frame_slice  # noqa: E402


#: model -> its options for the base (rdg's needs its demodulated input)
CASES = {"rdg-s": {"demod": True}, "rdg": {"demod": True}, "nsrr": {}, "nsrr-fec": {}, "fourier-sr": {}}


def make_batch(scale=4.0, h=6, w=8, frames=3, seed=0):
    """Random inputs of every key the five models and demod-bilinear read; a few demodulated LR/HR pixels beside
    F_used = 1 ones (the by-class upsampling) and a background row."""
    g = torch.Generator().manual_seed(seed)
    big_h, big_w = round(h * scale), round(w * scale)
    lr = lambda c: torch.rand(1, frames, c, h, w, generator=g)  # noqa: E731
    hr = lambda c: torch.rand(1, frames, c, big_h, big_w, generator=g)  # noqa: E731
    depth = 1 + 5 * lr(1)
    depth[..., 0, :] = float("inf")
    batch = {"lr/irradiance": 3 * lr(3), "lr/radiance": 2 * lr(3), "lr/normal": lr(3) - 0.5, "lr/depth": depth,
             "lr/fbeta": lr(3), "lr/albedo": lr(3), "lr/motion": 2 * lr(2) - 1, "lr/motion_next": 2 * lr(2) - 1,
             "depth_ref": torch.full((1, frames), 3.0), "lr_jitter": torch.rand(1, frames, 2, generator=g) - 0.5,
             "lr/fbeta_used": torch.ones(1, frames, 3, h, w), "hr/fbeta_used": 0.1 + hr(3),
             "hr/emission": 0.1 * hr(3), "hr/depth": 1 + 5 * hr(1), "hr/normal": hr(3) - 0.5, "hr/albedo": hr(3),
             "hr/metallic": hr(1), "hr/roughness": hr(1), "hr/specular": hr(1), "hr/motion": 2 * hr(2) - 1,
             "scale": torch.tensor([float(scale)])}
    batch["lr/fbeta_used"][..., 0, 1:3, 2:5] = 0.3
    batch["hr/fbeta_used"][..., 0, :8, :] = 1.0
    return batch


def n_params(m):
    return sum(p.numel() for p in m.parameters())


def demod_bilinear_at(scale):
    """demod-bilinear upsampling by ``scale`` (integer or not: its class takes 2, 4, 8; the upsampling any)."""
    base = build_model(ModelConfig.of("demod-bilinear"), 4).eval()
    base.scale = int(scale) if float(scale).is_integer() else float(scale)
    return base


@pytest.mark.parametrize("name,scale", [*[(n, 4) for n in CASES], ("fourier-sr", 2.5)])
def test_zero_initialised_base_is_demod_bilinear_on_every_frame(name, scale):
    torch.manual_seed(0)
    batch = make_batch(scale)
    model = build_model(ModelConfig.of(name, residual=True, zero_init_head=True, **CASES[name]), scale).eval()
    plain = build_model(ModelConfig.of(name, **CASES[name]), scale)
    base = demod_bilinear_at(scale)
    assert set(base.needs()) <= set(model.needs())
    assert n_params(model) == n_params(plain)  # the option adds no parameter
    state = None
    with torch.no_grad():
        for i in range(batch["lr/irradiance"].shape[1]):
            cur = {k: (v if k == "scale" else v[:, : i + 1]) for k, v in batch.items()}
            if getattr(model, "recurrent", False):
                sr, state = model.step(frame_slice(batch, i), state)
            else:
                sr = model(cur)
            torch.testing.assert_close(sr, base(cur), rtol=2e-6, atol=2e-6)


@pytest.mark.parametrize("name", list(CASES))
def test_base_trains_away_from_demod_bilinear(name):
    """A fresh network with the base (not zero-initialised) differs from demod-bilinear: the head is in the sum."""
    torch.manual_seed(0)
    batch = make_batch(4.0, frames=2)
    model = build_model(ModelConfig.of(name, residual=True, **CASES[name]), 4).eval()
    with torch.no_grad():
        assert not torch.allclose(model(batch), demod_bilinear_at(4)(batch), atol=1e-4)


def test_option_combinations():
    with pytest.raises(ConfigError, match="zero_init_head needs"):
        ModelConfig.of("nsrr-fec", zero_init_head=True)
    with pytest.raises(ConfigError, match="residual needs .*demod"):
        ModelConfig.of("rdg-s", residual=True)
    with pytest.raises(ConfigError, match="zero_init_head needs"):
        ModelConfig.of("fourier-sr", zero_init_head=True)
    # off (the default) is the paper's network: radiance out, no demodulated keys read
    assert "lr/irradiance" not in build_model(ModelConfig.of("nsrr-fec"), 4).needs()
    assert "lr/irradiance" not in build_model(ModelConfig.of("rdg-s"), 4).needs()
