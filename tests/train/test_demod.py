"""The torch demodulation mirror gives exactly what gbuffer_export.demod gives."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gbuffer_export import demod as np_demod  # noqa: E402
from gbuffer_export.conventions import Flag  # noqa: E402
from training import demod as t_demod  # noqa: E402



def chw(a):
    return torch.from_numpy(np.ascontiguousarray(np.asarray(a).transpose(2, 0, 1)))


def hwc(t):
    return t.numpy().transpose(1, 2, 0)


def random_case(seed, h=9, w=11):
    rng = np.random.default_rng(seed)
    rad = (rng.random((h, w, 3)) * 4 - 0.2).astype(np.float32)
    rad[0, 0, 0] = np.nan
    rad[1, 1, 1] = np.inf
    rad[2, 2, 2] = -np.inf
    rad[3, 3, 0] = 3e9  # beyond the cap
    em = (rng.random((h, w, 3)) * 0.3).astype(np.float32)
    em[4, 4, :] = np.nan
    fb = rng.random((h, w, 3)).astype(np.float32)
    fb[5, :, 0] = 0.0           # below eps
    fb[6, 0, 1] = np.nan        # non-finite F_beta
    fb[6, 1, 2] = 5e3           # above FBETA_MAX
    flags = np.zeros((h, w), np.uint32)
    flags[7, :3] = Flag.BACKGROUND
    flags[8, :3] = Flag.SUBSURFACE
    flags[8, 3] = Flag.EMISSIVE  # informative bit: F_beta still used
    return rad, em, fb, flags


@pytest.mark.parametrize("seed,eps", [(0, 0.01), (1, 0.02), (2, 1e-6)])
def test_demodulate_matches_numpy(seed, eps):
    rad, em, fb, flags = random_case(seed)
    irr_np, f_np = np_demod.demodulate(rad, em, fb, flags, eps)
    irr_t, f_t = t_demod.demodulate(chw(rad), chw(em), chw(fb), torch.from_numpy(flags.astype(np.int64)), eps)
    assert irr_t.dtype == torch.float32
    np.testing.assert_array_equal(hwc(f_t), f_np)
    np.testing.assert_array_equal(hwc(irr_t), irr_np)
    assert np.isfinite(hwc(irr_t)).all()
    # flagged pixels divide by 1, the EMISSIVE-only pixel by its own F_beta
    assert (hwc(f_t)[7, :3] == 1).all() and (hwc(f_t)[8, :3] == 1).all()
    assert np.allclose(hwc(f_t)[8, 3], np.clip(fb[8, 3], eps, None))


def test_single_channel_fbeta_no_emission_no_flags_and_batched():
    rad, _, fb, _ = random_case(3)
    fb1 = fb[..., :1]
    irr_np, f_np = np_demod.demodulate(rad, None, fb1)
    batch_rad = torch.stack([chw(rad), chw(rad)])
    irr_t, f_t = t_demod.demodulate(batch_rad, None, torch.stack([chw(fb1), chw(fb1)]))
    for i in range(2):
        np.testing.assert_array_equal(hwc(irr_t[i]), irr_np)
        np.testing.assert_array_equal(hwc(f_t[i]), f_np)


def test_remodulate_matches_numpy_and_round_trips():
    rad, em, fb, flags = random_case(4)
    irr, f = np_demod.demodulate(rad, em, fb, flags)
    back_np = np_demod.remodulate(irr, f, em)
    back_t = t_demod.remodulate(chw(irr), chw(f), chw(em))
    np.testing.assert_array_equal(hwc(back_t), back_np)
    sane = np.isfinite(rad) & (np.abs(rad) < 1e9) & np.isfinite(em)
    np.testing.assert_allclose(hwc(back_t)[sane], rad[sane], rtol=1e-5, atol=1e-5)


def test_eps_out_of_range_is_rejected():
    rad, em, fb, flags = random_case(5)
    with pytest.raises(ValueError, match="eps"):
        t_demod.demodulate(chw(rad), chw(em), chw(fb), None, eps=0.0)
