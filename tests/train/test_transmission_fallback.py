"""The FuseSR family's ``transmission_fallback`` (training/models/fusesr.py, "Transmission fallback"): on HR pixels
whose flags carry TRANSMISSION the output is the residual base, elsewhere the network with the same weights without
the option; it reads ``hr/flags`` only when on, needs the residual base, and can be set on a trained checkpoint. Its
fused stage and ONNX export: tests/train/test_confidence_gate.py."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.conventions import Flag  # noqa: E402
from gbuffer_export.typed_table import ConfigError  # noqa: E402
from training.config import ModelConfig  # noqa: E402
from training.inference.export import example_inputs  # noqa: E402
from training.inference.loading import with_inference_options  # noqa: E402
from training.models import build_model  # noqa: E402
from training.models.base import current  # noqa: E402
from training.models.fusesr import FuseSRFrame  # noqa: E402
from training.transforms import forward_transform  # noqa: E402

NAMES = ["fusesr-fast", "fusesr-l", "fusesr"]


def _models(name):
    torch.manual_seed(0)
    on = build_model(ModelConfig.of(name, residual_clamp="lr-guided", confidence_gate=True,
                                     transmission_fallback=True), 4).eval()
    off = build_model(ModelConfig.of(name, residual_clamp="lr-guided", confidence_gate=True), 4).eval()
    off.load_state_dict(on.state_dict())
    return on, off


@pytest.mark.parametrize("name", NAMES)
def test_transmission_pixels_get_the_residual_base_and_the_others_the_network(name):
    """Glass (TRANSMISSION, with ALPHA beside it) over the left half, other bits on the right. The remodulation
    filters with the ground truth's pixel filter (a few pixels wide), so the halves are compared away from the seam."""
    on, off = _models(name)
    batch = {k: torch.from_numpy(v) for k, v in example_inputs(on, None, (48, 32), seed=3).items()}
    flags = np.zeros((1, 1, 1, 32, 48), np.uint32)
    flags[..., :24] = int(Flag.TRANSMISSION | Flag.ALPHA)
    flags[..., 24:] = int(Flag.BACKGROUND | Flag.COAT)
    batch["hr/flags"] = torch.from_numpy(flags)
    color = forward_transform(current(batch, on.color_key), on.transform)
    with torch.no_grad():
        base = on.output(torch.zeros(1, 3, 32, 48), color, batch, on.frame_jitter(batch))
        fell, plain = on(batch), off(batch)
    glass, rest = (slice(None), slice(None), slice(None), slice(0, 20)), (slice(None),) * 3 + (slice(28, 48),)
    assert torch.equal(fell[glass], base[glass])
    assert torch.allclose(fell[rest], plain[rest], rtol=1e-6, atol=1e-7)
    assert float((plain - base)[glass].abs().max()) > 1e-3  # the network corrects there: the test can tell


@pytest.mark.parametrize("dtype", [torch.float32, torch.int32, torch.uint32])  # loaders, ONNX, a clip's cache
def test_mask_reads_the_transmission_bit_only(dtype):
    flags = torch.tensor([0, 1, 2048, 2049, 4096, 2048 | 32768, 2047, 6144], dtype=torch.int64).view(1, 1, 1, 1, 8)
    mask = FuseSRFrame.transmission_mask({"hr/flags": flags.to(dtype)})
    assert mask.flatten().tolist() == [0, 0, 1, 1, 0, 1, 0, 1]


def test_reads_flags_only_when_on_and_needs_the_residual_base():
    assert "hr/flags" in build_model(ModelConfig.of("fusesr-fast", transmission_fallback=True), 4).needs()
    assert "hr/flags" not in build_model(ModelConfig.of("fusesr-fast"), 4).needs()
    with pytest.raises(ConfigError, match="transmission_fallback needs model.fusesr-l.residual"):
        ModelConfig.of("fusesr-l", transmission_fallback=True, residual=False)


def test_is_an_inference_option_of_a_checkpoint():
    config = {"model": {"name": "fusesr-fast", "fusesr-fast": {"confidence_gate": True}}}
    out = with_inference_options(config, ["transmission_fallback=true"], "ck")
    assert out["model"]["fusesr-fast"] == {"confidence_gate": True, "transmission_fallback": True}
    assert "transmission_fallback" not in config["model"]["fusesr-fast"]


