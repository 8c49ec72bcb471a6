"""Demodulation that never breaks (gbuffer_export.demod): hard inputs, flags, exact round trip."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from gbuffer_export.conventions import UNTRUSTED, Flag
from gbuffer_export.demod import (EPS_MIN, RADIANCE_CAP, demodulate, demodulate_full, remodulate, sanitize)
from gbuffer_export.exr import read_exr, write_exr


def _close_round_trip(back, ref, emission):
    scale = np.maximum(np.maximum(np.abs(ref), np.abs(emission)), 1e-30)
    assert np.all(np.abs(back.astype(np.float64) - ref) <= 3e-7 * scale + 1e-30)


def test_formula_and_floor():
    i = np.array([[[0.5, 2.0, 0.0]]], np.float32)
    e = np.array([[[0.1, 0.0, 0.0]]], np.float32)
    f = np.array([[[0.5, 0.0, 0.005]]], np.float32)
    irr, fu = demodulate(i, e, f)
    np.testing.assert_allclose(fu, [[[0.5, 0.01, 0.01]]])
    np.testing.assert_allclose(irr, [[[0.8, 200.0, 0.0]]], rtol=1e-6)
    irr2, fu2 = demodulate(i, e, f, eps=0.02)
    np.testing.assert_allclose(fu2, [[[0.5, 0.02, 0.02]]])
    np.testing.assert_allclose(irr2[0, 0, 1], 100.0, rtol=1e-6)
    for bad in (0.0, -1.0, 1e-9, 2.0, np.nan):
        with pytest.raises(ValueError):
            demodulate(i, e, f, eps=bad)


def test_nonfinite_negative_and_fireflies():
    i = np.array([[[np.nan, np.inf, -np.inf], [-0.25, 1e6, 3e38]]], np.float32)
    e = np.zeros_like(i)
    f = np.full_like(i, 0.5)
    r = demodulate_full(i, e, f)
    assert np.all(np.isfinite(r.irradiance)) and np.all(np.isfinite(r.fbeta_used))
    np.testing.assert_allclose(r.irradiance[0, 0], [0.0, RADIANCE_CAP / 0.5, -RADIANCE_CAP / 0.5], rtol=1e-6)
    np.testing.assert_allclose(r.irradiance[0, 1], [-0.5, 2e6, RADIANCE_CAP / 0.5], rtol=1e-6)
    s = r.stats
    assert (s.nan, s.pos_inf, s.neg_inf, s.clipped, s.sanitised) == (1, 1, 1, 1, 4)
    back = remodulate(r.irradiance, r.fbeta_used, e)
    np.testing.assert_allclose(back, sanitize(i)[0], rtol=1e-6)


def test_fbeta_zero_nan_and_huge():
    i = np.ones((1, 4, 3), np.float32)
    f = np.array([[[0, 0, 0], [np.nan, np.inf, -np.inf], [-1, 0.3, 1e9], [1e-40, 1, 1]]], np.float32)
    r = demodulate_full(i, None, f)
    assert np.all(np.isfinite(r.irradiance))
    np.testing.assert_allclose(r.fbeta_used[0, 0], 0.01)
    np.testing.assert_allclose(r.fbeta_used[0, 1], 1.0)          # non-finite F_beta -> 1 (counted)
    np.testing.assert_allclose(r.fbeta_used[0, 2], [0.01, 0.3, 1e3], rtol=1e-6)
    assert r.stats.fbeta_nonfinite == 3 and r.stats.fbeta_floored == 5 and r.stats.fbeta_capped == 1
    _close_round_trip(remodulate(r.irradiance, r.fbeta_used, None), np.ones((1, 4, 3)), np.zeros((1, 4, 3)))


def test_background_and_untrusted_flags():
    h, w = 2, 3
    i = np.full((h, w, 3), 0.3, np.float32)
    e = np.full((h, w, 3), 0.1, np.float32)
    f = np.full((h, w, 3), 0.25, np.float32)
    flags = np.zeros((h, w), np.uint32)
    flags[0, 0] = Flag.BACKGROUND
    flags[0, 1] = Flag.ANISOTROPIC | Flag.EMISSIVE
    flags[0, 2] = Flag.EMISSIVE | Flag.MOVING           # informative bits only: demodulated normally
    flags[1, 0] = Flag.SUBSURFACE
    flags[1, 1] = Flag.BACKGROUND | Flag.NO_MATERIAL
    r = demodulate_full(i, e, f, flags)
    expect_one = np.array([[1, 1, 0], [1, 1, 0]], bool)
    np.testing.assert_array_equal(r.fbeta_used[..., 0] == 1.0, expect_one)
    np.testing.assert_allclose(r.irradiance[expect_one], 0.2, rtol=1e-6)
    np.testing.assert_allclose(r.irradiance[~expect_one], 0.8, rtol=1e-6)
    assert r.stats.background == 2 and r.stats.untrusted == 2
    r3 = demodulate_full(i, e, f, flags[..., None])
    np.testing.assert_array_equal(r3.irradiance, r.irradiance)
    for bit in Flag:
        fl = np.full((h, w), int(bit), np.uint32)
        _, fu = demodulate(i, e, f, fl)
        assert np.all(fu == 1.0) == bool(bit & (UNTRUSTED | Flag.BACKGROUND))


def test_emission_only_and_black_metal():
    # emission-only pixel: I = E, F_beta = 0 (black metal seen head-on): irradiance 0, round trip gives E
    e = np.array([[[5.0, 0.0, 1e4]]], np.float32)
    irr, fu = demodulate(e.copy(), e, np.zeros_like(e))
    np.testing.assert_array_equal(irr, 0.0)
    np.testing.assert_array_equal(remodulate(irr, fu, e), e)


def test_shape_errors():
    z = np.zeros((2, 3, 3), np.float32)
    with pytest.raises(ValueError):
        demodulate(z, z, np.zeros((3, 2, 3)))
    with pytest.raises(ValueError):
        demodulate(z, z, z, flags=np.zeros((2, 2), np.uint32))
    with pytest.raises(ValueError):
        demodulate(z[..., :2], z, z)


def test_values_above_half_range_survive_exr(tmp_path):
    i = np.array([[[1e6, 7e4, 0.5], [-1e5, 65504.0, 3.0]]], np.float32)
    write_exr(tmp_path / "r.exr", {c: i[..., k] for k, c in enumerate("RGB")}, half=True)
    back = read_exr(tmp_path / "r.exr", ("R", "G", "B"))
    np.testing.assert_array_equal(back, i)  # write_exr keeps float32 when a value exceeds half range
    irr, fu = demodulate(back, np.zeros_like(back), np.full_like(back, 0.02))
    assert np.all(np.isfinite(irr))
    np.testing.assert_allclose(remodulate(irr, fu, np.zeros_like(back)), i, rtol=1e-6)


def test_synthetic_clip_round_trip(tmp_path):
    from gbuffer_export.clip import open_clip
    from gbuffer_export.synthetic import make_synthetic_clip

    clip = open_clip(make_synthetic_clip(tmp_path / "c", frames=range(1, 2), jitter=True))
    for lvl in ("hr", "lr"):
        i = clip.read(1, f"{lvl}/radiance")
        e = clip.read(1, f"{lvl}/emission")
        f = clip.read(1, f"{lvl}/fbeta")
        flags = clip.read(1, f"{lvl}/flags")
        depth = clip.read(1, f"{lvl}/depth")
        assert np.isinf(depth).any()  # background depth is +inf
        irr, fu = demodulate(i, e, f, flags)
        bg = (flags[..., 0] & Flag.BACKGROUND) != 0
        assert np.all(fu[bg] == 1.0) and np.all(np.isfinite(irr))
        # synthetic radiance is albedo * shade on surfaces: demodulating by F_beta = albedo returns the shade
        surf = ~bg & (f.min(axis=-1) > 0.05)
        if lvl == "lr":
            shade = irr[surf]
            np.testing.assert_allclose(shade, shade[:, :1].repeat(3, 1), rtol=1e-5)
        _close_round_trip(remodulate(irr, fu, e), i.astype(np.float64), e)


finite_or_not = st.one_of(st.floats(width=32), st.sampled_from([np.nan, np.inf, -np.inf, 0.0, 1e6, -1e6, float(np.float32(3e38))]))


@settings(max_examples=150, deadline=None)
@given(hnp.arrays(np.float32, (3, 2, 3), elements=finite_or_not),
       hnp.arrays(np.float32, (3, 2, 3), elements=finite_or_not),
       hnp.arrays(np.float32, (3, 2, 3), elements=finite_or_not),
       hnp.arrays(np.uint32, (3, 2), elements=st.integers(0, 1023)),
       st.floats(EPS_MIN, 1.0))
def test_demodulation_property(i, e, f, flags, eps):
    irr, fu = demodulate(i, e, f, flags, eps=eps)
    assert irr.dtype == np.float32 and fu.dtype == np.float32
    assert np.all(np.isfinite(irr)) and np.all(np.isfinite(fu))
    assert np.all(fu >= np.float32(eps))
    back = remodulate(irr, fu, e)
    assert np.all(np.isfinite(back))
    _close_round_trip(back, sanitize(i)[0], sanitize(e)[0])
