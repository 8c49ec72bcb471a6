"""The add-on inside the bpy module: registration, property defaults against the CLI, the one mapping to
RenderConfig, panel drawing against a recording layout, and the two operators on a tiny scene built in code.
Every bpy script runs in its own subprocess (registration is global state; a crash in Blender kills the process)."""
from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from tests.conftest import ENV, REPO, requires_bpy

pytestmark = [pytest.mark.bpy, requires_bpy]

PRELUDE = r'''
import json, sys
import bpy
import blender_addon

def emit(obj):
    print("RESULT " + json.dumps(obj), flush=True)

def tiny_scene():
    """Plane + sphere (red Principled) + animated camera + world, frames 1-2."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    bpy.ops.mesh.primitive_plane_add(size=10)
    bpy.ops.mesh.primitive_uv_sphere_add(location=(0, 0, 1))
    mat = bpy.data.materials.new("red")
    mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.8, 0.1, 0.1, 1)
    bpy.context.object.data.materials.append(mat)
    bpy.ops.object.camera_add(location=(0, -8, 2.2), rotation=(1.45, 0, 0))
    cam = bpy.context.object
    sc.camera = cam
    cam.keyframe_insert("location", frame=0)
    cam.location = (0.4, -7.6, 2.3)
    cam.keyframe_insert("location", frame=3)
    w = bpy.data.worlds.new("World")
    sc.world = w
    w.node_tree.nodes["Background"].inputs[0].default_value = (0.6, 0.7, 1.0, 1.0)
    sc.frame_start, sc.frame_end = 1, 2
    return sc

def tiny_settings(sc, out):
    s = sc.blendsr
    s.output_dir = out
    s.use_scene_resolution = False
    s.hr_width, s.hr_height = 64, 36
    s.hr_spp, s.lr_spp, s.gbuffer_spp = 4, 2, 1
    return s
'''


def run_bpy(script: str, *args, helpers: str = "", timeout: float = 240) -> dict:
    """Run PRELUDE + ``helpers`` + ``script`` with this Python (bpy as a module); return the dict it emitted."""
    code = PRELUDE + helpers + textwrap.dedent(script)
    proc = subprocess.run([sys.executable, "-c", code, *map(str, args)], cwd=REPO, env=ENV, capture_output=True,
                          text=True, timeout=timeout)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, (f"exit {proc.returncode}\nstdout:\n{proc.stdout[-3000:]}\n"
                                            f"stderr:\n{proc.stderr[-3000:]}")
    return json.loads(lines[-1][len("RESULT "):])


# ------------------------------------------------------------------------------------------------------------
# Registration, defaults, mapping
# ------------------------------------------------------------------------------------------------------------

