"""The add-on's Dataset subpanel: ``Scene.blendsr.dataset`` defaults against the spec's and the CLI's, the mapping
to a dataset spec that round-trips through spec.toml, one-line errors, the subpanel drawn, a dataset job's
progress and errors, and ``blendsr.render_dataset`` rendering two clips (walk + fly) of the open garage level that
validate, resume, and refuse a changed scene. Clips of the last test also run through a stand-in for the Blender
application (``RunOptions.blender``)."""
from __future__ import annotations

import json
import sys
import textwrap
from pathlib import Path

import pytest

from tests.conftest import REPO, requires_bpy, run_cli, shared_or_skip
from tests.addon.test_blender import DRAW, run_bpy

GARAGE = "scenes/levels/garage/garage.blend"

TINY = r'''
def tiny_dataset(out):
    ds = bpy.context.scene.blendsr.dataset
    ds.output_dir = out
    ds.clips, ds.frames, ds.cameras = 2, 2, {"walk", "fly"}
    ds.hr_width, ds.hr_height = 64, 36
    ds.hr_spp, ds.lr_spp, ds.gbuffer_spp, ds.hr_denoise = 1, 1, 1, True  # denoised: 1 spp leaves dark noise
    ds.threads = 1
    ds.vary_lights = True  # the garage has two lamps: each clip multiplies their energy by a drawn factor
    return ds
'''


