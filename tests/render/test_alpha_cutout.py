"""Alpha cut-outs (``surface``, the default): the HR G-buffer pass passes alpha-0 texels as the LR render does, and
the AOV buffers (albedo, roughness, metallic, specular) describe the surface the data passes describe, the first
whose alpha reaches the view layer's pass alpha threshold, never a sum over the layers a camera ray passes. A tiny
scene (tests/scenes.py ``cutout``: a checkered wall behind a two-faced green metallic pane whose alpha is a 0/1
checker mask on its left half and 0.25 on its right; ``nocutout``: the wall alone), 128x64 HR, 4x, one frame,
rendered twice through ``blendsr render`` in one process (``cli_batch``).

Tolerances (measured, 2026-11-27): at the holes of the mask every G-buffer (depth, normal, flags, albedo,
roughness, metallic, specular, emission, point-sampled HR F_beta; LR F_beta too) equals the wall's without the pane
bit for bit at HR and LR; on the pane's opaque texels the AOVs are the pane's own values exactly. Before the fix HR
depth there was the pane's (3 m, not 8 m) and HR/LR albedo, roughness and metallic reached 1.6, 2.4 and 2.0.
Right of x = 0 (alpha 0.25, under the threshold 0.5) Cycles picks per sample whether a path passes or stops on the
pane, so only the ranges are checked there."""
from __future__ import annotations

import numpy as np
import pytest

from gbuffer_export import Flag, open_clip
from tests.conftest import requires_bpy, run_cli
from tests.render.cli_batch import make_blends, run_cli_batch

pytestmark = [pytest.mark.bpy, requires_bpy]
ARGS = ["--frames", "1:1", "--hr-size", "128x64", "--scales", "4", "--hr-spp", "4", "--lr-spp", "4",
        "--gbuffer-spp", "1", "--buffers", "all", "--hr-fbeta", "point", "--threads", "1", "--no-progress"]
PANE = {"albedo": (0.2, 0.8, 0.3), "roughness": (0.9,), "metallic": (1.0,)}
BUFFERS = ("depth", "normal", "flags", "albedo", "roughness", "metallic", "specular", "emission", "fbeta")
ALPHA = np.uint32(Flag.ALPHA)


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    d = tmp_path_factory.mktemp("cutout")
    blends = make_blends(["cutout", "nocutout"], d)
    for proc in run_cli_batch(*[["render", blend, "-o", d / kind, *ARGS] for kind, blend in blends.items()]):
        assert proc.returncode == 0, proc.stderr[-3000:]
    return open_clip(d / "cutout"), open_clip(d / "nocutout")


def _regions(clip, level):
    """Pane texels (the pane's depth), the mask's holes (the wall inside the pane's box, left half)."""
    d = clip.read(1, f"{level}/depth")[..., 0]
    pane = d < 4.0
    ys, xs = np.nonzero(pane & (np.arange(d.shape[1]) < d.shape[1] // 2))
    box = np.zeros_like(pane)
    box[ys.min():ys.max() + 1, xs.min():xs.max() + 1] = True
    return pane & box, box & ~pane


@pytest.mark.parametrize("level", ["hr", "lr"])
def test_cutout_holes_show_the_surface_behind(clips, level):
    cut, wall = clips
    opaque, holes = _regions(cut, level)
    assert holes.sum() >= (30 if level == "hr" else 4) and opaque.sum() >= (30 if level == "hr" else 4)
    for buf in BUFFERS:  # the holes: the wall, as without the pane
        np.testing.assert_array_equal(cut.read(1, f"{level}/{buf}")[holes], wall.read(1, f"{level}/{buf}")[holes],
                                      err_msg=f"{level}/{buf}")
    assert np.allclose(cut.read(1, f"{level}/depth")[holes], 8.0, atol=0.01)
    flags = cut.read(1, f"{level}/flags")[..., 0]
    assert ((flags[opaque] & ALPHA) != 0).all() and ((flags[holes] & ALPHA) == 0).all()
    for buf, want in PANE.items():  # alpha 1: the pane's own values, as without alpha
        np.testing.assert_array_equal(cut.read(1, f"{level}/{buf}")[opaque], np.float32([want] * opaque.sum()),
                                      err_msg=f"{level}/{buf}")


def test_cutout_buffers_stay_in_range_and_validate(clips):
    cut, _ = clips
    for level in ("hr", "lr"):  # the alpha-0.25 half included
        for buf in ("albedo", "roughness", "metallic", "specular"):
            v = cut.read(1, f"{level}/{buf}")
            assert v.min() >= 0.0 and v.max() <= 1.0, (level, buf, v.max())
    proc = run_cli("validate", cut.path)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
