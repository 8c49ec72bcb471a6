"""``materials = "untextured"`` (``gbuffer_export.blender.materials.make_untextured``): a tiny scene of two image
textured planes rendered with its materials kept and untextured, through ``blendsr render``."""
from __future__ import annotations

import numpy as np
import pytest

from gbuffer_export import open_clip
from gbuffer_export.colour_spaces import srgb_decode
from tests.conftest import make_blend, requires_bpy, run_cli
from tests.render.cli_batch import run_cli_batch

pytestmark = [pytest.mark.bpy, requires_bpy]
ARGS = ["--frames", "1:1", "--hr-size", "64x36", "--hr-spp", "1", "--lr-spp", "1", "--gbuffer-spp", "1",
        "--jitter", "none", "--buffers", "radiance,albedo,normal,flags", "--no-progress"]


@pytest.fixture(scope="module")
def imagetex(blend_dir):
    return make_blend("imagetex", blend_dir / "imagetex.blend")


def _halves(clip, level: str):
    """The albedo of the left plane (red/blue stripes) and the right one (green/white checker), a margin of 2 px
    kept from the seam at the image's centre."""
    alb = clip.read(1, f"{level}/albedo")
    w = alb.shape[1]
    return alb[:, : w // 2 - 2].reshape(-1, 3), alb[:, w // 2 + 2:].reshape(-1, 3)


def test_untextured_flattens_each_material_to_its_images_mean(imagetex, tmp_path):
    scene = imagetex
    for proc in run_cli_batch(*[["render", scene, "-o", tmp_path / mode, "--materials", mode, *ARGS]
                                for mode in ("keep", "untextured")]):  # one process (cli_batch)
        assert proc.returncode == 0, proc.stderr[-3000:]
    keep, flat = open_clip(tmp_path / "keep"), open_clip(tmp_path / "untextured")
    assert "material_mode" not in keep.manifest  # the scene's own materials: the manifest as before the key
    mode = flat.manifest["material_mode"]
    assert mode["mode"] == "untextured" and mode["links_replaced"] == 3  # two base colours and one bump height
    # means in linear light: sRGB-stored colours decoded before averaging; the Non-Color height map as stored
    np.testing.assert_allclose(mode["image_means"]["stripes"][:3], [0.5, 0.0, 0.5], atol=1e-4)
    green = (srgb_decode(np.array([0.2, 0.8, 0.2])) + srgb_decode(np.array([0.9, 0.9, 0.9]))) / 2
    np.testing.assert_allclose(mode["image_means"]["checker"][:3], green, atol=2e-3)
    np.testing.assert_allclose(mode["image_means"]["checker_height"][:3], [0.5, 0.5, 0.5], atol=1e-4)
    for level in ("hr", "lr"):
        for (k, f), mean in zip(zip(_halves(keep, level), _halves(flat, level)), ([0.5, 0.0, 0.5], green)):
            assert k.std(axis=0).max() > 0.05, (level, k.std(axis=0))  # textured: the pattern is in the albedo
            assert f.std(axis=0).max() < 1e-3, (level, f.std(axis=0))  # untextured: flat per material
            np.testing.assert_allclose(f.mean(axis=0), mean, atol=2e-3)
    # geometry stays (the same flags, the unbumped plane's normals), the bump map's detail goes (flat normals)
    np.testing.assert_array_equal(keep.read(1, "hr/flags"), flat.read(1, "hr/flags"))
    nk, nf = keep.read(1, "hr/normal"), flat.read(1, "hr/normal")
    w = nk.shape[1]
    np.testing.assert_array_equal(nk[:, : w // 2 - 2], nf[:, : w // 2 - 2])
    assert nf[:, w // 2 + 2:].reshape(-1, 3).std(axis=0).max() < 1e-5


def test_an_unknown_material_mode_is_one_line_exit_2(imagetex, tmp_path):
    scene = imagetex  # argparse refuses it before Blender loads
    proc = run_cli("render", scene, "-o", tmp_path / "x", "--materials", "grey", *ARGS)
    assert proc.returncode == 2
    err = [ln for ln in proc.stderr.splitlines() if "error:" in ln]
    assert len(err) == 1 and "--materials" in err[0] and "'grey'" in err[0] and "'untextured'" in err[0], \
        proc.stderr[-800:]