def test_register_unregister_twice_and_defaults():
    r = run_bpy(r'''
        CLASSES = ("BLENDSR_OT_export_dataset", "BLENDSR_OT_preview_upscale", "BLENDSR_PT_output",
                   "BLENDSR_PT_view3d")
        before = "gbuffer_export" in sys.modules
        states = []
        for _ in range(2):
            blender_addon.register()
            from blender_addon import prefs, props
            states.append({"scene_prop": hasattr(bpy.types.Scene, "blendsr"),
                           "classes": [hasattr(bpy.types, c) for c in CLASSES]
                           + [props.BlendSRSettings.is_registered, prefs.BlendSRPreferences.is_registered],
                           "ops": [hasattr(bpy.ops.blendsr, "export_dataset"),
                                   hasattr(bpy.ops.blendsr, "preview_upscale")]})
            blender_addon.unregister()
            states.append({"scene_prop": hasattr(bpy.types.Scene, "blendsr"),
                           "classes": [hasattr(bpy.types, c) for c in CLASSES]
                           + [props.BlendSRSettings.is_registered, prefs.BlendSRPreferences.is_registered]})
        blender_addon.register()
        s = bpy.context.scene.blendsr
        rna = s.bl_rna.properties
        defaults = {p.identifier: (list(p.default_array) if getattr(p, "is_array", False) else p.default)
                    for p in rna if p.identifier not in ("rna_type", "name", "dataset")}  # dataset: its own test
        read_only = {k: rna[k].is_readonly for k in ("preview_ms", "preview_psnr", "preview_metric",
                                                     "preview_info", "preview_clip", "last_export")}
        enums = {k: [i.identifier for i in rna[k].enum_items] for k in ("camera_path", "jitter", "fbeta_source")}
        # the model menu's items come from a callback (the library marks a network below demod-jbu)
        enums["preview_model"] = [i[0] for i in props.preview_model_items(s, bpy.context)]
        defaults["preview_model"] = s.preview_model
        model_labels = {i[0]: i[1] for i in props.preview_model_items(s, bpy.context)}
        s.preview_model = "pretrained:nsrd"
        model_set = [s.preview_model]
        from blender_addon import panels
        emit({"before": before, "lib_after_register": "gbuffer_export" in sys.modules, "states": states,
              "defaults": defaults, "read_only": read_only, "enums": enums, "model_labels": model_labels,
              "model_set": model_set,
              "panels": {c.__name__: [c.bl_space_type, c.bl_region_type, getattr(c, "bl_context", ""),
                                      getattr(c, "bl_category", "")] for c in panels.CLASSES},
              "closed": {c.__name__: [getattr(c, "bl_parent_id", ""), "DEFAULT_CLOSED" in getattr(c, "bl_options", ())]
                         for c in panels.CLASSES}})
    ''')
    assert not r["before"] and not r["lib_after_register"], "the add-on must not import the library at register"
    for i, st in enumerate(r["states"]):
        registered = i % 2 == 0
        assert st["scene_prop"] is registered
        assert all(v is registered for v in st["classes"]), st
        if registered:
            assert st["ops"] == [True, True]
    assert all(r["read_only"].values()), r["read_only"]
    assert r["panels"]["BLENDSR_PT_output"] == ["PROPERTIES", "WINDOW", "output", ""]
    assert r["panels"]["BLENDSR_PT_view3d"] == ["VIEW_3D", "UI", "", "BlendSR"]
    # collapsible subpanels (closed at first) instead of one long panel; a subpanel registers after its parent
    subs = {k: v for k, v in r["closed"].items() if v[0]}
    assert len(subs) >= 10 and all(closed for _, closed in subs.values()), r["closed"]
    order = list(r["closed"])
    assert all(order.index(p) < order.index(k) for k, (p, _) in subs.items())

    # Defaults equal the CLI's (and RenderConfig's where the two agree).
    from gbuffer_export.commands.render import add_render_arguments
    from gbuffer_export.config import CAMERA_PATHS, FBETA_SOURCES, JITTERS, RenderConfig
    import argparse
    p = argparse.ArgumentParser()
    add_render_arguments(p)
    cli = p.parse_args(["-o", "x"])
    d = r["defaults"]
    for prop, arg in [("scale", "scale"), ("hr_spp", "hr_spp"), ("lr_spp", "lr_spp"), ("gbuffer_spp", "gbuffer_spp"),
                      ("hr_denoise", "hr_denoise"), ("lr_denoise", "lr_denoise"), ("adaptive", "adaptive"),
                      ("adaptive_min_samples", "adaptive_min_samples"), ("camera_path", "camera_path"),
                      ("seed", "seed"), ("jitter", "jitter"), ("buffers", "buffers"), ("fbeta_source", "fbeta"),
                      ("threads", "threads")]:
        assert d[prop] == getattr(cli, arg), prop
    assert d["adaptive_threshold"] == pytest.approx(cli.adaptive_threshold)
    # CLI defaults None = "the scene's": the add-on's use_scene_* switches are on, no bounce override.
    assert cli.frames is None and d["use_scene_frames"] is True
    assert cli.hr_size is None and d["use_scene_resolution"] is True
    assert cli.max_bounces is None and d["use_max_bounces"] is False
    rc = RenderConfig(output="x")
    for prop, field in [("scale", "scale"), ("hr_spp", "hr_spp"), ("lr_spp", "lr_spp"), ("camera_path", "camera_path"),
                        ("jitter", "jitter"), ("fbeta_source", "fbeta"), ("seed", "seed")]:
        assert d[prop] == getattr(rc, field), prop
    assert d["with_reference"] is False and d["checkpoint"] == "" and d["preview_model"] == "pretrained:fusesr-l"
    assert r["enums"]["camera_path"] == list(CAMERA_PATHS)
    assert r["enums"]["jitter"] == list(JITTERS)
    assert r["enums"]["fbeta_source"] == list(FBETA_SOURCES)
    from training.models import MODELS
    from training.pretrained import PREFIX, PRETRAINED
    for m in r["enums"]["preview_model"]:  # shipped weights, or non-learned models
        assert (m.startswith(PREFIX) and m[len(PREFIX):] in PRETRAINED) or (m in MODELS and not MODELS[m].learned), m
    assert {PREFIX + n for n in PRETRAINED} <= set(r["enums"]["preview_model"])  # every shipped network is offered
    # a shipped network below demod-jbu on its val split says so in the menu (training.pretrained, the weights' JSON)
    from training.pretrained import below_baseline
    for n in PRETRAINED:
        label = r["model_labels"][PREFIX + n]
        assert ("below demod-jbu on val" in label) is below_baseline(n), label
    assert r["model_set"][0] == "pretrained:nsrd"


