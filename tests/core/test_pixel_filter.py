"""Cycles' pixel filters as discrete weights (gbuffer_export.pixel_filter), checked against the formula and against
Cycles itself: a point-sampled render convolved with the weights must give the filtered render."""
import subprocess
import sys

import numpy as np
import pytest

from gbuffer_export import pixel_filter as pf
from gbuffer_export.exr import read_exr
from tests.conftest import ENV, requires_bpy


def _cycles_bh(v, width):  # Cycles' filter_func_blackman_harris after filter_table's width *= 2
    v = 2 * np.pi * (v / (2 * width) + 0.5)
    return 0.35875 - 0.48829 * np.cos(v) + 0.14128 * np.cos(2 * v) - 0.01168 * np.cos(3 * v)


def test_weights_integrate_the_filter_over_each_pixel():
    x = np.linspace(-1.5, 1.5, 300001)
    f = _cycles_bh(x, 1.5)
    cells = [(x >= o - 0.5) & (x < o + 0.5) for o in (-1, 0, 1)]
    ref = np.array([f[c].sum() for c in cells])
    np.testing.assert_allclose(pf.weights_1d("BLACKMAN_HARRIS", 1.5), ref / ref.sum(), atol=2e-4)
    for kind, width in (("BLACKMAN_HARRIS", 1.5), ("GAUSSIAN", 1.5), ("BOX", 3.0)):
        w = pf.weights_1d(kind, width)
        assert w.sum() == pytest.approx(1.0) and np.allclose(w, w[::-1]) and len(w) % 2 == 1
    np.testing.assert_array_equal(pf.weights_1d("GAUSSIAN", 0.01), [1.0])  # BlendSR's point sampling
    np.testing.assert_allclose(pf.weights_1d("BOX", 3.0), [1 / 3] * 3)
    with pytest.raises(ValueError, match="pixel filter 'MITCHELL'"):
        pf.weights_1d("MITCHELL", 1.5)


def test_convolve_is_separable_and_replicates_edges():
    img = np.zeros((5, 7, 1), np.float32)
    img[2, 3] = 1.0
    w = np.array([0.25, 0.5, 0.25])
    out = pf.convolve(img, w)
    np.testing.assert_allclose(out[1:4, 2:5, 0], np.outer(w, w), atol=1e-7)
    np.testing.assert_allclose(pf.convolve(np.ones((4, 4, 3)), w), 1.0)


_RENDER = r"""
import sys, bpy
out, size = sys.argv[-1], (48, 32)
bpy.ops.wm.read_factory_settings(use_empty=True)
sc = bpy.context.scene
sc.render.engine = "CYCLES"
sc.cycles.device = "CPU"
sc.render.resolution_x, sc.render.resolution_y = size
sc.render.resolution_percentage = 100
sc.render.image_settings.file_format = "OPEN_EXR"
sc.render.image_settings.color_depth = "32"
sc.view_settings.view_transform = "Standard"
mesh = bpy.data.meshes.new("p")
mesh.from_pydata([(-1, 0, -1), (1, 0, -1), (1, 0, 1), (-1, 0, 1)], [], [(0, 1, 2, 3)])
obj = bpy.data.objects.new("p", mesh)
sc.collection.objects.link(obj)
mat = bpy.data.materials.new("m")
nt = mat.node_tree
nt.nodes.clear()
em = nt.nodes.new("ShaderNodeEmission")
chk = nt.nodes.new("ShaderNodeTexChecker")
chk.inputs["Scale"].default_value = 9.0
chk.inputs["Color1"].default_value = (4.0, 4.0, 4.0, 1)
chk.inputs["Color2"].default_value = (0.05, 0.05, 0.05, 1)
nt.links.new(chk.outputs["Color"], em.inputs["Color"])
outn = nt.nodes.new("ShaderNodeOutputMaterial")
nt.links.new(em.outputs[0], outn.inputs["Surface"])
mesh.materials.append(mat)
cam = bpy.data.objects.new("c", bpy.data.cameras.new("c"))
cam.location, cam.rotation_euler = (0.1, -3.0, 0.05), (1.5708, 0, 0.13)
sc.collection.objects.link(cam)
sc.camera = cam
for name, ftype, width, spp, pct in (("filtered", "BLACKMAN_HARRIS", 1.5, 1024, 100),
                                     ("point", "GAUSSIAN", 0.01, 16, 100), ("fine", "GAUSSIAN", 0.01, 16, 400)):
    sc.cycles.pixel_filter_type, sc.cycles.filter_width, sc.cycles.samples = ftype, width, spp
    sc.render.resolution_percentage = pct
    sc.render.filepath = f"{out}/{name}.exr"
    bpy.ops.render.render(write_still=True)
"""


