"""FuseSR's ``hr_material`` (training/models/fusesr.py, "Material inputs"): the HR branch reads HR roughness and
metallic too; weights trained without them load through ``run.init_from`` with zero weights on the new channels, so
the network starts exactly as theirs, and the new channels then take the gradient and change the output."""
import types

import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.typed_table import ConfigError  # noqa: E402
from training.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, save_checkpoint  # noqa: E402
from training.config import ModelConfig  # noqa: E402
from training.inference.export import example_inputs  # noqa: E402
from training.models import build_model  # noqa: E402
from training.models.fusesr import HR_MATERIAL_KEYS  # noqa: E402
from training.train import init_from  # noqa: E402

CASES = [("fusesr-l", {}), ("fusesr", {"hr_guide": True})]


def _batch(model, size=(48, 32), seed=3):
    return {k: torch.from_numpy(v) for k, v in example_inputs(model, None, size, seed=seed).items()}


def _cfg(name, init):
    return types.SimpleNamespace(run=types.SimpleNamespace(init_from=str(init)),
                                 model=types.SimpleNamespace(name=name))


def test_material_inputs_need_the_hr_branch_and_add_their_buffers():
    with pytest.raises(ConfigError, match="hr_material needs model.fusesr-l.hr_gbuffer"):
        ModelConfig.of("fusesr-l", hr_material=True, hr_gbuffer=False)
    plain = build_model(ModelConfig.of("fusesr-l"), 4)
    wide = build_model(ModelConfig.of("fusesr-l", hr_material=True), 4)
    assert not set(HR_MATERIAL_KEYS) & set(plain.needs()) and set(HR_MATERIAL_KEYS) <= set(wide.needs())
    assert wide.hr_branch[0].weight.shape[1] == plain.hr_branch[0].weight.shape[1] + 2 * 16


@pytest.mark.parametrize("name,extra", CASES, ids=[c[0] for c in CASES])
def test_init_from_weights_without_them_starts_as_their_network(tmp_path, caplog, name, extra):
    torch.manual_seed(1)
    plain = build_model(ModelConfig.of(name, residual_clamp="lr-guided", **extra), 4).eval()
    path = tmp_path / "plain.pt"
    save_checkpoint(path, {"model": plain.state_dict(), "scale": 4, "step": 7, "format": CHECKPOINT_FORMAT,
                           "version": CHECKPOINT_VERSION})
    torch.manual_seed(2)
    wide = build_model(ModelConfig.of(name, residual_clamp="lr-guided", hr_material=True, **extra), 4).eval()
    with caplog.at_level("INFO", logger="training.train"):
        init_from(wide, _cfg(name, path), 4)
    grown = [k for k in wide.GROWN_INPUTS if k in wide.state_dict()]
    assert f"{', '.join(grown)} gain zero-weighted input channels" in caplog.text
    batch = _batch(wide)
    with torch.no_grad():
        assert torch.allclose(wide(batch), plain(batch), rtol=1e-5, atol=1e-6)   # summation order may differ
    wide.train()
    wide(batch).mean().backward()
    for k in grown:
        grad = dict(wide.named_parameters())[k].grad
        assert float(grad[:, -2 * 16 if k.startswith("hr_branch") else -2:].abs().max()) > 0.0, k
    with torch.no_grad():
        wide.hr_branch[0].weight[:, -2 * 16:].normal_(0.0, 0.3)
        assert float((wide.eval()(batch) - plain(batch)).abs().max()) > 1e-4   # the channels reach the output


def test_material_inputs_run_the_fused_hr_stage_and_export_to_onnx(fused_then_onnx):
    torch.manual_seed(0)
    model = build_model(ModelConfig.of("fusesr-l", residual_clamp="lr-guided", hr_material=True), 4).eval()
    report = fused_then_onnx(model, _batch(model), "material")
    assert {"hr_roughness", "hr_metallic"} <= set(report["inputs"])