def test_mapping_equals_cli_config(tmp_path):
    """render_config(settings) equals config_from_args of the equivalent command line, option by option."""
    r = run_bpy(r'''
        sc = tiny_scene()
        blender_addon.register()
        from blender_addon import mapping
        sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage = 1280, 720, 50
        sc.frame_start, sc.frame_end = 3, 9
        s = sc.blendsr
        s.output_dir = sys.argv[1]
        a = mapping.render_config(s, sc).to_json()
        s.use_scene_frames = False; s.frame_start, s.frame_end = 4, 6
        s.use_scene_resolution = False; s.hr_width, s.hr_height = 96, 48
        s.scale = 2; s.hr_spp = 7; s.lr_spp = 3; s.gbuffer_spp = 2; s.hr_denoise = True; s.adaptive = True
        s.adaptive_threshold = 0.05; s.adaptive_min_samples = 5; s.camera_path = "orbit"; s.seed = 11
        s.jitter = "none"; s.buffers = "custom"; s.buffer_set = {"depth", "normal"}; s.fbeta_source = "lut-paper"
        s.use_max_bounces = True
        s.max_bounces = 3; s.threads = 1
        b = mapping.render_config(s, sc).to_json()
        s.hr_width = 97
        try:
            mapping.render_config(s, sc)
            err = ""
        except ValueError as exc:
            err = str(exc)
        emit({"a": a, "b": b, "err": err})
    ''', tmp_path / "out")
    from gbuffer_export.commands.render import add_render_arguments, config_from_args
    import argparse
    p = argparse.ArgumentParser()
    add_render_arguments(p)

    def cli(*args):
        return config_from_args(p.parse_args(["-o", str(tmp_path / "out"), *args, "--no-progress"])).to_json()
    assert r["a"] == json.loads(json.dumps(cli("--frames", "3:9", "--hr-size", "640x360")))
    assert r["b"] == json.loads(json.dumps(cli(
        "--frames", "4:6", "--hr-size", "96x48", "--scale", "2", "--hr-spp", "7", "--lr-spp", "3",
        "--gbuffer-spp", "2", "--hr-denoise", "--adaptive", "--adaptive-threshold", "0.05",
        "--adaptive-min-samples", "5", "--camera-path", "orbit", "--seed", "11", "--jitter", "none",
        "--buffers", "depth,normal", "--fbeta", "lut-paper", "--max-bounces", "3", "--threads", "1")))
    assert "97" in r["err"] and "scale" in r["err"]


# ------------------------------------------------------------------------------------------------------------
# Panels against a recording layout
# ------------------------------------------------------------------------------------------------------------

DRAW = r'''
class Rec:
    """A fake UILayout recording prop/label/operator calls, with nested row/column/box/split."""
    def __init__(self, log, depth=0):
        self.__dict__.update(log=log, depth=depth)
    def __setattr__(self, k, v):
        self.__dict__[k] = v
    def _child(self, kind):
        self.log.append(("open", kind, self.depth))
        return Rec(self.log, self.depth + 1)
    def row(self, **kw): return self._child("row")
    def column(self, **kw): return self._child("column")
    def box(self): return self._child("box")
    def split(self, **kw): return self._child("split")
    def column_flow(self, **kw): return self._child("column_flow")
    def separator(self, **kw): pass
    def prop(self, data, name, **kw):
        ok = name in data.bl_rna.properties
        self.log.append(("prop", name, ok))
    def label(self, text="", **kw):
        self.log.append(("label", text))
    def operator(self, idname, **kw):
        mod, _, op = idname.partition(".")
        self.log.append(("operator", idname, hasattr(getattr(bpy.ops, mod), op)))
        return type("OpProps", (), {})()

def draw_tree(root, skip=()):
    """The log of ``root`` and every subpanel below it (drawn open), in drawing order."""
    from blender_addon import panels
    log = []
    for cls in panels.subtree(root, skip):
        if hasattr(cls, "poll") and not cls.poll(bpy.context):
            continue
        log.append(("panel", cls.bl_idname, getattr(cls, "bl_parent_id", "")))
        cls.draw(type("FakePanel", (), {"layout": Rec(log)})(), bpy.context)
    return log

def draw_all():
    from blender_addon import panels
    # the Dataset subpanels: tests/addon/test_dataset.py
    return {cls.__name__: draw_tree(cls, panels.DATASET_PANELS) for cls in panels.MAIN_PANELS}
'''