@requires_bpy
@pytest.mark.bpy
def test_dataset_defaults_mapping_errors_and_subpanel(tmp_path):
    r = run_bpy(r'''
        sc = tiny_scene()
        blender_addon.register()
        from blender_addon import mapping, panels
        from gbuffer_export.dataset.writer import spec_to_toml
        ds = sc.blendsr.dataset
        rna = ds.bl_rna.properties
        defaults = {p.identifier: sorted(p.default_flag) if getattr(p, "is_enum_flag", False) else p.default
                    for p in rna if p.identifier not in ("rna_type", "name") and not p.is_readonly}
        spec_path = sys.argv[1] + "/spec.toml"
        default_toml = spec_to_toml(mapping.dataset_spec(ds, "lvl", spec_path))
        default_opts = mapping.run_options_json(mapping.dataset_run_options(ds))
        ds.scales, ds.for_models, ds.regions_x, ds.regions_y, ds.region_val, ds.region_test = {"2", "4"}, {"nsrr"}, 3, 3, 1, 1
        ds.dataset_name = "mine"
        ds.for_formats = {"nss", "rdg"}
        ds.vary_sun, ds.sun_elevation_min, ds.sun_elevation_max = True, 25.0, 60.0
        ds.vary_world, ds.world_strength_min, ds.world_strength_max = True, 0.7, 1.3
        custom_doc = mapping.dataset_spec_dict(ds, "lvl")
        custom_toml = spec_to_toml(mapping.dataset_spec(ds, "lvl", spec_path))
        custom_opts = mapping.run_options_json(mapping.dataset_run_options(ds, blender="/opt/blender"))
        errors = {}
        for key, value in (("scales", set()), ("cameras", set()),
                           ("hr_width", 66), ("region_val", 9), ("world_strength_max", 0.5)):
            old = getattr(ds, key)
            setattr(ds, key, value)
            try:
                mapping.dataset_spec(ds, "lvl", spec_path)
                mapping.dataset_run_options(ds)
                errors[f"{key}={value}"] = ""
            except ValueError as exc:
                errors[f"{key}={value}"] = str(exc)
            setattr(ds, key, old)
        ds.buffers = "custom"  # its checkboxes are drawn
        draws = {cls.__name__: draw_tree(cls) for cls in panels.DATASET_PANELS}
        emit({"defaults": defaults, "default_toml": default_toml, "default_opts": default_opts,
              "custom_doc": custom_doc, "custom_toml": custom_toml, "custom_opts": custom_opts, "errors": errors,
              "draws": draws, "parents": {c.__name__: getattr(c, "bl_parent_id", "") for c in panels.CLASSES}})
    ''', tmp_path, helpers=DRAW)
    import tomllib
    from gbuffer_export.dataset.build import RunOptions
    from gbuffer_export.dataset.spec import RenderSettings, parse_spec
    d, spec_path = r["defaults"], tmp_path / "spec.toml"

    # Defaults: the spec's [render] and scene-source defaults, and blendsr dataset's run options.
    default = parse_spec(tomllib.loads(r["default_toml"]), spec_path)
    plain = parse_spec({"dataset": {"name": "lvl"}, "source": [
        {"name": "scene", "kind": "scene", "paths": ["scene/lvl.blend"]}]}, spec_path)
    assert default == plain and default.sources[0].render == RenderSettings()
    assert (d["frames"], d["hr_width"], d["hr_height"], d["scales"]) == (12, 256, 144, ["4"])
    assert d["cameras"] == ["fly", "walk"] and d["for_models"] == [] and d["buffers"] == "default"
    assert d["for_formats"] == [] and default.for_formats == ()
    opts = RunOptions(**r["default_opts"])
    assert opts == RunOptions(progress=False)
    assert d["output_dir"] == "//blendsr_dataset/" and d["light"] == "auto" and d["device"] == "auto"

    # Several scales: every clip with an LR level per scale; the settings round-trip through spec.toml.
    custom = parse_spec(tomllib.loads(r["custom_toml"]), spec_path)
    assert custom == parse_spec(r["custom_doc"], spec_path)
    assert [(s.name, s.render.scale, s.render.scales) for s in custom.sources] == [("scene", 2, (2.0, 4.0))]
    assert custom.name == "mine" and all(s.regions == (3, 3) and s.region_val == s.region_test == 1
                                         for s in custom.sources)
    assert all(s.paths == ("scene/lvl.blend",) and s.cameras == ("walk", "fly") for s in custom.sources)
    assert all(s.variation.sun_elevation_deg == (25.0, 60.0) and s.variation.world_strength == (0.7, 1.3)
               and s.variation.light_strength is None for s in custom.sources)
    assert r["custom_doc"]["source"][0]["world_strength"] == [0.7, 1.3]  # float32 settings as their decimals
    assert r["custom_opts"]["buffers_for"] == ["nsrr"] and r["custom_opts"]["blender"] == "/opt/blender"
    # For models is written into the spec as the buffers those models read: the spec alone renders the same clips.
    from gbuffer_export.dataset.buffers import buffers_for_models
    assert r["custom_doc"]["render"]["buffers"] == list(buffers_for_models(["nsrr"]))
    # For formats is the spec's [dataset] for_formats: the spec adds what they need (RDG's buffers) to every clip.
    assert r["custom_doc"]["dataset"]["for_formats"] == ["nss", "rdg"] and custom.for_formats == ("nss", "rdg")
    assert all(set(s.render.buffers) == set(buffers_for_models(["nsrr"])) | {"normal", "fbeta", "depth"}
               for s in custom.sources)

    # Bad settings: one line naming the setting or the spec key.
    e = r["errors"]
    assert "dataset Scales" in e["scales=set()"] and "tick at least one scale" in e["scales=set()"]
    assert "dataset Cameras: tick at least one camera path" in e["cameras=set()"]
    assert "not divisible by scale" in e["hr_width=66"] and "region_val" in e["region_val=9"]
    assert "world_strength" in e["world_strength_max=0.5"] and "low <= high" in e["world_strength_max=0.5"]
    assert all("\n" not in v and v for v in e.values()), e

    # The Dataset subpanels: under each BlendSR panel, every setting drawn, the button, the summary.
    assert r["parents"]["BLENDSR_PT_output_dataset"] == "BLENDSR_PT_output"
    assert r["parents"]["BLENDSR_PT_view3d_dataset"] == "BLENDSR_PT_view3d"
    for name, log in r["draws"].items():
        props = {e[1] for e in log if e[0] == "prop"}
        assert all(e[2] for e in log if e[0] == "prop"), log
        settable = {k for k in d if k != "last_dataset_ok"}
        assert props == settable, (name, settable ^ props)
        assert [e[1:] for e in log if e[0] == "operator"] == [["blendsr.render_dataset", True],
                                                              ["blendsr.open_output", True],
                                                              ["blendsr.contact_sheet", True]]
        subs = [e for e in log if e[0] == "panel"]  # collapsible subpanels under the Dataset subpanel
        assert len(subs) == 5 and all(e[2] == subs[0][1] for e in subs[1:]), subs
        labels = [e[1] for e in log if e[0] == "label"]
        assert "4 clips x 12 frames, HR 256x144, scales 2, 4" in labels, labels
        assert "cameras walk, fly (clip k: kind k), light auto" in labels
        assert "For formats (what each export needs is added)" in labels
        assert any("relative to the .blend file: save the file first" in t for t in labels)  # unsaved file


