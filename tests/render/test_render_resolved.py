"""A render resolved once (gbuffer_export.blender.render_setup.resolve_render -> frozen ResolvedRender, through its five
stages) and the pass table (gbuffer_export.blender.convert.PASSES: enabling a pass and planning it from one row). bpy
runs in a subprocess."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from tests.conftest import ENV, REPO, requires_bpy

pytestmark = [pytest.mark.bpy, requires_bpy]

SCRIPT = r'''
import dataclasses, json, sys
from pathlib import Path
from gbuffer_export.config import RenderConfig
from gbuffer_export.blender.convert import PASSES, PassPlan, plan_passes
from gbuffer_export.blender.default_scene import build_default_scene
from gbuffer_export.blender.render import resolve_render, set_passes

out = {"fields": [f.name for f in dataclasses.fields(PassPlan)], "rows": list(PASSES)}
out["plans"] = {f"{b}/{fb}": dataclasses.asdict(plan_passes(b.split(","), fb, ())) for b, fb in
                (("radiance", "cycles"), ("depth", "cycles"), ("motion_next", "cycles"), ("emission", "cycles"),
                 ("fbeta", "cycles"), ("fbeta", "lut"), ("flags,normal", "cycles"))}
cfg = RenderConfig(output=Path(sys.argv[1]), frames=(2, 5), hr_size=(64, 32), scales=(2, 4), shard=(2, 2),
                   buffers=("depth", "motion"), progress=False)
scene = build_default_scene(seed=0, frames=(1, 48), resolution=(64, 32))
r = resolve_render(cfg, scene)
try:
    r.frames = ()
    frozen = False
except dataclasses.FrozenInstanceError:
    frozen = True
vl = r.view_layer
set_passes(vl, r.plan)
out.update(frozen=frozen, frames=list(r.frames), my_frames=list(r.my_frames), hr_size=list(r.hr_size),
           levels={k: [v["width"], v["height"]] for k, v in r.levels.items()}, light=r.light["light"],
           camera=r.cam.name, report=r.camera_report["kind"], plan=dataclasses.asdict(r.plan),
           moving=list(r.moving), flag_lut=len(r.flag_lut) == len(r.materials) + 1,
           switches={s: bool(getattr(vl, s)) for row in PASSES.values() for s in row.switches})
print("RESULT " + json.dumps(out))
'''


def test_a_render_is_resolved_once_and_passes_come_from_their_rows(tmp_path):
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(SCRIPT), str(tmp_path / "clip")], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=240)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-2000:] + proc.stderr[-2000:]
    r = json.loads(lines[-1][len("RESULT "):])
    assert r["fields"] == [*r["rows"], "aovs"]  # one plan field per row of PASSES
    plans = {b: {k for k, v in p.items() if v is True} for b, p in r["plans"].items()}
    assert plans == {"radiance/cycles": set(), "depth/cycles": {"depth"}, "motion_next/cycles": {"depth", "vector"},
                     "emission/cycles": {"depth", "emit"}, "fbeta/cycles": {"depth", "colors", "index"},
                     "flags,normal/cycles": {"depth", "normal", "index"},
                     # a table F_beta: the G-buffers it is computed from, never the colour passes
                     "fbeta/lut": plans["fbeta/lut"] - {"colors"}}
    assert {"depth", "normal", "index"} <= plans["fbeta/lut"]
    assert r["frozen"] and r["frames"] == [2, 3, 4, 5] and r["my_frames"] == [3, 5]  # shard 2/2
    assert r["hr_size"] == [64, 32] and r["levels"] == {"hr": [64, 32], "lr": [32, 16], "lr_x4": [16, 8]}
    assert r["light"] == "auto" and r["report"] == "scene" and r["flag_lut"]  # the default; the built-in keeps its own
    assert r["plan"]["depth"] and r["plan"]["vector"] and not r["plan"]["colors"] and not r["plan"]["normal"]
    assert r["moving"], "the built-in scene's ball moves"
    on = {s for s, v in r["switches"].items() if v}
    assert on == {"use_pass_z", "use_pass_vector"}  # exactly the rows of the planned fields


STAGES_SCRIPT = r'''
import dataclasses, inspect, json, sys
from pathlib import Path
from gbuffer_export.config import RenderConfig
from gbuffer_export.blender import render_setup as rs
from gbuffer_export.blender.default_scene import build_default_scene

sig = [inspect.signature(f) for f in rs.STAGES]
out = {"stages": [f.__name__ for f in rs.STAGES], "returns": [s.return_annotation for s in sig],
       "takes": [list(s.parameters.values())[0].annotation for s in sig[1:]], "seen": []}
cfg = RenderConfig(output=Path(sys.argv[1]), frames=(1, 2), hr_size=(32, 16), scales=(2,), buffers=("depth",),
                   progress=False)
stage = rs.scene_stage(cfg, build_default_scene(seed=0, frames=(1, 48), resolution=(32, 16)), {"builtin": "default"})
for f in rs.STAGES[1:]:
    nxt = f(stage)
    old = [k.name for k in dataclasses.fields(stage)]
    try:
        nxt.cfg = None
        frozen = False
    except dataclasses.FrozenInstanceError:
        frozen = True
    out["seen"].append({"type": type(nxt).__name__, "extends": isinstance(nxt, type(stage)), "frozen": frozen,
                        "kept": all(getattr(nxt, k) is getattr(stage, k) for k in old),
                        "new": [k.name for k in dataclasses.fields(nxt)][len(old):]})
    stage = nxt
out["not_in_stages"] = sorted({k.name for k in dataclasses.fields(rs.ResolvedRender)}
                              - {k.name for k in dataclasses.fields(stage)})
out["light"], out["level"] = stage.light["light"], stage.level
print("RESULT " + json.dumps(out))
'''


def test_the_render_setup_is_five_stages_each_extending_the_frozen_one_before(tmp_path):
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(STAGES_SCRIPT), str(tmp_path / "clip")], cwd=REPO,
                          env=ENV, capture_output=True, text=True, timeout=240)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-2000:] + proc.stderr[-2000:]
    r = json.loads(lines[-1][len("RESULT "):])
    names = ["SceneStage", "UnitStage", "CameraStage", "LightStage", "PassStage"]
    # the order the constraints need: the camera plans on the level in its unit, the light probes the camera's view
    assert r["stages"] == ["scene_stage", "unit_stage", "camera_stage", "light_stage", "pass_stage"]
    assert r["returns"] == names and r["takes"] == names[:-1]  # each a function of the stage before it
    assert [s["type"] for s in r["seen"]] == names[1:]
    assert all(s["extends"] and s["frozen"] and s["kept"] for s in r["seen"]), r["seen"]
    assert [s["new"] for s in r["seen"]] == [["level", "geom", "unit"], ["cam", "camera_report"], ["light"],
                                             ["my_frames", "view_layer", "materials", "plan", "behind", "flag_lut",
                                              "moving"]]
    assert r["not_in_stages"] == ["levels"]  # ResolvedRender is the last stage plus the levels' header
    assert r["light"] == "auto" and r["level"] is None  # the built-in scene keeps its own light, no level measured
