"""Cycles' thread count: --threads when given, else OMP_NUM_THREADS where set (the library's one thread rule,
resources.default_threads), else Blender's automatic count."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from gbuffer_export.resources import render_threads
from tests.conftest import ENV, REPO, requires_bpy

CODE = """
import json, bpy
from pathlib import Path
from gbuffer_export.blender.render import base_settings
from gbuffer_export.config import RenderConfig
s = bpy.context.scene
out = {}
for n in (0, 3):
    base_settings(s, s.view_layers[0], RenderConfig(output=Path("unused"), threads=n, device="cpu"))
    out[n] = [s.render.threads_mode, s.render.threads]
print(json.dumps(out))
"""


@pytest.mark.parametrize("env, requested, expected", [("", 0, 0), ("", 3, 3), ("2", 0, 2), ("2", 5, 5),
                                                      ("0", 0, 0), ("two", 0, 0)])
def test_the_rule(monkeypatch, env, requested, expected):
    monkeypatch.setenv("OMP_NUM_THREADS", env)
    assert render_threads(requested) == expected


@requires_bpy
@pytest.mark.bpy
def test_blender_renders_on_the_threads_the_rule_gives():
    def run(omp: str | None) -> dict:
        env = {k: v for k, v in ENV.items() if k != "OMP_NUM_THREADS"}
        if omp:
            env["OMP_NUM_THREADS"] = omp
        p = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, env=env, cwd=REPO,
                           timeout=300)
        assert p.returncode == 0, p.stderr[-2000:]
        return json.loads(p.stdout.strip().splitlines()[-1])
    capped, free = run("1"), run(None)
    assert capped["0"] == ["FIXED", 1] and capped["3"] == ["FIXED", 3]
    assert free["0"][0] == "AUTO" and free["3"] == ["FIXED", 3]