def test_dataset_job_progress_and_worker_error(tmp_path):
    """Progress counts every clip's frame records; a worker that cannot build the dataset reports one line."""
    from blender_addon import jobs
    out = tmp_path / "ds"
    for cid, n in (("a", 2), ("b", 1)):
        (out / "clips" / cid / "frames").mkdir(parents=True)
        for f in range(1, n + 1):
            (out / "clips" / cid / "frames" / f"{f:06d}.json").write_text("{}")
    payload = {"spec": str(tmp_path / "missing.toml"), "output": str(out), "options": {}}
    job = jobs.DatasetJob(payload, {"a": 2, "b": 2, "c": 3}, job_dir=tmp_path / "job",
                          library_paths={"site_dirs": [], "sys_path": [str(REPO)]}, python=sys.executable)
    assert job.done_at_start == 3 and job.clip_frames() == {"a": 2, "b": 1, "c": 0}
    assert job.status_line().startswith("1/3 clips, 3/7 frames")
    assert json.loads(job.job_file.read_text())["dataset"] == payload
    res = job.result()
    assert not res.ok and res.returncode == 2 and "missing.toml: dataset spec not found" in res.error


def _fake_blender(tmp_path: Path) -> Path:
    """Stands in for the Blender application: drops Blender's options and runs the --python script with this
    Python, without $PYTHONPATH (Blender ignores it), the arguments after it kept as Blender passes them."""
    exe = tmp_path / "blender"
    exe.write_text(textwrap.dedent(f'''\
        #!/bin/sh
        [ "$1" = "--background" ] || exit 9
        echo "$@" >> {tmp_path / "blender_calls.txt"}
        while [ "$1" != "--python" ]; do shift; done
        script=$2; shift 2
        exec env -u PYTHONPATH {sys.executable} "$script" "$@"
        '''))
    exe.chmod(0o755)
    return exe