def test_panels_draw_with_library(tmp_path):
    r = run_bpy(r'''
        sc = tiny_scene()
        blender_addon.register()
        s = tiny_settings(sc, sys.argv[1])
        from blender_addon import library
        ok = draw_all()
        # torch missing from Blender's Python: the preview section says what to do.
        st = library.status()
        library._CACHE[""] = library.LibraryStatus(True, root=st.root, torch=False, training=True)
        no_torch = draw_all()["BLENDSR_PT_view3d"]
        # results of a preview are shown
        from blender_addon.props import store_preview_results
        store_preview_results(s, ms=12.5, psnr=31.25, metric="m", info="frame 1", clip="c")
        with_results = draw_all()["BLENDSR_PT_output"]
        # the arbitrary-scale network gets a scale field; a fixed-scale one at another scale a warning, and the
        # preview operator refuses it before rendering
        library._CACHE.clear()
        s.preview_model, s.scale = "pretrained:fourier-sr", 3
        any_scale = draw_all()["BLENDSR_PT_output"]
        s.preview_model = "pretrained:fusesr"
        fixed = draw_all()["BLENDSR_PT_output"]
        try:  # in background mode an ERROR report raises
            refused = sorted(bpy.ops.blendsr.preview_upscale())
        except RuntimeError as exc:
            refused = str(exc)
        emit({"ok": ok, "no_torch": no_torch, "with_results": with_results, "any_scale": any_scale,
              "fixed": fixed, "refused": refused})
    ''', tmp_path / "clip", helpers=DRAW)
    n_scale = {k: sum(e[:2] == ["prop", "scale"] for e in r[k]) for k in ("any_scale", "fixed")}  # JSON: lists
    assert n_scale == {"any_scale": 2, "fixed": 1}  # Frames and size's Scale, plus the preview's
    assert "pretrained:fusesr was trained for scale 4, not 3" in [e[1] for e in r["fixed"] if e[0] == "label"]
    assert not any(e[0] == "label" and "trained for scale" in e[1] for e in r["any_scale"])
    assert r["refused"] == ("Error: BlendSR preview: pretrained:fusesr was trained for scale 4, not 3: set Scale to "
                            "it, or choose a model that takes any scale\n")
    for name, log in r["ok"].items():
        props = [e for e in log if e[0] == "prop"]
        assert props and all(e[2] for e in props), f"{name}: unknown property drawn: {props}"
        drawn = {e[1] for e in props}
        assert {"output_dir", "scale", "hr_spp", "lr_spp", "camera_path", "buffers", "fbeta_source", "jitter",
                "frame_start", "frame_end", "hr_width", "hr_height", "checkpoint", "with_reference"} <= drawn
        ops = [e for e in log if e[0] == "operator"]
        assert {e[1] for e in ops} == {"blendsr.export_dataset", "blendsr.preview_upscale", "blendsr.open_output",
                                       "blendsr.contact_sheet", "blendsr.create_camera_paths"} and all(e[2] for e in ops)
        # collapsible subpanels under the head, closed at first; the head holds the export and its buttons
        subs = [e for e in log if e[0] == "panel"]
        assert subs[0][2] == "" and len(subs) >= 5 and all(e[2] == subs[0][1] for e in subs[1:]), subs
        head = log[:next(i for i, e in enumerate(log) if e[0] == "panel" and e[2])]
        assert [e[1] for e in head if e[0] == "operator"] == ["blendsr.export_dataset", "blendsr.open_output",
                                                              "blendsr.contact_sheet"]
        assert len([e for e in head if e[0] == "prop"]) <= 2, head  # the ~35 settings sit in the subpanels
        assert any(e[0] == "open" and e[2] >= 1 for e in log), "nested layouts are drawn"
        labels = [e[1] for e in log if e[0] == "label"]
        # default buffers x 2 levels x 2 frames; size from the channel counts (float32).
        from gbuffer_export.conventions import BUFFERS, DEFAULT_BUFFERS
        nb, nch = len(DEFAULT_BUFFERS), sum(len(BUFFERS[b].channels) for b in DEFAULT_BUFFERS)
        assert f"{nb} buffers x 2 levels x 2 frames = {nb * 4} EXR files" in labels
        mb = nch * 4 * (64 * 36 + 16 * 9) * 2 / 1e6
        assert any(f"at most {mb:.2f} MB" in t for t in labels), labels
        assert any(t.startswith("Time: about") and "cost model" in t for t in labels)
        assert not any("pip install" in t for t in labels)
    labels = [e[1] for e in r["no_torch"] if e[0] == "label"]
    from blender_addon.panels import TORCH_MISSING
    assert [t for t in labels if "torch" in t] == [TORCH_MISSING]  # one line: the preview needs [train]
    assert "External Python" in TORCH_MISSING and "blendsr[train]" in TORCH_MISSING
    labels = [e[1] for e in r["with_results"] if e[0] == "label"]
    assert "Inference: 12.5 ms per frame, warm-up 0 ms" in labels and "PSNR: 31.25 dB" in labels


