"""White-furnace benchmark pieces: pixel-to-material assignment (numpy) and an end-to-end furnace render (bpy)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gbuffer_export.commands.bench_brdf import material_map, sphere_ids, summarise, update_docs, DOC_BEGIN, DOC_END

REPO = Path(__file__).resolve().parents[2]


def _camera_looking_down_y(distance=10.0):
    m = np.eye(4)
    # columns: camera X -> world X, camera Y -> world Z, camera Z -> world -Y (looks along +Y, as the furnace camera)
    m[:3, 0], m[:3, 1], m[:3, 2] = (1, 0, 0), (0, 0, 1), (0, -1, 0)
    m[:3, 3] = (0, -distance, 0)
    return m


def test_sphere_ids_and_margin():
    layout = {"spheres": [{"centre": [0.0, 0.0, 0.0], "radius": 1.0}, {"centre": [3.0, 0.0, 0.0], "radius": 1.0}]}
    cam = {"world_from_camera": _camera_looking_down_y(), "intrinsics": (20.0, 20.0, 16.0, 8.0), "jitter": (0, 0)}
    ids = material_map(layout, cam, (32, 16), margin=0.0)
    # sphere 0 projects to a disc of radius ~ f * r / sqrt(d^2 - r^2) = 2.01 px around (16, 8); sphere 1 at x = 22
    assert ids[8, 16] == 0 and ids[8, 22] == 1 and ids[0, 0] == -1
    # analytic check of every pixel centre against the projected circles
    ys, xs = np.mgrid[0:16, 0:32] + 0.5
    rad = 20.0 * 1.0 / np.sqrt(100.0 - 1.0)
    inside0 = (xs - 16) ** 2 + (ys - 8) ** 2 < rad ** 2 * 0.98
    assert np.all(ids[inside0] == 0)
    eroded = material_map(layout, cam, (32, 16), margin=0.5)
    assert eroded[8, 16] == 0 and (eroded == 0).sum() < (ids == 0).sum()
    assert np.all((eroded == ids) | (eroded == -1))
    # nearest hit wins when spheres overlap in projection
    layout2 = {"spheres": [{"centre": [0.0, 2.0, 0.0], "radius": 1.0}, {"centre": [0.0, 0.0, 0.0], "radius": 1.0}]}
    assert sphere_ids(layout2, cam["world_from_camera"], cam["intrinsics"], np.array([16.0]), np.array([8.0]))[0] == 1


def test_update_docs_replaces_block(tmp_path):
    p = tmp_path / "brdf.md"
    p.write_text(f"# T\n\nintro\n\n{DOC_BEGIN}\nold\n{DOC_END}\n\ntail\n")
    update_docs(p, "new table")
    text = p.read_text()
    assert "new table" in text and "old" not in text and text.startswith("# T") and text.endswith("tail\n")
    q = tmp_path / "other.md"
    update_docs(q, "first")
    assert DOC_BEGIN in q.read_text() and "first" in q.read_text()


@pytest.mark.bpy
def test_furnace_end_to_end(tmp_path):
    """A 2-sphere furnace rendered by 'blendsr render': the model and Cycles' passes match the furnace truth;
    the split-sum table is far off on a rough metal (VERIFIED-FACTS: -14..-20% at r = 0.5)."""
    blend, layout_path = tmp_path / "f.blend", tmp_path / "layout.json"
    mats = "diel_grey_r0.50,metal_gold_r0.50"
    subprocess.run([sys.executable, "-m", "gbuffer_export.blender.furnace", str(blend), str(layout_path),
                    "--size", "128", "64", "--columns", "2", "--materials", mats], check=True, cwd=REPO,
                   capture_output=True, timeout=300)
    clip = tmp_path / "clip"
    subprocess.run([sys.executable, "-m", "gbuffer_export.cli", "render", str(blend), "-o", str(clip), "--frames",
                    "1:1", "--hr-size", "128x64", "--scale", "4", "--hr-spp", "64", "--lr-spp", "256", "--buffers",
                    "all", "--jitter", "none", "--no-progress", "--threads", "2"], check=True, cwd=REPO,
                   capture_output=True, timeout=600)
    from gbuffer_export.clip import open_clip
    from gbuffer_export.commands.bench_brdf import evaluate

    layout = json.loads(layout_path.read_text())
    res = evaluate(layout, [open_clip(clip)], ("cycles", "lut", "model"))
    for level in ("lr", "hr"):
        grey, gold = res["levels"][level]["materials"]
        assert grey["pixels"] > 20 and gold["pixels"] > 20
        for m in (grey, gold):
            assert abs(m["sources"]["model"]["bias"]) < 0.02, (level, m)
            assert abs(m["sources"]["cycles"]["bias"]) < 0.02, (level, m)
        assert gold["sources"]["lut"]["bias"] < -0.08
    s = summarise(res, ("cycles", "lut", "model"))
    assert s["lr"]["standard"]["model"]["count"] == 2


def test_filter_model():
    from gbuffer_export.commands.bench_brdf import blackman_harris_variance, filter_matched

    var = blackman_harris_variance(1.5)
    # independent: the 4-term Blackman-Harris window on [-1.5, 1.5] px (Cycles doubles filter_width 1.5 to 3)
    x = (np.arange(300000) + 0.5) / 300000 * 3.0 - 1.5
    w = 0.35875 + 0.48829 * np.cos(2 * np.pi * x / 3) + 0.14128 * np.cos(4 * np.pi * x / 3) \
        + 0.01168 * np.cos(6 * np.pi * x / 3)
    assert abs(var - np.sum(x * x * w) / np.sum(w)) < 1e-6
    # on a quadratic image the second-order model is exact: filtering x^2 + y^2 adds 2 var
    ys, xs = np.mgrid[0:9, 0:9].astype(float)
    img = (xs ** 2 + ys ** 2)[..., None]
    out = filter_matched(img, var)
    np.testing.assert_allclose(out[2:-2, 2:-2], img[2:-2, 2:-2] + 2 * var, atol=1e-9)


def test_bench_brdf_rejects_bad_arguments(tmp_path):
    from gbuffer_export.cli import main

    out = ["--out", str(tmp_path / "o"), "--docs", ""]
    assert main(["bench", "brdf", "--sources", "cycles,nope", *out]) == 2
    assert main(["bench", "brdf", "--hr-size", "642x480", *out]) == 2
    assert main(["bench", "brdf", "--reuse", *out]) == 2
    assert not (tmp_path / "o").exists()