@pytest.mark.heavy
@requires_bpy
@pytest.mark.bpy
@pytest.mark.shared
def test_render_dataset_on_the_open_garage_validates_resumes_and_refuses_a_changed_scene(tmp_path):
    garage = shared_or_skip(GARAGE)
    out = tmp_path / "ds"
    r = run_bpy(r'''
        import time
        bpy.ops.wm.open_mainfile(filepath=sys.argv[1])
        blender_addon.register()
        sc = bpy.context.scene
        before = [sc.render.engine, sc.render.resolution_x, len(bpy.context.view_layer.aovs), bpy.data.filepath]
        ds = tiny_dataset(sys.argv[2])
        res = sorted(bpy.ops.blendsr.render_dataset())
        after = [sc.render.engine, sc.render.resolution_x, len(bpy.context.view_layer.aovs), bpy.data.filepath]
        first = [ds.last_dataset, ds.last_dataset_ok]
        # the dataset's contact sheet (gbuffer_export.preview.dataset_sheet) as an image: a row per clip
        sheet = sorted(bpy.ops.blendsr.contact_sheet(target="dataset"))
        first.append([sheet, list(bpy.data.images["BlendSR contact sheet"].size)])
        # the same scene opened again: the run resumes (nothing left to render)
        bpy.ops.wm.open_mainfile(filepath=sys.argv[1])
        ds = tiny_dataset(sys.argv[2])
        t = time.monotonic()
        again = sorted(bpy.ops.blendsr.render_dataset())
        again_s = time.monotonic() - t
        # a moved object: refused, the dataset untouched
        bpy.data.objects[sorted(o.name for o in bpy.context.scene.objects if o.type == "MESH")[0]].location.x += 1
        try:
            bpy.ops.blendsr.render_dataset()
            changed = ""
        except RuntimeError as exc:
            changed = str(exc)
        again_text = ds.last_dataset
        # a clip that fails (no camera of that name): the run reports it, the subpanel says failed
        ds.output_dir, ds.device, ds.clips = sys.argv[2] + "_bad", "metal", 1  # no Metal device on Linux
        try:
            bpy.ops.blendsr.render_dataset()
            failed = ""
        except RuntimeError as exc:
            failed = str(exc)
        emit({"res": res, "first": first, "before": before, "after": after, "again": again, "again_s": again_s,
              "again_text": again_text, "changed": changed, "failed": failed,
              "failed_panel": [ds.last_dataset, ds.last_dataset_ok]})
    ''', garage, out, helpers=TINY, timeout=300)
    assert r["res"] == ["FINISHED"] and r["first"][1] is True, r
    assert r["first"][2][0] == ["FINISHED"] and r["first"][2][1][1] > 2 * 36, r["first"]  # two clips' rows
    assert r["first"][0].startswith(f"OK: {out}: 2/2 clips valid"), r["first"]
    assert r["before"] == r["after"], "the open scene is untouched: clips render in worker processes"
    from gbuffer_export.dataset.check import validate_dataset
    from gbuffer_export.dataset.spec import load_spec
    rep = validate_dataset(out, progress=False)
    assert rep.ok, rep.lines()
    index = json.loads((out / "dataset.json").read_text())
    assert [(c["camera"], c["state"], c["frames_done"]) for c in index["clips"]] == [("walk", "done", 2),
                                                                                    ("fly", "done", 2)]
    for c in index["clips"]:
        m = json.loads((out / c["path"] / "manifest.json").read_text())
        assert m["camera"]["kind"] == c["camera"] and m["scene"]["file"] == "garage.blend"
        k = c["variation"]["light_strength"]
        assert 0.5 <= k <= 2.0 and m["light"]["variation"]["light_strength"] == {"multiplier": k, "lamps": 2}
        assert m["render"]["hr"]["spp"] == 1 and (m["levels"]["hr"]["width"], m["levels"]["hr"]["height"]) == (64, 36)
    spec = load_spec(out / "spec.toml")
    assert spec.sources[0].paths == ("scene/garage.blend",) and (out / "scene" / "garage.blend").is_file()
    assert index["spec"]["text"] == (out / "spec.toml").read_text()
    assert r["again"] == ["FINISHED"] and "2 done" in r["again_text"] and r["again_s"] < 30
    assert "differs from the copy this dataset's clips were rendered from" in r["changed"]
    assert "1 of 1 clips not done; scene-garage-00:" in r["failed"] and "METAL" in r["failed"], r["failed"]
    assert r["failed_panel"][0].startswith("failed: 1 of 1 clips not done") and r["failed_panel"][1] is False
    assert "FAILED" in r["failed_panel"][0]  # the validation's verdict too
    # The written spec re-runs the same dataset from the command line: nothing left to render.
    cli = run_cli("dataset", out / "spec.toml", "-o", out, "--no-progress")
    assert cli.returncode == 0 and "2 done, 0 to render" in cli.stderr, cli.stderr[-2000:]

    # The same clips rendered by "Blender" (a stand-in): the executor runs dataset_job_script.py in it.
    from gbuffer_export.dataset.build import RunOptions, build_dataset
    spec_b = load_spec(out / "spec.toml")
    index_b = build_dataset(spec_b, out, RunOptions(blender=str(_fake_blender(tmp_path)), threads=1, progress=False,
                                                    limit=0))
    assert index_b["last_run"]["clips_rendered"] == 0
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / "scene").mkdir()
    (fresh / "scene" / "garage.blend").write_bytes((out / "scene" / "garage.blend").read_bytes())
    text = (out / "spec.toml").read_text().replace("clips_per_scene = 2", "clips_per_scene = 1")
    (fresh / "spec.toml").write_text(text)
    index_f = build_dataset(load_spec(fresh / "spec.toml"), fresh,
                            RunOptions(blender=str(_fake_blender(tmp_path)), threads=1, progress=False))
    assert [c["state"] for c in index_f["clips"]] == ["done"], list((fresh / "logs").iterdir())
    calls = (tmp_path / "blender_calls.txt").read_text().splitlines()
    assert len(calls) == 1 and "--factory-startup" in calls[0] and "dataset_job_script.py -- " in calls[0]
    assert validate_dataset(fresh, progress=False).ok


