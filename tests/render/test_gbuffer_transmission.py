"""``gbuffer_transmission``: with "behind" every G-buffer describes the first surface that is not transmissive, at HR
and at every LR level, as the same scene with the panes deleted; ``flags`` keep TRANSMISSION there (the reactive
mask) and the radiance is the "surface" render's. A tiny scene (tests/scenes.py ``glasspane``: a checkered wall
under the sky behind a Principled glass pane and a Glass BSDF pane; ``nopane``: the same without them), 64x32 HR,
4x and 2x, two frames of a moving camera, rendered four times through ``blendsr render`` in one process
(``cli_batch``).

Tolerances (measured, 2026-11-27): depth, albedo, roughness, metallic, specular, emission and the footprint HR
F_beta behind the panes are bit-identical to the scene without them; normals differ by at most 6e-8, motion by
2e-6 px and LR F_beta by 1.5e-6: a ray that passes a transparent surface is relaunched from the hit point, so the
surface behind is found from another origin (float32 rounding). The bounds below are about 10x those."""
from __future__ import annotations

import filecmp

import numpy as np
import pytest

from gbuffer_export import Flag, open_clip
from gbuffer_export.regions import dilate
from tests.conftest import requires_bpy, run_cli
from tests.render.cli_batch import make_blends, run_cli_batch

pytestmark = [pytest.mark.bpy, requires_bpy]
ARGS = ["--frames", "1:2", "--hr-size", "64x32", "--scales", "4,2", "--hr-spp", "4", "--lr-spp", "4",
        "--gbuffer-spp", "1", "--buffers", "all", "--threads", "1", "--no-progress"]
LEVELS = ("hr", "lr", "lr_x2")
#: buffer -> absolute tolerance against the scene without panes (module docstring)
TOL = {"depth": 0.0, "albedo": 0.0, "roughness": 0.0, "metallic": 0.0, "specular": 0.0, "emission": 0.0,
       "normal": 1e-6, "motion": 2e-5, "motion_next": 2e-5, "fbeta": 2e-5}
T = np.uint32(Flag.TRANSMISSION)


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    d = tmp_path_factory.mktemp("transmission")
    blends = make_blends(["glasspane", "nopane"], d)
    glass, nopane = blends["glasspane"], blends["nopane"]
    runs = {"surface": (glass, "surface"), "behind": (glass, "behind"), "nopane": (nopane, "surface"),
            "nopane_behind": (nopane, "behind")}
    procs = run_cli_batch(*[["render", scene, "-o", d / name, "--gbuffer-transmission", mode, *ARGS]
                            for name, (scene, mode) in runs.items()])
    for proc in procs:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return {name: open_clip(d / name) for name in runs}


def _transmission(clip, frame, level):
    return (clip.read(frame, f"{level}/flags")[..., 0] & T) != 0


def test_behind_gbuffers_are_those_of_the_scene_without_the_panes(clips):
    b, n, s = clips["behind"], clips["nopane"], clips["surface"]
    for frame in b.frames:
        for level in LEVELS:
            glass = s.read(frame, f"{level}/depth")[..., 0] != n.read(frame, f"{level}/depth")[..., 0]
            assert 0.3 < glass.mean() < 0.9, (level, glass.mean())  # both panes, the wall and the sky beside them
            # the reactive mask: exactly where a pane is the first surface (the Glass BSDF's pixels too)
            np.testing.assert_array_equal(_transmission(b, frame, level), glass, err_msg=level)
            bg = (b.read(frame, f"{level}/flags")[..., 0] & np.uint32(Flag.BACKGROUND)) != 0
            assert (bg & glass).any() and (~bg & glass).any(), level  # the sky and the wall seen through glass
            # otherwise the flags of the surface behind
            np.testing.assert_array_equal(b.read(frame, f"{level}/flags")[..., 0] & ~T,
                                          n.read(frame, f"{level}/flags")[..., 0], err_msg=level)
            for buf, tol in TOL.items():
                if buf == "fbeta" and level == "hr":
                    continue  # the footprint HR F_beta: the next test
                got, want = b.read(frame, f"{level}/{buf}"), n.read(frame, f"{level}/{buf}")
                np.testing.assert_allclose(got, want, rtol=0, atol=tol, err_msg=f"{level}/{buf} frame {frame}")
                # where no glass is in front, the "surface" render's G-buffers (the same samples)
                np.testing.assert_array_equal(got[~glass], s.read(frame, f"{level}/{buf}")[~glass],
                                              err_msg=f"{level}/{buf} frame {frame}")
            # the radiance is the "surface" render's, bit for bit (the panes are restored for it)
            np.testing.assert_array_equal(b.read(frame, f"{level}/radiance"), s.read(frame, f"{level}/radiance"))


def test_behind_footprint_fbeta_is_the_filtered_surface_behind_glass(clips):
    """The footprint HR F_beta comes from the ground truth's colour passes, which see the glass: within 1 px of it
    they come from a render of the surface behind with the ground truth's filter, seed and samples (as the scene
    without the panes gives them), elsewhere from the ground truth as with "surface"."""
    b, n, s = clips["behind"], clips["nopane"], clips["surface"]
    assert b.manifest["render"]["gbuffer"]["hr_fbeta"] == "footprint"
    for frame in b.frames:
        near = dilate(_transmission(b, frame, "hr"), 1)
        fb, fn = b.read(frame, "hr/fbeta"), n.read(frame, "hr/fbeta")
        np.testing.assert_allclose(fb, fn, rtol=0, atol=TOL["fbeta"])
        np.testing.assert_array_equal(fb[~near], s.read(frame, "hr/fbeta")[~near])
        assert (~near).sum() > 100 and b.record(frame)["hr"]["seconds"]["footprint"] > 0


def test_the_manifest_records_behind_and_surface_keeps_its_identity(clips):
    b, s = clips["behind"], clips["surface"]
    assert "transmission" not in s.manifest["render"]["gbuffer"]  # "surface": the manifest as before the key
    g = b.manifest["render"]["gbuffer"]
    assert g["transmission"] == "behind" and g["transmissive_materials"] == ["glass", "glass_bsdf"]
    assert "G-buffer render over its bounding box" in g["lr_source"]
    for level in ("lr", "lr_x2"):  # one G-buffer render per LR level, with the LR render's seed
        rec = b.record(1)[level]
        assert rec["gbuffer_seed"] == rec["seed"] and rec["seconds"]["gbuffer"] > 0
        assert "gbuffer_seed" not in s.record(1)[level]
    # "surface" flags the Principled pane only (the material bit), and its depth is the pane's
    assert (_transmission(s, 1, "hr") & (s.read(1, "hr/depth")[..., 0] < 3.5)).sum() > 0
    proc = run_cli("validate", b.path)  # the sky seen through glass is not an emission-background error
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]


def test_behind_without_transmissive_materials_renders_as_surface(clips):
    n, nb = clips["nopane"], clips["nopane_behind"]
    g = nb.manifest["render"]["gbuffer"]
    assert g["transmission"] == "behind" and g["transmissive_materials"] == [] and "no extra render" in \
        g["transmission_note"]
    exrs = sorted(p.relative_to(n.path) for p in n.path.rglob("*.exr"))
    assert exrs and exrs == sorted(p.relative_to(nb.path) for p in nb.path.rglob("*.exr"))
    assert all(filecmp.cmp(n.path / p, nb.path / p, shallow=False) for p in exrs)
    assert "gbuffer" not in nb.record(1)["lr"]["seconds"]  # no extra render
