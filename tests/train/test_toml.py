"""The TOML writer of training.config (run directories' config.toml): tomli-w, a [train] dependency, or an
equivalent fallback in environments made before it was one; both escape every control character."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

TRICKY = {"data": {"clips": ["a\nb", 'q"uote', "back\\slash", "tab\there", "bell\x07", "del\x7f", "é ü"],
                   "crop": 48, "ratio": 0.5, "on": True, "inf": float("inf")},
          "model": {"name": "fusesr", "fusesr": {"note": "line1\r\nline2"}}}


@pytest.mark.parametrize("writer", ["tomli_w", "fallback"])
def test_config_toml_escapes_every_control_character(writer, monkeypatch):
    """training.config.dict_to_toml (tomli-w, the [train] extra; or its fallback in an older environment) writes
    TOML that reads back to the same values, newlines and control characters included."""
    import sys
    import tomllib
    if writer == "tomli_w":
        pytest.importorskip("tomli_w")
    else:
        monkeypatch.setitem(sys.modules, "tomli_w", None)  # import raises ModuleNotFoundError
    from training.config import dict_to_toml
    text = dict_to_toml(TRICKY)
    assert tomllib.loads(text) == TRICKY
    assert "\x07" not in text and "\x7f" not in text


def test_tomli_w_is_a_train_dependency():
    text = (ROOT / "pyproject.toml").read_text()
    assert re.search(r'train = \[[^\]]*"tomli-w>=', text)