@requires_bpy
@pytest.mark.bpy
def test_render_dataset_modal_progress_on_an_unsaved_scene(tmp_path):
    """The application's modal path, driven by hand: TIMER events show clips and frames in the status bar until the
    worker ends; an unsaved scene (built in code, its own camera: ``scene``) is copied as scene/untitled.blend."""
    out = tmp_path / "ds"
    r = run_bpy(r'''
        import time
        from blender_addon import dataset_ops, operators
        sc = tiny_scene()
        blender_addon.register()
        ds = tiny_dataset(sys.argv[1])
        ds.cameras, ds.vary_lights = {"scene"}, False
        operators.interactive = lambda: True
        Event = type("Event", (), {})
        def event(kind, value="NOTHING"):
            e = Event(); e.type, e.value = kind, value
            return e
        status, reports = [], []
        class WM:
            windows = []
            def event_timer_remove(self, t): pass
        class WS:
            def status_text_set(self, text): status.append(text)
        class Ctx:
            scene, preferences, window_manager, workspace, window = sc, bpy.context.preferences, WM(), WS(), None
        class Op(operators._JobOperator):
            job_key, label = "dataset", "dataset"
            start = dataset_ops.BLENDSR_OT_render_dataset.start
            finish = dataset_ops.BLENDSR_OT_render_dataset.finish
            def report(self, kind, msg): reports.append([sorted(kind), msg])
        op, ctx = Op(), Ctx()
        op._timer = "t"
        job = op._start(ctx)
        res = None
        while res is None:
            out = op.modal(ctx, event("TIMER"))
            if out != {"PASS_THROUGH"}:
                res = sorted(out)
            time.sleep(0.1)
        emit({"res": res, "status": status, "reports": reports, "last": ds.last_dataset, "ok": ds.last_dataset_ok})
    ''', out, helpers=TINY)
    assert r["res"] == ["FINISHED"] and r["ok"], r
    progress = [t for t in r["status"] if t]
    assert progress and all("/2 clips, " in t and "/4 frames" in t and "Esc cancels" in t for t in progress), progress
    assert r["status"][-1] is None and r["reports"][-1][0] == ["INFO"] and "OK" in r["reports"][-1][1]
    assert (out / "scene" / "untitled.blend").is_file()
    index = json.loads((out / "dataset.json").read_text())
    assert index["name"] == "untitled" and [c["camera"] for c in index["clips"]] == ["scene", "scene"]
