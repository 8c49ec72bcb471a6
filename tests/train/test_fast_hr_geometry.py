"""``fusesr-fast``'s ``hr_geometry`` (training/models/fusesr_fast.py, "HR geometry"): it reads the HR depth, normals
and albedo, starts as the network without it (also from weights trained without it, through ``run.init_from``),
changes the output once trained, takes the gradient, and is refused where it means nothing."""
import types

import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.typed_table import ConfigError  # noqa: E402
from training.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, save_checkpoint  # noqa: E402
from training.config import ModelConfig  # noqa: E402
from training.inference.export import example_inputs  # noqa: E402
from training.models import build_model  # noqa: E402
from training.train import init_from  # noqa: E402


def _batch(model, seed=3):
    return {k: torch.from_numpy(v) for k, v in example_inputs(model, None, (48, 32), seed=seed).items()}


def test_hr_geometry_starts_as_the_network_without_it_and_then_reads_the_hr_gbuffers(tmp_path):
    torch.manual_seed(0)
    plain = build_model(ModelConfig.of("fusesr-fast", residual_clamp="lr-guided"), 4).eval()
    path = tmp_path / "plain.pt"
    save_checkpoint(path, {"model": plain.state_dict(), "scale": 4, "step": 1, "format": CHECKPOINT_FORMAT,
                           "version": CHECKPOINT_VERSION})
    model = build_model(ModelConfig.of("fusesr-fast", residual_clamp="lr-guided", hr_geometry=True), 4).eval()
    assert {"hr/depth", "hr/normal", "hr/albedo"} <= set(model.needs())
    assert not {"hr/albedo"} & set(plain.needs())
    cfg = types.SimpleNamespace(run=types.SimpleNamespace(init_from=str(path)),
                                model=types.SimpleNamespace(name="fusesr-fast"))
    init_from(model, cfg, 4)
    assert sum(p.numel() for p in model.parameters()) - sum(p.numel() for p in plain.parameters()) == 7 * 16 * 32 + 32
    batch = _batch(model)
    with torch.no_grad():
        assert torch.equal(model(batch), plain(batch))
    model.train()
    model(batch).mean().backward()
    assert float(model.hr_in.weight.grad.abs().max()) > 0  # zero weights, non-zero gradient: it learns
    with torch.no_grad():
        model.eval().hr_in.weight.normal_(0.0, 0.1)
        moved = model(batch)
        other = dict(batch, **{"hr/albedo": batch["hr/albedo"].flip(-1)})  # other HR albedo, same everything else
        assert float((moved - plain(batch)).abs().max()) > 1e-3
        assert float((model(other) - moved).abs().max()) > 1e-4


def test_hr_geometry_is_refused_where_it_means_nothing():
    with pytest.raises(ConfigError, match="hr_geometry needs model.fusesr-fast.hr_gbuffer"):
        ModelConfig.of("fusesr-fast", hr_geometry=True, hr_gbuffer=False)
    for name in ("fusesr", "fusesr-l"):
        with pytest.raises(ConfigError, match="is fusesr-fast's"):
            ModelConfig.of(name, hr_geometry=True)
