"""tests/train: the torch layer: data, models, trainer, evaluation (every test here needs torch). Every test here is marked `train` and `torch`."""
from pathlib import Path

import pytest

from tests.conftest import mark_folder


def pytest_collection_modifyitems(items):
    mark_folder(items, Path(__file__).parent, pytest.mark.train, pytest.mark.torch)



@pytest.fixture
def fused_then_onnx(tmp_path):
    """``check(model, batch, name)``: the fused torch HR stage gives the eager output on ``batch``, and the ONNX export
    of ``InferenceModel(model, name)`` (64x48 HR) matches torch; returns the export's report (its ``inputs``)."""
    pytest.importorskip("onnxruntime")
    import torch

    from training.inference.export import export_onnx
    from training.inference.model import InferenceModel

    def check(model, batch, name: str) -> dict:
        with torch.no_grad():
            eager = model(batch)
            model.hr_impl = "torch"
            fused = model(batch)
        model.hr_impl = None
        assert torch.allclose(fused, eager, rtol=1e-5, atol=1e-6)
        report = export_onnx(InferenceModel(model, name), tmp_path / f"{name}.onnx", hr_size=(64, 48))
        assert report["match"], report
        return report
    return check
