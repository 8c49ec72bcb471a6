"""The torch floor of pyproject.toml ('[train]': torch>=2.5) is the oldest release with every torch API the code
calls (docs/evaluation.md, "torch versions and the ONNX exporter"), and the installed torch has them all."""
from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

#: torch API -> (the release that added it, a file of ours that calls it)
APIS = {
    "torch.serialization.safe_globals": ("2.5", "training/checkpoint.py"),
    "torch.onnx.export(dynamo=)": ("2.5", "training/inference/export.py"),
    "torch.amp.GradScaler": ("2.3", "training/trainer.py"),
}
#: used when present (the refusal message names the globals from 2.6 on)
OPTIONAL = {"torch.serialization.get_unsafe_globals_in_checkpoint": ("2.6", "training/checkpoint.py")}


def _floor() -> str:
    text = (ROOT / "pyproject.toml").read_text()
    m = re.search(r'train = \[[^\]]*"torch>=([0-9.]+)"', text)
    assert m, "pyproject.toml: [train] has no torch>= floor"
    return m.group(1)


def test_floor_is_the_newest_release_among_the_required_apis():
    newest = max((tuple(map(int, v.split("."))) for v, _ in APIS.values()))
    assert tuple(map(int, _floor().split("."))) == newest
    doc = (ROOT / "docs" / "evaluation.md").read_text()
    assert f"`torch>={_floor()}`" in doc
    for api, (_, path) in {**APIS, **OPTIONAL}.items():
        name = api.split("(")[0].rsplit(".", 1)[-1]
        assert name in (ROOT / path).read_text(), f"{path} no longer calls {api}: update APIS and the floor"


@pytest.mark.torch
def test_installed_torch_has_every_api():
    torch = pytest.importorskip("torch")
    from torch.serialization import safe_globals  # noqa: F401
    assert "dynamo" in inspect.signature(torch.onnx.export).parameters
    torch.amp.GradScaler("cuda", enabled=False)
    assert hasattr(torch.serialization, "get_unsafe_globals_in_checkpoint")


@pytest.mark.torch
def test_checkpoint_refusal_still_one_line_without_get_unsafe_globals(tmp_path, monkeypatch):
    """On torch 2.5 (no get_unsafe_globals_in_checkpoint) a crafted checkpoint is still refused in one line."""
    torch = pytest.importorskip("torch")
    import os
    from training.checkpoint import CheckpointError, load_checkpoint
    path = tmp_path / "evil.pt"
    torch.save({"format": "blendsr.checkpoint", "x": os.getcwd}, path)
    monkeypatch.delattr(torch.serialization, "get_unsafe_globals_in_checkpoint")
    with pytest.raises(CheckpointError, match="refused"):
        load_checkpoint(path)