def test_without_library_panel_says_how_to_install():
    """gbuffer_export blocked on import: registration works, the panel explains, the operator refuses cleanly."""
    r = run_bpy(r'''
        import importlib.abc
        class Block(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("gbuffer_export", "training"):
                    raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        sys.meta_path.insert(0, Block())
        sc = tiny_scene()
        blender_addon.register()
        logs = draw_all()
        try:
            res = bpy.ops.blendsr.export_dataset()
            err = ""
        except RuntimeError as exc:
            res, err = None, str(exc)
        emit({"logs": logs, "err": err, "res": sorted(res) if res else None})
    ''', helpers=DRAW)
    for name, log in r["logs"].items():
        labels = [e[1] for e in log if e[0] == "label"]
        assert any("not importable" in t for t in labels), labels
        assert any("pip install blendsr" in t for t in labels), labels
        assert any("Library path" in t for t in labels), labels
        assert all(e[2] for e in log if e[0] == "prop")
    assert "not importable" in r["err"]


# ------------------------------------------------------------------------------------------------------------
# Operators
# ------------------------------------------------------------------------------------------------------------

def test_export_dataset_operator(tmp_path):
    out = tmp_path / "clip"
    r = run_bpy(r'''
        sc = tiny_scene()
        blender_addon.register()
        s = tiny_settings(sc, sys.argv[1])
        engine = sc.render.engine
        res = bpy.ops.blendsr.export_dataset()
        mats = bpy.data.materials["red"].node_tree.nodes
        first = {"res": sorted(res), "last": s.last_export, "engine_before": engine, "engine": sc.render.engine,
                 "aovs": len(bpy.context.view_layer.aovs), "nodes": len(mats), "res_x": sc.render.resolution_x,
                 "pass_index": [ob.pass_index for ob in sc.objects], "dirty": bpy.data.is_dirty}
        import hashlib, os, pathlib
        from blender_addon import operators
        out = pathlib.Path(sys.argv[1])
        copy = out / operators.CLIP_SCENE_DIR / "untitled.blend"
        sha = lambda: hashlib.sha256(copy.read_bytes()).hexdigest()
        first["copy_sha"] = sha()
        # Open output (the system's file browser, recorded here) and the contact sheet in the Image Editor
        opened = []
        operators.open_folder = lambda path: opened.append(str(path)) or {"FINISHED"}
        first["open"] = [sorted(bpy.ops.blendsr.open_output(target="clip")), opened]
        first["sheet"] = sorted(bpy.ops.blendsr.contact_sheet(target="clip"))
        img = bpy.data.images["BlendSR contact sheet"]
        from PIL import Image  # the PNG gbuffer_export.preview.contact_sheet wrote (in Blender's temporary folder)
        with Image.open(img.filepath) as im:
            first["sheet_image"] = [list(img.size), list(im.size)]
        s.dataset.output_dir = sys.argv[1] + "_dataset"
        try:
            bpy.ops.blendsr.open_output(target="dataset")
            first["no_dataset"] = ""
        except RuntimeError as exc:
            first["no_dataset"] = str(exc)
        # interrupted after frame 1 (frame 2's record gone), then changes a render does not read: selection, the
        # active object, the current frame, the preview's settings
        os.remove(out / "frames" / "000002.json")
        fp = operators.scene_fingerprint(sc)
        for ob in sc.objects:
            ob.select_set(ob.type == "MESH")
        bpy.context.view_layer.objects.active = sc.objects[0]
        sc.frame_current, s.with_reference, s.preview_model = 2, True, "bicubic"
        unchanged = operators.scene_fingerprint(sc) == fp
        resumed = sorted(bpy.ops.blendsr.export_dataset())
        resumed_sha, resumed_last = sha(), s.last_export
        # what a render reads changes the fingerprint: a material's colour, a moved object (refused: other clip)
        mat_in = bpy.data.materials["red"].node_tree.nodes["Principled BSDF"].inputs["Base Color"]
        mat_in.default_value = (0.1, 0.8, 0.1, 1)
        material_changes = operators.scene_fingerprint(sc) != fp
        mat_in.default_value = (0.8, 0.1, 0.1, 1)
        back = operators.scene_fingerprint(sc) == fp
        sc.objects[0].location.x += 1
        try:
            moved = str(sorted(bpy.ops.blendsr.export_dataset()))
        except RuntimeError as exc:
            moved = str(exc)
        emit({**first, "unchanged": unchanged, "resumed": resumed, "resumed_sha": resumed_sha,
              "resumed_last": resumed_last, "material_changes": material_changes, "back": back, "moved": moved})
    ''', out)
    assert r["res"] == ["FINISHED"], r
    # a clip export resumes after changes that do not affect what it renders (the scene copy's fingerprint)
    assert r["unchanged"] and r["resumed"] == ["FINISHED"] and r["resumed_sha"] == r["copy_sha"], r
    assert "OK" in r["resumed_last"]
    assert r["material_changes"] and r["back"]
    assert r["open"] == [["FINISHED"], [str(out)]]
    assert r["sheet"] == ["FINISHED"] and min(r["sheet_image"][0]) > 36, r["sheet_image"]  # the clip's tiles
    assert r["sheet_image"][0] == r["sheet_image"][1]
    assert "no such folder yet; render the dataset first" in r["no_dataset"], r["no_dataset"]
    assert "the open scene differs from the copy this clip was rendered from" in r["moved"], r["moved"]
    # the user's scene is untouched: the render happened in the worker
    assert r["engine"] == r["engine_before"] and r["aovs"] == 0 and r["nodes"] == 2 and r["res_x"] == 1920
    assert r["pass_index"] == [0, 0, 0]
    from gbuffer_export import open_clip
    from gbuffer_export.validate import validate_clip
    rep = validate_clip(out)
    assert rep.ok, rep.summary_line()
    clip = open_clip(out)
    assert clip.frames == [1, 2] and clip.scale == 4
    assert clip.sizes == {"hr": (64, 36), "lr": (16, 9)}
    m = clip.manifest
    assert m["render"]["hr"]["spp"] == 4 and m["render"]["lr"]["spp"] == 2 and m["render"]["gbuffer"]["spp"] == 1
    assert m["scene"]["file"] == "untitled.blend"
    assert "OK" in r["last"] and str(out) in r["last"]
    # the summary's counts and size bound describe what was written
    exrs = list(out.glob("*/*/*.exr"))
    from gbuffer_export.conventions import BUFFERS, DEFAULT_BUFFERS
    nch = sum(len(BUFFERS[b].channels) for b in DEFAULT_BUFFERS)
    assert len(exrs) == len(m["buffers"]) * 2 * 2 == len(DEFAULT_BUFFERS) * 4
    payload = nch * 4 * (64 * 36 + 16 * 9) * 2
    assert sum(p.stat().st_size for p in exrs) < payload + len(exrs) * 2000  # ZIP data + per-file header