def test_gate_transmission_starts_as_the_gate_learns_and_can_close_on_glass():
    """``gate_transmission``: a weight on the mask added to the gate's logit, from 0 (the gated network unchanged); it
    takes the gradient, and at -60 the glass half is the residual base; refused without the gate."""
    torch.manual_seed(0)
    on = build_model(ModelConfig.of("fusesr-fast", residual_clamp="lr-guided", confidence_gate=True,
                                     gate_transmission=True), 4)
    off = build_model(ModelConfig.of("fusesr-fast", residual_clamp="lr-guided", confidence_gate=True), 4)
    off.load_state_dict({k: v for k, v in on.state_dict().items() if k != "confidence_transmission"})
    batch = {k: torch.from_numpy(v) for k, v in example_inputs(on, None, (48, 32), seed=3).items()}
    flags = np.zeros((1, 1, 1, 32, 48), np.uint32)
    flags[..., :24] = int(Flag.TRANSMISSION)
    batch["hr/flags"] = torch.from_numpy(flags)
    assert "confidence_transmission" in on.GATE_PARAMETERS and "confidence_transmission" in on.FRESH_PARAMETERS
    on.train()(batch).mean().backward()
    assert float(on.confidence_transmission.grad.abs()) > 0.0
    on.eval(), off.eval()
    color = forward_transform(current(batch, on.color_key), on.transform)
    with torch.no_grad():
        assert torch.equal(on(batch), off(batch))
        on.confidence_transmission.fill_(-60.0)
        base = on.output(torch.zeros(1, 3, 32, 48), color, batch, on.frame_jitter(batch))
        closed, plain = on(batch), off(batch)
    assert torch.equal(closed[..., :20], base[..., :20])
    assert torch.allclose(closed[..., 28:], plain[..., 28:], rtol=1e-6, atol=1e-7)
    with pytest.raises(ConfigError, match="gate_transmission needs model.fusesr-fast.confidence_gate"):
        ModelConfig.of("fusesr-fast", gate_transmission=True)


def test_gate_transmission_learns_with_the_gate_and_starts_fresh_from_older_weights(tmp_path):
    """``confidence_transmission`` is in the gate's parameter group (``optim.gate_lr_scale``), and ``run.init_from``
    of weights made without it (no error) keeps it at its start, 0, and loads everything else."""
    import types
    from training.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, save_checkpoint
    from training.config import load_config
    from training.train import init_from
    from training.trainer import param_groups
    cfg = load_config(None, ['model.name="fusesr-fast"', "model.fusesr-fast.confidence_gate=true",
                             "model.fusesr-fast.gate_transmission=true", "optim.gate_lr_scale=100", "optim.lr=1e-4"])
    torch.manual_seed(1)
    model = build_model(ModelConfig.of("fusesr-fast", confidence_gate=True, gate_transmission=True), 4)
    groups = param_groups(model, cfg)
    assert id(model.confidence_transmission) in {id(p) for p in groups[1]["params"]}
    assert groups[1]["lr"] == pytest.approx(1e-2)
    older = build_model(ModelConfig.of("fusesr-fast", confidence_gate=True), 4)
    path = tmp_path / "older.pt"
    save_checkpoint(path, {"model": older.state_dict(), "scale": 4, "step": 3, "format": CHECKPOINT_FORMAT,
                           "version": CHECKPOINT_VERSION})
    init_from(model, types.SimpleNamespace(run=types.SimpleNamespace(init_from=str(path)),
                                           model=types.SimpleNamespace(name="fusesr-fast")), 4)
    assert float(model.confidence_transmission) == 0.0
    assert torch.equal(model.confidence.weight, older.confidence.weight)


def test_onnx_graph_takes_the_flags_as_int32_from_any_source():
    from training.inference.export import graph_dtypes
    for dtype in (np.float32, np.uint32):
        out = graph_dtypes({"hr/flags": np.array([0, 2048], dtype), "hr/depth": np.ones(2, np.float32)})
        assert out["hr/flags"].dtype == np.int32 and out["hr/flags"].tolist() == [0, 2048]
        assert out["hr/depth"].dtype == np.float32
