"""The FuseSR family's ``confidence_gate`` (training/models/fusesr.py, "Confidence gate"): closed, the output is the
residual base; open, it is the ungated network with the same weights; the gradient reaches the gate; ``run.init_from``
starts the gate fresh from a checkpoint made without it, and nothing else."""
import types

import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.typed_table import ConfigError  # noqa: E402
from training.config import ModelConfig  # noqa: E402
from training.inference.export import example_inputs  # noqa: E402
from training.models import build_model  # noqa: E402
from training.models.base import current  # noqa: E402
from training.models.fusesr import GATE_OPEN  # noqa: E402
from training.train import init_from  # noqa: E402
from training.transforms import forward_transform  # noqa: E402

NAMES = ["fusesr-fast", "fusesr-l", "fusesr"]


def _batch(model, size=(48, 32), seed=3):
    return {k: torch.from_numpy(v) for k, v in example_inputs(model, None, size, seed=seed).items()}


def _gated(name, **opts):
    torch.manual_seed(0)
    return build_model(ModelConfig.of(name, confidence_gate=True, **opts), 4).eval()


@pytest.mark.parametrize("name", NAMES)
def test_closed_gate_outputs_the_residual_base_and_open_the_ungated_network(name):
    gated = _gated(name, residual_clamp="lr-guided")
    plain = build_model(ModelConfig.of(name, residual_clamp="lr-guided"), 4).eval()
    plain.load_state_dict({k: v for k, v in gated.state_dict().items() if not k.startswith("confidence.")})
    batch = _batch(gated)
    color = forward_transform(current(batch, gated.color_key), gated.transform)
    with torch.no_grad():
        base = gated.output(torch.zeros(1, 3, 32, 48), color, batch, gated.frame_jitter(batch))
        gated.confidence.bias.fill_(-60.0)
        closed = gated(batch)
        gated.confidence.bias.fill_(60.0)
        opened, ungated = gated(batch), plain(batch)
    assert torch.equal(closed, base)
    assert torch.allclose(opened, ungated, rtol=1e-6, atol=1e-7)
    assert float((opened - base).abs().max()) > 1e-3  # the network's correction is not 0: the test can tell


def test_gate_starts_nearly_open_reads_the_features_and_takes_the_gradient():
    model = _gated("fusesr-fast").train()
    assert float(model.confidence.weight.detach().abs().max()) == 0.0
    assert torch.allclose(model.confidence.bias, torch.full_like(model.confidence.bias, GATE_OPEN))
    model(_batch(model)).mean().backward()
    assert float(model.confidence.weight.grad.abs().max()) > 0.0
    assert float(model.confidence.bias.grad.abs().max()) > 0.0


def test_gate_needs_the_residual_base():
    with pytest.raises(ConfigError, match="confidence_gate needs model.fusesr-fast.residual"):
        ModelConfig.of("fusesr-fast", confidence_gate=True, residual=False)
    assert build_model(ModelConfig.of("fusesr-fast"), 4).confidence is None  # off by default: the paper's head


def _cfg(init):
    return types.SimpleNamespace(run=types.SimpleNamespace(init_from=str(init)),
                                 model=types.SimpleNamespace(name="fusesr-fast"))


def _ungated_weights(tmp_path):
    """fusesr-fast weights made without the gate: an ungated network's, saved by ``save_checkpoint``."""
    from training.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, save_checkpoint
    torch.manual_seed(1)
    plain = build_model(ModelConfig.of("fusesr-fast", residual_clamp="lr-guided"), 4)
    path = tmp_path / "plain.pt"
    save_checkpoint(path, {"model": plain.state_dict(), "scale": 4, "step": 7, "format": CHECKPOINT_FORMAT,
                           "version": CHECKPOINT_VERSION})
    return path, plain


def test_init_from_ungated_weights_starts_only_the_gate_fresh(tmp_path, caplog):
    path, plain = _ungated_weights(tmp_path)
    model = _gated("fusesr-fast", residual_clamp="lr-guided")
    with caplog.at_level("INFO", logger="training.train"):
        init_from(model, _cfg(path), 4)
    assert "confidence.weight, confidence.bias start fresh" in caplog.text
    for k, v in plain.state_dict().items():
        assert torch.equal(model.state_dict()[k], v), k
    assert float(model.confidence.weight.detach().abs().max()) == 0.0
    narrow = build_model(ModelConfig.of("fusesr-fast", confidence_gate=True, width=16), 4)
    with pytest.raises(ConfigError, match="do not fit model fusesr-fast"):
        init_from(narrow, _cfg(path), 4)


@pytest.mark.parametrize("extra", [{}, {"transmission_fallback": True}], ids=["gate", "gate+fallback"])
def test_gated_network_runs_the_fused_hr_stage_and_exports_to_onnx(fused_then_onnx, extra):
    """The gate (and ``transmission_fallback``, which reads the HR flags: the example inputs hold TRANSMISSION on
    about half the pixels) acts before the fused HR stage (unchanged): the fused torch stage equals the eager output,
    and the ONNX export (the flags an int32 input) matches torch (a gate that reads its features: random 1x1
    weights)."""
    model = _gated("fusesr-fast", residual_clamp="lr-guided", **extra)
    with torch.no_grad():
        model.confidence.weight.normal_(0.0, 0.3)
    report = fused_then_onnx(model, _batch(model), "gated")
    assert ("hr_flags" in report["inputs"]) == bool(extra)  # the graph reads the flags only with the fallback


def test_gate_learns_at_its_own_rate_through_the_schedule():
    """``optim.gate_lr_scale``: the gate's parameters in a group of their own at lr x scale, kept in that ratio by
    the schedule; 1 is one group; a scale for a model without a gate is refused."""
    from training.config import load_config
    from training.trainer import lr_lambda, param_groups
    cfg = load_config(None, ['model.name="fusesr-fast"', "optim.gate_lr_scale=30", "optim.lr=1e-4",
                             "run.max_steps=10"])
    model = _gated("fusesr-fast")
    groups = param_groups(model, cfg)
    assert len(groups) == 2 and groups[1]["lr"] == pytest.approx(3e-3)
    assert {id(p) for p in groups[1]["params"]} == {id(model.confidence.weight), id(model.confidence.bias)}
    assert sum(len(g["params"]) for g in groups) == len(list(model.parameters()))
    opt = torch.optim.Adam(groups, lr=cfg.optim.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_lambda(cfg))
    for _ in range(5):
        opt.step()
        sched.step()
        net, gate = (g["lr"] for g in opt.param_groups)
        assert net < 1e-4 and gate == pytest.approx(30 * net)
    cfg.optim.gate_lr_scale = 1.0
    assert len(param_groups(model, cfg)) == 1
    cfg.optim.gate_lr_scale = 30.0
    with pytest.raises(ConfigError, match="has no confidence gate"):
        param_groups(build_model(ModelConfig.of("fusesr-fast"), 4), cfg)