@pytest.mark.torch
def test_preview_upscale_operator(tmp_path):
    r = run_bpy(r'''
        import numpy as np
        from blender_addon import images
        sc = tiny_scene()
        blender_addon.register()
        s = tiny_settings(sc, sys.argv[1])
        sc.frame_set(2)
        area = bpy.context.window_manager.windows[0].screen.areas[0]
        area.type = "IMAGE_EDITOR"  # an open Image Editor shows the SR image
        out = {}
        for ref in (False, True):
            s.with_reference = ref
            res = bpy.ops.blendsr.preview_upscale()
            imgs = {n: list(bpy.data.images[n].size) for n in
                    (images.SR_IMAGE, images.BILINEAR_IMAGE, images.REFERENCE_IMAGE) if n in bpy.data.images}
            out[str(ref)] = {"res": sorted(res), "imgs": imgs, "ms": s.preview_ms, "psnr": s.preview_psnr,
                             "metric": s.preview_metric, "info": s.preview_info, "clip": s.preview_clip,
                             "float": [bpy.data.images[n].is_float for n in imgs]}
        d = sys.argv[2]
        for key, n in (("sr", images.SR_IMAGE), ("bilinear", images.BILINEAR_IMAGE),
                       ("reference", images.REFERENCE_IMAGE)):
            np.save(f"{d}/{key}.npy", images.image_array(bpy.data.images[n]))
        import shutil
        shutil.copytree(s.preview_clip, f"{d}/preview_clip")  # Blender's session temp folder goes at exit
        out["editor"] = getattr(area.spaces.active.image, "name", None)
        emit(out)
    ''', tmp_path / "unused", tmp_path)
    no_ref, ref = r["False"], r["True"]
    assert r["editor"] == "BlendSR SR"
    for case in (no_ref, ref):
        assert case["res"] == ["FINISHED"]
        assert case["imgs"]["BlendSR SR"] == [64, 36] and case["imgs"]["BlendSR bilinear"] == [64, 36]
        assert all(case["float"]) and case["ms"] > 0 and "frame 2" in case["info"]
    assert "BlendSR reference" not in no_ref["imgs"] and no_ref["psnr"] == 0 and no_ref["metric"] == ""
    assert ref["imgs"]["BlendSR reference"] == [64, 36]
    assert "psnr_tm" in ref["metric"]

    # The images are the clip's data with rows in the right order, and the PSNR is the evaluation's.
    from gbuffer_export import open_clip
    from gbuffer_export.preview import tonemap
    assert ref["clip"].endswith("clip")
    clip = open_clip(tmp_path / "preview_clip")
    assert clip.frames == [2] and clip.manifest["frames"] == [1, 2]  # frame 2 of the export's range only
    assert clip.manifest["shard"] == [1, 1]  # only_frames, not a shard: the same render of the range resumes it
    assert {"motion_next", "metallic", "fbeta"} <= set(clip.manifest["buffers"])  # every buffer: any model runs
    sr, bil, gt = (np.load(tmp_path / f"{k}.npy") for k in ("sr", "bilinear", "reference"))
    np.testing.assert_array_equal(gt, clip.read(2, "hr/radiance"))
    lr = clip.read(2, "lr/radiance")
    # independent bilinear x4 with half-pixel centres, the LR samples at their jittered positions, clamped at the
    # borders
    jx, jy = clip.camera(2, "lr")["jitter"]
    assert (jx, jy) != (0.0, 0.0)
    ys = np.clip((np.arange(36) + 0.5) / 4 - 0.5 - jy, 0, 8)
    xs = np.clip((np.arange(64) + 0.5) / 4 - 0.5 - jx, 0, 15)
    y0, x0 = np.floor(ys).astype(int), np.floor(xs).astype(int)
    y1, x1 = np.minimum(y0 + 1, 8), np.minimum(x0 + 1, 15)
    wy, wx = (ys - y0)[:, None, None], (xs - x0)[None, :, None]
    ref_bil = ((1 - wy) * ((1 - wx) * lr[y0][:, x0] + wx * lr[y0][:, x1])
               + wy * ((1 - wx) * lr[y1][:, x0] + wx * lr[y1][:, x1]))
    np.testing.assert_allclose(bil, ref_bil, rtol=1e-5, atol=1e-6)
    mse = np.mean((tonemap(sr) - tonemap(gt)) ** 2)
    assert ref["psnr"] == pytest.approx(10 * math.log10(1 / mse), abs=0.01)
    assert 10 < ref["psnr"] < 60
    assert not np.allclose(sr, bil)  # demod-bilinear uses the HR G-buffers


