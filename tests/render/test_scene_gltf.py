"""examples/render_gltf.py on the real glTF models in ../shared/scenes (skipped when absent)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ENV, REPO, requires_bpy, shared_or_skip
from tests.render.test_scene_default import run_probe

pytestmark = [pytest.mark.bpy, pytest.mark.shared, requires_bpy]
MODELS = {"WaterBottle": "scenes/gltf/WaterBottle/glTF/WaterBottle.gltf",
          "Fox": "scenes/gltf/Fox/glTF-Binary/Fox.glb"}


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    paths = {name: shared_or_skip(rel) for name, rel in MODELS.items()}
    tmp = tmp_path_factory.mktemp("gltf")
    res = run_probe("gltf", {"models": [[str(p), str(tmp / f"{name}.blend")] for name, p in paths.items()]})
    return dict(zip(paths, res["models"]))


@pytest.mark.parametrize("name", list(MODELS))
def test_model_is_normalised_onto_a_ground(built, name):
    rec = built[name]
    assert Path(rec["blend"]).is_file()
    for boxes in rec["per_frame"]:
        model = [b for b in boxes if not b[3]]
        ground = [b for b in boxes if b[3]]
        assert [b[0] for b in ground] == ["Ground"]
        lo = np.min([b[1] for b in model], axis=0)
        hi = np.max([b[2] for b in model], axis=0)
        size = hi - lo
        assert 1.0 <= size.max() <= 2.0, size          # WaterBottle is 0.26 m, the Fox about 150 m raw
        assert abs(lo[2]) < 0.05 * size.max()          # standing on the ground (z = 0)
        assert np.abs(0.5 * (lo[:2] + hi[:2])).max() < 0.3 * size.max()
        assert ground[0][2][2] == pytest.approx(0.0, abs=1e-6)


def test_fox_stays_animated(built):
    fox = built["Fox"]
    a, b = (np.array([x[1] + x[2] for x in boxes if not x[3]]) for boxes in fox["per_frame"])
    assert np.abs(a - b).max() > 1e-3  # the skinned mesh moves between frames 1 and 6


@pytest.mark.parametrize("name", list(MODELS))
def test_scene_settings_world_and_packing(built, name):
    rec = built[name]
    assert rec["frames"] == [1, 6] and rec["resolution"] == [320, 180]
    assert rec["camera"] == "BlendSR Camera"
    w = rec["world"]
    assert w["background_color_from"] == "TEX_ENVIRONMENT"
    assert Path(w["image"]).name == "courtyard.exr" and Path(w["image"]).parent == Path(w["studiolights"])
    assert rec["packed"] and not rec["unpacked"]


def test_script_renders_a_clip(tmp_path):
    fox = shared_or_skip(MODELS["Fox"])
    out = tmp_path / "fox"
    proc = subprocess.run([sys.executable, str(REPO / "examples" / "render_gltf.py"), str(fox), "-o", str(out),
                           "--frames", "1:1", "--hr-size", "64x36", "--hr-spp", "2", "--lr-spp", "1",
                           "--gbuffer-spp", "1", "--no-progress"], cwd=REPO, env=ENV, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "fox.blend").is_file()
    from gbuffer_export import open_clip
    clip = open_clip(out)
    assert list(clip.frames) == [1]  # one frame: a render's cost here is its Cycles calls under the HDRI world
    depth = clip.read(1, "hr/depth")[..., 0]
    assert depth.shape == (36, 64)
    assert np.isfinite(depth).mean() > 0.3   # the orbit camera sees the fox and the ground
