"""``training.inference.onnx_infer``: the exported graphs run through ONNX Runtime without torch give the torch path's
upscaled frame (``training.inference.loading.upscale_frame``) on a synthetic clip: feed-forward, non-learned, recurrent
(state carried over the lead-in frames) and the any-scale bilinear image."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from tests.conftest import ENV, REPO, edit_manifest  # noqa: E402

#: ONNX Runtime against torch: max |diff| relative to the largest magnitude of the torch frame (export's own check
#: is 1e-4 relative; measured here 1e-7 to 1e-6).
TOL = 1e-4


@pytest.fixture(scope="module")
def graphs(tmp_path_factory):
    from training.inference.export import export_onnx
    from training.inference.loading import load_model
    from training.inference.onnx_infer import graph_name
    out = tmp_path_factory.mktemp("graphs")
    for spec, scale in (("pretrained:fusesr-l", 4), ("demod-jbu", 4), ("pretrained:nsrd", 4), ("bilinear", None)):
        report = export_onnx(load_model(spec, scale or 4), out / graph_name(spec, scale), hr_size=(64, 32))
        assert report["match"], report
    return out


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """Three frames whose ground truth says BlendSR's own pixel filter (a rendered clip's; demod-jbu's graph
    remodulates through the filter it was exported with)."""
    from gbuffer_export.pixel_filter import HR_REFERENCE_FILTER
    c = make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)

    def filt(m):
        m["render"]["hr"]["pixel_filter"], m["render"]["hr"]["filter_width_px"] = HR_REFERENCE_FILTER
    edit_manifest(c, filt)
    return c


@pytest.mark.parametrize("spec", ["pretrained:fusesr-l", "demod-jbu", "pretrained:nsrd"])
def test_onnx_runtime_matches_the_torch_path(graphs, clip, spec):
    from training.inference import onnx_infer
    from training.inference.loading import load_model, upscale_frame
    model = onnx_infer.OnnxModel(onnx_infer.find_graph(graphs, spec, 4))
    bil = onnx_infer.OnnxModel(onnx_infer.find_graph(graphs, "bilinear", 4))
    got = onnx_infer.upscale_frame(model, clip, 3, bilinear=bil)  # 36 HR rows: another size than the export's
    ref = upscale_frame(load_model(spec, 4), clip, 3)  # a recurrent model runs frames 1, 2 first in both
    assert got["sr"].shape == ref["sr"].shape == (36, 64, 3)
    for k in ("sr", "bilinear", "reference"):
        peak = float(np.abs(ref[k]).max())
        assert float(np.abs(got[k] - ref[k]).max()) <= TOL * peak, k
    assert got["ms"] > 0 and model.load_ms > 0


def test_runner_imports_no_torch_and_refuses_another_scale(graphs, clip, tmp_path):
    code = ("import sys; from training.inference import onnx_infer; "
            f"m = onnx_infer.OnnxModel(onnx_infer.find_graph({str(graphs)!r}, 'demod-jbu', 4)); "
            "assert 'torch' not in sys.modules, 'torch imported'; print(m.keys)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=ENV, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    from gbuffer_export.clip import ClipError
    from training.inference import onnx_infer
    assert onnx_infer.find_graph(graphs, "demod-jbu", 2) is None
    other = make_synthetic_clip(tmp_path / "x2", frames=range(1, 2), hr_size=(32, 16), scale=2)
    m = onnx_infer.OnnxModel(onnx_infer.find_graph(graphs, "pretrained:fusesr-l", 4))
    with pytest.raises(ClipError, match="clip scale 2 but pretrained_fusesr-l_x4.onnx upscales by 4"):
        onnx_infer.upscale_frame(m, other, 1, bilinear=m)
    box = make_synthetic_clip(tmp_path / "box", frames=range(1, 2), hr_size=(32, 16), scale=4)  # BOX 1 px
    jbu = onnx_infer.OnnxModel(onnx_infer.find_graph(graphs, "demod-jbu", 4))
    with pytest.raises(ClipError, match="pixel filter is BOX 1 px but demod-jbu_x4.onnx remodulates through "
                                        "BLACKMAN_HARRIS 1.5 px"):
        onnx_infer.upscale_frame(jbu, box, 1, bilinear=m)
