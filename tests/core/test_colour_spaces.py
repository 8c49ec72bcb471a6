"""Colour spaces (gbuffer_export.colour_spaces) against colour-science and published values: the sRGB encoding of
previews and of the torch evaluation tonemap, the BT.709 YCbCr matrices, and the conversion of clips rendered in
another working space into the training space (synthetic clips and an ACEScg render)."""
from __future__ import annotations

import colour
import numpy as np
import pytest

from tests.conftest import make_blend, requires_bpy, run_cli
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


def test_bt709_ycbcr_matrices_are_colours():
    from gbuffer_export.colour_spaces import RGB_TO_YCBCR_709, YCBCR_TO_RGB_709
    k = colour.WEIGHTS_YCBCR["ITU-R BT.709"]
    rgb = np.random.default_rng(0).uniform(0.0, 1.0, (64, 3))
    np.testing.assert_allclose(rgb @ RGB_TO_YCBCR_709.T, colour.RGB_to_YCbCr(rgb, K=k, out_legal=False,
                                                                              out_int=False), atol=1e-12)
    np.testing.assert_allclose(YCBCR_TO_RGB_709, colour.matrix_YCbCr(K=k, is_legal=False), atol=1e-12)
    np.testing.assert_allclose(YCBCR_TO_RGB_709 @ RGB_TO_YCBCR_709, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(RGB_TO_YCBCR_709 @ [1.0, 1.0, 1.0], [1.0, 0.0, 0.0], atol=1e-12)  # grey: no chroma
    assert not RGB_TO_YCBCR_709.flags.writeable


# --------------------------------------------------------------------------------------------- working spaces

def test_conversion_matrices_match_published_ones():
    from gbuffer_export.colour_spaces import WORKING_SPACES, conversion_matrix
    assert conversion_matrix("Linear Rec.709") is None  # the training space itself: no conversion
    # ITU-R BT.2087 (Rec.2020 -> Rec.709, both D65) and the ACES AP1 -> Rec.709 matrix with Bradford adaptation
    bt2087 = [[1.6605, -0.5876, -0.0728], [-0.1246, 1.1329, -0.0083], [-0.0182, -0.1006, 1.1187]]
    ap1 = [[1.70505, -0.62179, -0.08326], [-0.13026, 1.14080, -0.01055], [-0.02400, -0.12897, 1.15297]]
    np.testing.assert_allclose(conversion_matrix("Linear Rec.2020"), bt2087, atol=1e-4)
    np.testing.assert_allclose(conversion_matrix("ACEScg"), ap1, atol=1e-4)
    for a in WORKING_SPACES:
        for b in WORKING_SPACES:
            if a != b:  # white stays white (fbeta = 1 on background stays 1); the two directions are inverses
                np.testing.assert_allclose(conversion_matrix(a, b).sum(axis=1), 1.0, atol=1e-6)
                np.testing.assert_allclose(conversion_matrix(a, b) @ conversion_matrix(b, a), np.eye(3), atol=1e-9)
    with pytest.raises(ValueError, match="'Filmic Log'.*known: Linear Rec.709"):
        conversion_matrix("Filmic Log")


@pytest.fixture(scope="module")
def acescg_clip(tmp_path_factory):
    """A synthetic clip whose manifest declares ACEScg (the stored values are what the generator writes)."""
    from gbuffer_export.synthetic import SyntheticLook, make_synthetic_clip
    return make_synthetic_clip(tmp_path_factory.mktemp("acescg") / "clip", frames=(1, 2), hr_size=(32, 16),
                               scale=4, look=SyntheticLook(scene_linear="ACEScg"))


def test_clip_read_converts_colour_buffers_only(acescg_clip):
    from gbuffer_export.clip import open_clip
    from gbuffer_export.colour_spaces import COLOUR_BUFFERS, TRAINING_SPACE, conversion_matrix
    clip = open_clip(acescg_clip)
    assert clip.scene_linear == "ACEScg"
    m = conversion_matrix("ACEScg")
    for name in clip.buffers:
        for lvl in ("hr", "lr"):
            raw = clip.read(1, f"{lvl}/{name}")
            got = clip.read(1, f"{lvl}/{name}", space=TRAINING_SPACE)
            assert got.dtype == raw.dtype and got.shape == raw.shape
            if name in COLOUR_BUFFERS:
                np.testing.assert_allclose(got, np.einsum("ij,hwj->hwi", m, raw.astype(np.float64)),
                                           rtol=1e-6, atol=1e-6)
                assert name not in ("radiance", "albedo") or not np.allclose(got, raw)  # coloured in the clip
            else:
                assert np.array_equal(got, raw, equal_nan=True), name
    assert np.array_equal(clip.read(1, "hr/radiance", space="ACEScg"), clip.read(1, "hr/radiance"))


def test_contact_sheet_shows_rec709_colours(tmp_path):
    """The same stored values declared ACEScg and Linear Rec.709 give different contact sheets."""
    from PIL import Image

    from gbuffer_export.clip import open_clip
    from gbuffer_export.preview import contact_sheet
    from gbuffer_export.synthetic import SyntheticLook, make_synthetic_clip
    sheet = {}
    for space in ("ACEScg", "Linear Rec.709"):
        clip = make_synthetic_clip(tmp_path / space, frames=(1,), hr_size=(64, 36), scale=4, look=SyntheticLook(scene_linear=space))
        sheet[space] = np.asarray(Image.open(contact_sheet(open_clip(clip), tmp_path / f"{space}.png")), np.int16)
    assert sheet["ACEScg"].shape == sheet["Linear Rec.709"].shape
    assert np.abs(sheet["ACEScg"] - sheet["Linear Rec.709"]).max() > 50


@pytest.mark.torch
def test_training_cache_and_evaluation_see_the_training_space(acescg_clip, tmp_path):
    pytest.importorskip("torch")
    from gbuffer_export.clip import open_clip
    from gbuffer_export.colour_spaces import TRAINING_SPACE
    from training.cache import ClipCache
    from training.inference.loading import ClipFrames
    clip = open_clip(acescg_clip)
    cache = ClipCache(acescg_clip, cache_dir=tmp_path).ensure(
        ["hr/radiance", "lr/radiance", "lr/albedo", "lr/fbeta", "lr/emission", "lr/irradiance", "lr/fbeta_used"])
    frames = ClipFrames(acescg_clip)
    for key, tol in (("hr/radiance", 1e-6), ("lr/radiance", 1e-6), ("lr/albedo", 1e-3), ("lr/fbeta", 1e-6),
                     ("lr/emission", 1e-6)):  # albedo is cached as float16
        want = clip.read(2, key, space=TRAINING_SPACE)
        np.testing.assert_allclose(cache.read(2, key), want, rtol=tol, atol=tol)
        np.testing.assert_allclose(frames.read(2, key), want, rtol=1e-6, atol=1e-6)
    # demodulation ran in the training space: radiance = fbeta_used * irradiance + emission
    rad, em = cache.read(2, "lr/radiance"), cache.read(2, "lr/emission")
    np.testing.assert_allclose(cache.read(2, "lr/fbeta_used") * cache.read(2, "lr/irradiance") + em, rad,
                               rtol=1e-5, atol=1e-5)


def test_unknown_working_space_is_one_clear_error(tmp_path):
    from gbuffer_export.clip import ClipError, open_clip
    from gbuffer_export.synthetic import SyntheticLook, make_synthetic_clip
    path = make_synthetic_clip(tmp_path / "clip", frames=(1,), hr_size=(16, 8), scale=4, look=SyntheticLook(scene_linear="Filmic Log"))
    with pytest.raises(ClipError, match=r"manifest\.json: scene_linear: working colour space 'Filmic Log'"):
        open_clip(path).read(1, "hr/radiance", space="Linear Rec.709")
    pytest.importorskip("torch")
    proc = run_cli("evaluate", "--model", "bicubic", "--data", path, "--json", tmp_path / "e.json")
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "scene_linear" in proc.stderr and "Filmic Log" in proc.stderr


@pytest.mark.bpy
@requires_bpy
def test_clip_rendered_in_acescg_loads_as_the_rec709_render(tmp_path):
    """The same scene rendered with the .blend's working space Linear Rec.709 and ACEScg (Blender converts the
    file's colours when the space changes): the manifest names the space, the training cache loads the converted
    colour buffers, and they match the Rec.709 render (colours to float rounding, radiance within 4-spp noise)."""
    from gbuffer_export.clip import open_clip
    from gbuffer_export.colour_spaces import conversion_matrix
    from training.cache import ClipCache
    clips = {}
    for kind in ("colours", "acescg"):
        blend = make_blend(kind, tmp_path / f"{kind}.blend")
        clips[kind] = tmp_path / kind
        run_cli("render", blend, "-o", clips[kind], "--frames", "2:2", "--hr-size", "64x36", "--buffers",
                "radiance,albedo,emission,fbeta,flags", "--hr-spp", "4", "--lr-spp", "2", "--gbuffer-spp", "1",
                "--threads", "1", "--no-progress", check=True)
    rec709, acescg = open_clip(clips["colours"]), open_clip(clips["acescg"])
    assert (rec709.scene_linear, acescg.scene_linear) == ("Linear Rec.709", "ACEScg")
    keys = [f"{lvl}/{b}" for lvl in ("hr", "lr") for b in ("radiance", "albedo", "emission", "fbeta")]
    loaded = ClipCache(clips["acescg"], cache_dir=tmp_path / "cache").ensure(keys)
    reference = ClipCache(clips["colours"], cache_dir=tmp_path / "cache").ensure(keys)
    m = conversion_matrix("ACEScg")
    for key in keys:
        raw = acescg.read(2, key).astype(np.float64)
        got, ref = loaded.read(2, key), reference.read(2, key)
        tol = 2e-3 if key.endswith("albedo") else 1e-5  # albedo is cached as float16
        np.testing.assert_allclose(got, np.einsum("ij,hwj->hwi", m, raw), rtol=tol, atol=tol, err_msg=key)
        if key.endswith("radiance"):  # the same image in expectation; the stored ACEScg values are not
            mean, mean_ref, mean_raw = (a.reshape(-1, 3).mean(0) for a in (got, ref, raw))
            np.testing.assert_allclose(mean, mean_ref, rtol=0.01, err_msg=key)
            assert np.abs(mean_raw / mean_ref - 1).max() > 0.03, key
        else:  # colours of the materials: what the Rec.709 scene holds (Blender stored them converted, in float32)
            np.testing.assert_allclose(got, ref, rtol=max(tol, 1e-4), atol=max(tol, 1e-4), err_msg=key)
            assert np.abs(raw - ref).max() > 0.05, key


# ------------------------------------------------------------------------------------------------ Delta E ITP

@pytest.mark.torch
def test_delta_e_itp_against_colour_through_xyz():
    pytest.importorskip("torch")
    from training.metrics import ITP_WHITE_NITS, delta_e_itp
    rng = np.random.default_rng(1)
    gt = rng.gamma(1.0, 0.5, (12, 16, 3))
    sr = gt * rng.uniform(0.9, 1.1, gt.shape)
    # independent path: Rec.709 RGB -> XYZ -> ICtCp, absolute luminance ITP_WHITE_NITS * Y
    def ictcp(a):
        return colour.XYZ_to_ICtCp(ITP_WHITE_NITS * colour.RGB_to_XYZ(a, "ITU-R BT.709"), method="ITU-R BT.2100-2 PQ")
    want = np.mean(colour.delta_E(ictcp(sr), ictcp(gt), method="ITP"))
    assert delta_e_itp(sr, gt) == pytest.approx(want, rel=1e-6)
    assert delta_e_itp(gt, gt) == 0.0
    grey = np.full((4, 4, 3), 1.0)  # a 1% brighter grey at 203 cd/m^2: under one just-noticeable difference
    assert 0.0 < delta_e_itp(1.01 * grey, grey) < 1.0 < delta_e_itp(1.1 * grey, grey)
