"""gbuffer_export.regions: the pixel regions of an error breakdown, checked on a hand-built frame."""
import numpy as np
import pytest

from gbuffer_export.conventions import Flag
from gbuffer_export.regions import REGIONS, error_breakdown, pixel_regions


def frame(h=12, w=16):
    """Sky in rows 0-3; below, a ground plane seen at a grazing angle (inverse depth affine in y, depth from 1 m to
    50 m: its depth ratio between rows reaches 40%) with a box 0.5 m away in rows 7-9, columns 5-9."""
    flags = np.zeros((h, w, 1), np.uint32)
    flags[:4] = int(Flag.BACKGROUND)
    depth = np.full((h, w, 1), np.inf)
    inv = np.linspace(1 / 50, 1.0, h - 4)
    depth[4:, :, 0] = 1.0 / inv[:, None]
    depth[7:10, 5:10] = 0.5
    return flags, depth


def test_regions_of_a_hand_built_frame():
    flags, depth = frame()
    r = pixel_regions(flags, depth)
    assert tuple(r) == REGIONS
    total = sum(m.astype(int) for m in r.values())
    assert (total == 1).all()  # disjoint, covering the frame
    sil = np.zeros((12, 16), bool)
    sil[3:5] = True  # the last sky row and the first ground row
    np.testing.assert_array_equal(r["silhouette"], sil)
    box = np.zeros((12, 16), bool)
    box[7:10, 5:10] = True
    pad = np.pad(box, 1)
    four = pad[:-2, 1:-1] | pad[2:, 1:-1] | pad[1:-1, :-2] | pad[1:-1, 2:]  # a 4-neighbour in the box
    pad = np.pad(~box, 1)
    four_out = pad[:-2, 1:-1] | pad[2:, 1:-1] | pad[1:-1, :-2] | pad[1:-1, 2:]
    edge = (box & four_out) | (~box & four)
    edge[:4] = False
    np.testing.assert_array_equal(r["depth_edge"], edge)  # none on the grazing ground however fast its depth grows
    np.testing.assert_array_equal(r["background"], np.arange(12)[:, None].repeat(16, 1) < 3)
    assert r["interior"].sum() == 12 * 16 - 3 * 16 - 2 * 16 - edge.sum()


def test_error_breakdown_shares_and_means():
    flags, depth = frame()
    r = pixel_regions(flags[..., 0], depth[..., 0])
    err = np.random.default_rng(0).random((12, 16))
    b = error_breakdown(err, r)
    assert sum(v["fraction"] for v in b.values()) == pytest.approx(1.0)
    assert sum(v["err_share"] for v in b.values()) == pytest.approx(1.0)
    for name, m in r.items():
        assert b[name]["mse"] == pytest.approx(err[m].mean())
    zero = error_breakdown(np.zeros((12, 16)), {"all": np.ones((12, 16), bool), "none": np.zeros((12, 16), bool)})
    assert zero == {"all": {"fraction": 1.0, "mse": 0.0, "err_share": None},
                    "none": {"fraction": 0.0, "mse": None, "err_share": None}}
    with pytest.raises(ValueError, match="differ in size"):
        pixel_regions(flags[:5], depth)


def test_material_classes_take_the_first_that_applies():
    """Background wins over every material flag, transmission over a coat, a coat or thin film over low roughness;
    roughness 0.25 itself is rough (the threshold is strict); no material, or a non-Principled shader reading
    roughness 0 (not written), is unknown, while a Glossy BSDF's 0.1 is glossy and a Diffuse BSDF's 1 rough; NaN is
    rough."""
    from gbuffer_export.regions import GLOSSY_ROUGHNESS, MATERIALS, material_regions
    fl = np.array([[Flag.BACKGROUND | Flag.TRANSMISSION, Flag.TRANSMISSION | Flag.COAT, Flag.COAT, Flag.THIN_FILM,
                    0, 0, Flag.SHEEN, Flag.NO_MATERIAL, Flag.NON_PRINCIPLED, Flag.NON_PRINCIPLED,
                    Flag.NON_PRINCIPLED, 0]], np.uint32)
    rough = np.array([[0.0, 0.0, 0.0, 0.9, 0.1, GLOSSY_ROUGHNESS, 0.1, 0.8, 0.0, 0.1, 1.0, np.nan]])
    m = material_regions(fl[..., None], rough[..., None])
    assert tuple(m) == MATERIALS
    assert (sum(v.astype(int) for v in m.values()) == 1).all()
    got = [next(k for k, v in m.items() if v[0, i]) for i in range(fl.shape[1])]
    assert got == ["background", "transmission", "coated", "coated", "glossy", "rough", "glossy", "unknown", "unknown",
                   "glossy", "rough", "rough"]
    with pytest.raises(ValueError, match="differ in size"):
        material_regions(fl, rough[:, :3])
