"""Colour spaces (gbuffer_export.colour_spaces) against colour-science and known values: the sRGB encoding of
previews and of the torch evaluation tonemap."""
from __future__ import annotations

import colour
import numpy as np
import pytest

from gbuffer_export.colour_spaces import srgb_encode
from gbuffer_export.preview import tonemap

#: Linear values across both branches of the sRGB curve, beyond its ends, and non-finite ones.
XS = np.array([-1.0, 0.0, 1e-5, 0.0031308, 0.004, 0.01, 0.18, 0.5, 0.99, 1.0, 2.0, 1e3, np.inf, np.nan])


def test_srgb_encode_known_values():
    x = np.array([0.0, 0.0031308, 0.18, 1.0])
    # IEC 61966-2-1: 12.92 x below 0.0031308, 1.055 x^(1/2.4) - 0.055 above
    expect = np.array([0.0, 0.0404500, 1.055 * 0.18 ** (1 / 2.4) - 0.055, 1.0])
    np.testing.assert_allclose(srgb_encode(x), expect, atol=1e-6)
    np.testing.assert_allclose(srgb_encode(np.array([-0.5, 3.0])), [0.0, 1.0])  # clipped to [0, 1]


def test_preview_tonemap_is_reinhard_then_colour_srgb():
    x = np.nan_to_num(XS, nan=0.0, posinf=1e6)
    v = np.maximum(x, 0.0)
    expect = colour.models.eotf_inverse_sRGB(v / (1.0 + v))
    np.testing.assert_allclose(tonemap(XS), expect, atol=1e-12)
    assert tonemap(XS).min() >= 0.0 and tonemap(XS).max() <= 1.0


@pytest.mark.torch
def test_torch_tonemap_matches_colour_and_differentiates():
    torch = pytest.importorskip("torch")
    from training.transforms import srgb_oetf, tonemap as torch_tonemap
    xs = torch.tensor(XS, dtype=torch.float32)
    np.testing.assert_allclose(torch_tonemap(xs).numpy(), tonemap(XS), atol=2e-6)
    lin = np.linspace(0.0, 1.0, 10001)
    np.testing.assert_allclose(srgb_oetf(torch.tensor(lin, dtype=torch.float64)).numpy(),
                               colour.cctf_encoding(lin, function="sRGB"), atol=1e-12)
    x = torch.tensor([0.0, 1e-4, 0.01, 1.0, 10.0], requires_grad=True)
    torch_tonemap(x).sum().backward()
    assert torch.isfinite(x.grad).all() and (x.grad > 0).all()
