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

results = []
for kind, kw in json.loads(sys.argv[1]):  # several renders in one process, each its own clip and config
    cls = RenderConfig if kind == "before" else WithScratchKey
    try:
        render_clip(cls(**kw))
        results.append(None)
    except Exception as exc:  # the refusal of a render, as the CLI's one line would name it
        results.append(f"{type(exc).__name__}: {exc}")
print("RESULTS " + json.dumps(results))
"""

TINY = dict(hr_size=(32, 16), hr_spp=1, lr_spp=1, gbuffer_spp=1, threads=1, progress=False, frames=(1, 2))


def _render(*runs: tuple[str, dict]) -> list[str | None]:
    """Render each (kind, keys) of ``runs`` in order in one process; None for a clip written, else the error."""
    proc = subprocess.run([sys.executable, "-c", SCRIPT, json.dumps([(kind, {**TINY, **kw}) for kind, kw in runs])],
                          cwd=REPO, env=ENV, capture_output=True, text=True, timeout=300)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULTS ")]
    assert proc.returncode == 0 and lines, proc.stderr[-2000:]
    return json.loads(lines[-1][len("RESULTS "):])


def test_every_key_of_render_config_is_by_hand_or_recorded_from_its_rule():
    cfg = RenderConfig(output="x", hr_size=(32, 16))
    assert recorded_keys(cfg) == {}, "a key outside MANIFEST_BY_HAND changed the manifest of a default clip"
    assert "trial_gain" not in MANIFEST_BY_HAND


@pytest.mark.skipif(not HAVE_BPY, reason="needs bpy")
def test_a_clip_rendered_before_a_new_key_resumes_with_it(tmp_path):
    clip = tmp_path / "clip"
    assert _render(("before", dict(output=str(clip), only_frames=[1]))) == [None]
    old = json.loads((clip / "manifest.json").read_text())
    assert "settings" not in old
    # the key at the value older clips were made with: the same clip, resumed (frame 2 rendered); another value of
    # the key is another clip: refused where the old one lies, recorded under "settings" in a folder of its own
    other = tmp_path / "bright"
    after, bright, bright_new = _render(("after", dict(output=str(clip))),
                                        ("after", dict(output=str(clip), trial_gain="bright")),
                                        ("after", dict(output=str(other), trial_gain="bright", only_frames=[1])))
    assert after is None, after
    new = json.loads((clip / "manifest.json").read_text())
    assert new["identity"] == old["identity"]
    assert (clip / "frames" / "000002.json").is_file()
    assert bright is not None and "holds a different clip" in bright, bright
    assert bright_new is None, bright_new
    assert json.loads((other / "manifest.json").read_text())["settings"] == {"trial_gain": "bright"}