def test_modal_progress_status_bar_and_escape(tmp_path):
    """The application's modal path, driven by hand (the bpy module has no event loop): TIMER events update the
    status bar from the clip's frame records until the worker ends; Esc kills the worker and a rerun resumes."""
    r = run_bpy(r'''
        import time
        from blender_addon import operators
        sc = tiny_scene()
        blender_addon.register()
        s = tiny_settings(sc, sys.argv[1])
        batch = operators.interactive
        operators.interactive = lambda: True
        Event = type("Event", (), {})
        def event(kind, value="NOTHING"):
            e = Event(); e.type, e.value = kind, value
            return e
        status, removed, reports = [], [], []
        class WM:
            windows = []
            def event_timer_remove(self, t): removed.append(t)
        class WS:
            def status_text_set(self, text): status.append(text)
        class Ctx:
            scene, preferences, window_manager, workspace, window = sc, bpy.context.preferences, WM(), WS(), None
        class Op(operators._JobOperator):
            job_key, label = "export", "export"
            start = operators.BLENDSR_OT_export_dataset.start
            finish = operators.BLENDSR_OT_export_dataset.finish
            def report(self, kind, msg): reports.append([sorted(kind), msg])
        ctx = Ctx()
        # Esc right away: the worker is killed, nothing is left running
        op = Op(); op._timer = "t1"
        job = op._start(ctx)
        esc = sorted(op.modal(ctx, event("ESC", "PRESS")))
        killed = job.proc.poll() is not None and "export" not in operators.ACTIVE
        # a full run through TIMER events
        op = Op(); op._timer = "t2"
        job = op._start(ctx)
        seen, res = [], None
        while res is None:
            out = op.modal(ctx, event("TIMER"))
            if out != {"PASS_THROUGH"}:
                res = sorted(out)
            seen.append(job.frames_done())
            time.sleep(0.1)
        active = list(operators.ACTIVE)
        # without a UI (bpy as a module, blender --background) INVOKE runs synchronously: here on the finished clip
        operators.interactive = batch
        invoke_res = sorted(bpy.ops.blendsr.export_dataset("INVOKE_DEFAULT"))
        emit({"invoke": invoke_res, "esc": esc, "killed": killed, "res": res, "status": status,
              "removed": removed, "reports": reports, "seen_max": max(seen), "active": active})
    ''', tmp_path / "clip")
    assert r["invoke"] == ["FINISHED"]
    assert r["esc"] == ["CANCELLED"] and r["killed"]
    assert r["reports"][0][0] == ["WARNING"] and "cancelled" in r["reports"][0][1] and "resume" in r["reports"][0][1]
    assert r["res"] == ["FINISHED"] and r["active"] == []
    assert r["removed"] == ["t1", "t2"]
    progress = [t for t in r["status"] if t and "frames" in t]
    assert progress and all("/2 frames" in t and "Esc cancels" in t for t in progress), r["status"]
    assert r["status"][-1] is None  # cleared at the end
    assert r["reports"][-1][0] == ["INFO"] and "OK" in r["reports"][-1][1]
    from gbuffer_export.validate import validate_clip
    assert validate_clip(tmp_path / "clip").ok


