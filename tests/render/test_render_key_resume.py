"""A render key added after a clip was rendered never makes that clip "a different clip" (config.recorded_keys)."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from gbuffer_export.config import MANIFEST_BY_HAND, RenderConfig, recorded_keys
from tests.conftest import ENV, HAVE_BPY, REPO

# A scratch key, as a developer adds one: a field with its rule, nothing written by hand into the manifest.
SCRIPT = r"""
import dataclasses, json, sys
from gbuffer_export.config import RenderConfig
from gbuffer_export.typed_table import option
from gbuffer_export.blender.render import render_clip

@dataclasses.dataclass
class WithScratchKey(RenderConfig):
    trial_gain: str = option("auto", choices=("auto", "bright"), help="a scratch key (test only)")

kind, kw = sys.argv[1], json.loads(sys.argv[2])
cls = RenderConfig if kind == "before" else WithScratchKey
render_clip(cls(**kw))
"""

TINY = dict(hr_size=(32, 16), hr_spp=1, lr_spp=1, gbuffer_spp=1, threads=1, progress=False, frames=(1, 2))


def _render(kind: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", SCRIPT, kind, json.dumps({**TINY, **kw})], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=300)


def test_every_key_of_render_config_is_by_hand_or_recorded_from_its_rule():
    cfg = RenderConfig(output="x", hr_size=(32, 16))
    assert recorded_keys(cfg) == {}, "a key outside MANIFEST_BY_HAND changed the manifest of a default clip"
    assert "trial_gain" not in MANIFEST_BY_HAND


@pytest.mark.skipif(not HAVE_BPY, reason="needs bpy")
def test_a_clip_rendered_before_a_new_key_resumes_with_it(tmp_path):
    clip = tmp_path / "clip"
    before = _render("before", output=str(clip), only_frames=[1])
    assert before.returncode == 0, before.stderr[-2000:]
    old = json.loads((clip / "manifest.json").read_text())
    assert "settings" not in old
    # the key at the value older clips were made with: the same clip, resumed (frame 2 rendered)
    after = _render("after", output=str(clip))
    assert after.returncode == 0, after.stderr[-2000:]
    new = json.loads((clip / "manifest.json").read_text())
    assert new["identity"] == old["identity"]
    assert (clip / "frames" / "000002.json").is_file()
    # another value of the key is another clip: recorded under "settings", and refused where the old one lies
    bright = _render("after", output=str(clip), trial_gain="bright")
    assert bright.returncode != 0 and "holds a different clip" in bright.stderr
    other = tmp_path / "bright"
    assert _render("after", output=str(other), trial_gain="bright", only_frames=[1]).returncode == 0
    assert json.loads((other / "manifest.json").read_text())["settings"] == {"trial_gain": "bright"}