@requires_bpy
def test_point_samples_convolved_with_the_weights_match_a_cycles_filtered_render(tmp_path):
    script = tmp_path / "render.py"
    script.write_text(_RENDER)
    proc = subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True, text=True,
                          timeout=300, env=ENV)
    assert proc.returncode == 0, proc.stderr[-2000:]
    filtered = read_exr(tmp_path / "filtered.exr", ("R", "G", "B"))[2:-2, 2:-2]
    point = read_exr(tmp_path / "point.exr", ("R", "G", "B"))
    fine = read_exr(tmp_path / "fine.exr", ("R", "G", "B"))  # point samples on a 4x finer grid

    # 1. The filter function and width convention: the filtered render is the fine point samples weighted by
    #    f(dx) f(dy) about each pixel centre (fine samples sit at (j + 1/2) / 4 pixels).
    def through_filter(width):
        def matrix(n):
            d = (np.arange(4 * n) + 0.5)[None, :] / 4 - (np.arange(n) + 0.5)[:, None]
            m = pf.evaluate("BLACKMAN_HARRIS", width, d)
            return m / m.sum(1, keepdims=True)
        my, mx = matrix(point.shape[0]), matrix(point.shape[1])
        out = np.einsum("ij,jkc,lk->ilc", my, fine.astype(np.float64), mx)
        return np.abs(out[2:-2, 2:-2] - filtered).mean()

    cycles, half_width = through_filter(1.5), through_filter(0.75)  # 0.75: without Cycles' width doubling
    assert cycles < 0.5 * half_width, (cycles, half_width)  # measured 0.069 against 0.238

    # 2. The pixel weights BlendSR applies to point-sampled images (one sample per pixel): closer to the filtered
    #    render than no filter or the half-width filter (the rest is sub-pixel detail one sample cannot hold).
    def err(w):
        return np.abs(pf.convolve(point, w)[2:-2, 2:-2] - filtered).mean()

    right, half, none = err(pf.weights_1d("BLACKMAN_HARRIS", 1.5)), err(pf.weights_1d("BLACKMAN_HARRIS", 0.75)), \
        err(np.array([1.0]))
    assert right < 0.8 * none and right < 0.8 * half, (right, half, none)  # measured 0.267, 0.410, 0.426


def test_footprint_fbeta_keeps_point_values_near_background_and_where_the_filtered_one_is_unusable():
    point = np.full((6, 7, 3), 0.5, np.float32)
    point[:, 0] = 1.0  # background column
    filtered = np.full((6, 7, 3), 0.3, np.float32)
    filtered[4, 5] = np.nan
    filtered[2, 5, 1] = 0.0
    bg = np.zeros((6, 7), bool)
    bg[:, 0] = True
    out = pf.footprint_fbeta(point, filtered, bg)
    np.testing.assert_array_equal(out[:, :2], point[:, :2])  # background and its 1-pixel neighbours: point
    np.testing.assert_array_equal(out[4, 5], point[4, 5])    # non-finite filtered value
    np.testing.assert_array_equal(out[2, 5], point[2, 5])    # a zero channel where the point value is positive
    assert np.all(out[0, 2:5] == 0.3) and out.dtype == np.float32
    zero = np.zeros_like(point)  # a black surface: zero either way
    assert np.all(pf.footprint_fbeta(zero, zero, bg)[:, 2:] == 0)