# ------------------------------------------------------------------------------------------------------------
# Create camera paths (level walk/fly paths as editable cameras)
# ------------------------------------------------------------------------------------------------------------

def test_create_camera_paths_on_garage_keeps_eyes_clear():
    from tests.conftest import shared_or_skip
    blend = shared_or_skip("scenes/levels/garage/garage.blend")
    r = run_bpy(r'''
        import numpy as np
        bpy.ops.wm.open_mainfile(filepath=sys.argv[1])
        blender_addon.register()
        sc = bpy.context.scene
        sc.frame_start, sc.frame_end = 1, 3
        res = bpy.ops.blendsr.create_camera_paths(kinds={"walk", "fly"}, clips=2, seed=0)
        from gbuffer_export.blender.level_geometry import from_scene
        geom = from_scene(sc, 1)
        out = {"res": list(res), "cams": {}}
        for name in ("BlendSR walk 00", "BlendSR fly 01"):
            cam = bpy.data.objects[name]
            eyes = []
            for f in range(0, 4):
                sc.frame_set(f)
                eyes.append(list(cam.matrix_world.translation))
            d = geom.nearest_distance(np.asarray(eyes))
            out["cams"][name] = {"animated": bool(cam.animation_data and cam.animation_data.action),
                                 "moves": float(np.linalg.norm(np.asarray(eyes[-1]) - eyes[0])),
                                 "min_clear_m": float(d.min()) / geom.units(1.0)}
        emit(out)
    ''', blend)
    assert r["res"] == ["FINISHED"]
    for name, c in r["cams"].items():
        assert c["animated"] and c["moves"] > 0, (name, c)
        assert c["min_clear_m"] >= 0.2, (name, c)
