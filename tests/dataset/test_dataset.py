"""Datasets: the spec (pure), the index and splits, a tiny dataset rendered by local workers and by a local
2-node Ray cluster, resume after kill -9, ``validate DATASET``, ``--for-models`` and ``train --data DATASET``."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ENV, REPO, assert_same_render, requires_bpy, run_cli
from gbuffer_export.dataset.build import read_index, split_clips
from gbuffer_export.dataset.buffers import MODEL_BUFFERS, buffers_for_models
from gbuffer_export.dataset.spec import SpecError, assign_split, expand, load_spec, parse_spec, Splits, stable_hash
from gbuffer_export.exr import read_exr_channels


def make_assets(folder: Path) -> Path:
    """Two tiny GLB assets made with trimesh (a box and a sphere), each with a Khronos-style metadata.json."""
    import trimesh
    for name, mesh, lic in (("Box", trimesh.creation.box((1.0, 0.6, 0.4)), "CC0-1.0"),
                            ("Ball", trimesh.creation.icosphere(2, 0.4), "CC-BY-4.0")):
        d = folder / name / "glTF-Binary"
        d.mkdir(parents=True, exist_ok=True)
        mesh.export(d / f"{name}.glb")
        (folder / name / "metadata.json").write_text(json.dumps(
            {"legal": [{"spdx": lic, "artist": f"{name} maker", "year": "2026", "what": "Everything"}]}))
    return folder


def write_spec(path: Path, assets: Path, extra: str = "", name: str = "tiny") -> Path:
    path.write_text(f"""
[dataset]
name = "{name}"
seed = 3
[render]
frames = 2
hr_size = "64x32"
scale = 4
hr_spp = 2
lr_spp = 2
gbuffer_spp = 1
hr_denoise = false
[splits]
test = ["Ball"]
[[source]]
name = "builtin"
kind = "builtin"
seeds = "0:0"
cameras = ["scene"]
hdri = ["builtin:courtyard"]
[[source]]
name = "objs"
kind = "assets"
paths = ["{assets}"]
clips_per_asset = 1
clutter = 1
cameras = ["orbit"]
hdri = ["builtin:studio", "builtin:forest"]
{extra}
""")
    return path


# ----------------------------------------------------------------------------------------------
# The spec (pure)
# ----------------------------------------------------------------------------------------------

def test_spec_expands_deterministically_with_splits_by_asset(tmp_path):
    assets = make_assets(tmp_path / "assets")
    spec_path = write_spec(tmp_path / "s.toml", assets)
    a, b = expand(load_spec(spec_path)), expand(load_spec(spec_path))
    assert [j.to_json() for j in a] == [j.to_json() for j in b]
    by_id = {j.id: j for j in a}
    assert set(by_id) == {"builtin-s0000", "objs-Ball-00", "objs-Box-00"}
    assert by_id["objs-Ball-00"].split == "test" and by_id["objs-Box-00"].split == "train"
    # clutter only from the same split: the lone training asset has nobody to borrow, the test asset neither
    assert by_id["objs-Box-00"].clutter == [] and by_id["objs-Ball-00"].clutter == []
    assert by_id["objs-Box-00"].licence["licence"] == "CC0-1.0"
    assert by_id["objs-Ball-00"].licence["licence"] == "CC-BY-4.0"
    assert by_id["builtin-s0000"].seed == 0
    # another dataset seed draws other per-clip seeds
    other = expand(parse_spec({**__import__("tomllib").loads(spec_path.read_text()), "dataset": {"name": "t",
                                                                                                   "seed": 4}},
                              spec_path))
    assert {j.id: j.seed for j in other}["objs-Box-00"] != by_id["objs-Box-00"].seed


def test_spec_rejects_unknown_keys_and_bad_values(tmp_path):
    assets = make_assets(tmp_path / "assets")
    with pytest.raises(SpecError, match=r"unknown key render.frmaes \(known: frames"):
        parse_spec({"render": {"frmaes": 3}, "source": [{"kind": "builtin", "seeds": 0}]}, "x.toml")
    with pytest.raises(SpecError, match=r"source\[0\]\.kind 'nope': choose one of builtin, assets, scene"):
        parse_spec({"source": [{"kind": "nope"}]}, "x.toml")
    with pytest.raises(SpecError, match="not divisible by scale"):
        parse_spec({"render": {"hr_size": "65x32"}, "source": [{"kind": "builtin", "seeds": 0}]}, "x.toml")
    with pytest.raises(SpecError, match="render.hr_spp: expected an integer"):
        parse_spec({"render": {"hr_spp": "many"}, "source": [{"kind": "builtin", "seeds": 0}]}, "x.toml")
    with pytest.raises(SpecError, match="no such file or folder"):
        expand(parse_spec({"source": [{"kind": "assets", "paths": [str(tmp_path / "none")]}]}, "x.toml"))
    with pytest.raises(SpecError, match="both val and test"):
        parse_spec({"splits": {"val": ["Box"], "test": ["Box"]}, "source": [{"kind": "builtin", "seeds": 0}]}, "x")
    proc = run_cli("dataset", write_spec(tmp_path / "bad.toml", assets, extra="colour = 1"), "-o", tmp_path / "o")
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "unknown key source[1].colour" in proc.stderr


def test_builtin_props_are_opt_in_per_source_and_recorded(tmp_path):
    """``props`` adds a prop to every clip of a builtin source; a source without it expands to the clips it gave
    before the key existed (``props`` None: older indexes compare equal); other kinds and unknown props refused."""
    doc = {"source": [{"name": "plain", "kind": "builtin", "seeds": "0:1"},
                      {"name": "pane", "kind": "builtin", "seeds": "0:1", "props": ["broken_pane"]}]}
    jobs = {j.id: j for j in expand(parse_spec(doc, tmp_path / "s.toml"))}
    assert jobs["plain-s0000"].props is None
    assert jobs["pane-s0001"].props == ["broken_pane"] and jobs["pane-s0001"].seed == 1
    with pytest.raises(SpecError, match=r"source\[0\]\.props.*'glass'.*broken_pane"):
        parse_spec({"source": [{"kind": "builtin", "seeds": 0, "props": ["glass"]}]}, "x.toml")
    with pytest.raises(SpecError, match="seeds, sun and props are for kind = \"builtin\""):
        parse_spec({"source": [{"kind": "assets", "paths": ["a"], "props": ["broken_pane"]}]}, "x.toml")
    with pytest.raises(SpecError, match=r"source\[0\]\.props .*an item is repeated"):
        parse_spec({"source": [{"kind": "builtin", "seeds": 0, "props": ["broken_pane", "broken_pane"]}]}, "x.toml")


def test_hash_split_rule_is_stable_and_near_its_fractions():
    splits = Splits(test_fraction=0.2, val_fraction=0.1)
    got = [assign_split(f"asset{i}", splits, None, 0) for i in range(2000)]
    assert got == [assign_split(f"asset{i}", splits, None, 0) for i in range(2000)]
    assert abs(got.count("test") / 2000 - 0.2) < 0.03 and abs(got.count("val") / 2000 - 0.1) < 0.03
    assert stable_hash("a", 1) == stable_hash("a", 1) != stable_hash("a", 2)
    assert assign_split("x", Splits(test=("x",)), None, 0) == "test"
    assert assign_split("y", Splits(test=("x",)), "train", 0) == "train"  # a source may force its split
    assert assign_split("x", Splits(test=("x",)), "test", 0) == "test"
    with pytest.raises(SpecError, match="listed under \\[splits\\] test"):  # but never a test asset into train
        assign_split("x", Splits(test=("x",)), "train", 0)


def test_for_models_buffers():
    assert buffers_for_models(["bicubic"]) == ("radiance", "motion")
    assert set(buffers_for_models(["fusesr-l"])) == {"radiance", "albedo", "normal", "depth", "emission", "fbeta",
                                                     "motion", "flags"}
    with pytest.raises(ValueError, match="unknown model 'nope'"):
        buffers_for_models(["nope"])


@pytest.mark.torch
def test_model_buffer_table_is_derived_from_every_models_needs():
    pytest.importorskip("torch")
    from training.models import MODELS
    from training.commands.buffer_table import model_buffer_table
    table = model_buffer_table()
    assert list(table) == list(MODELS)
    assert {k: tuple(v) for k, v in table.items()} == MODEL_BUFFERS, (
        "gbuffer_export/dataset/model_buffers.json is stale: run make generate")


def assert_same_geometry(a: Path, b: Path, frame: int) -> None:
    """Depth bit-identical, normals and motion within 1e-6 (float32 rounding of Cycles' averaged passes)."""
    for key, tol in (("hr/depth", 0.0), ("lr/depth", 0.0), ("hr/normal", 1e-6), ("hr/motion", 1e-5)):
        x = read_exr_channels(a / key / f"{frame:06d}.exr")
        y = read_exr_channels(b / key / f"{frame:06d}.exr")
        for k in x:
            both_inf = np.isinf(x[k]) & np.isinf(y[k]) & (np.sign(x[k]) == np.sign(y[k]))
            diff = np.abs(np.where(both_inf, 0.0, x[k]) - np.where(both_inf, 0.0, y[k]))
            assert float(diff.max()) <= tol, (a.name, frame, key, k, float(diff.max()))


# ----------------------------------------------------------------------------------------------
# Rendering datasets (Cycles in subprocesses)
# ----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    assets = make_assets(root / "assets")
    spec = write_spec(root / "tiny.toml", assets)
    out = root / "local"
    proc = run_cli("dataset", spec, "-o", out, "--workers", "2", "--threads", "1", "--no-progress", timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return spec, out


@requires_bpy
@pytest.mark.bpy
def test_dataset_renders_validates_and_indexes(tiny):
    spec, out = tiny
    idx = read_index(out)
    assert [c["state"] for c in idx["clips"]] == ["done"] * 3
    assert idx["splits"] == {"train": ["builtin-s0000", "objs-Box-00"], "val": [], "test": ["objs-Ball-00"]}
    assert [p.name for p in split_clips(out, "test")] == ["objs-Ball-00"]
    box = json.loads((out / "clips" / "objs-Box-00" / "manifest.json").read_text())
    assert box["scene"]["asset"] == "Box.glb" and box["scene"]["licence"]["licence"] == "CC0-1.0"
    assert box["scene"]["camera_min_distance_m"] >= box["scene"]["camera_clearance_m"]
    proc = run_cli("validate", out, "--no-progress")
    assert proc.returncode == 0, proc.stdout + proc.stderr[-2000:]
    assert proc.stdout.strip().splitlines()[-1].startswith("OK:") and "3/3 clips valid" in proc.stdout
    # nothing to do on a rerun
    again = run_cli("dataset", spec, "-o", out, "--no-progress")
    assert again.returncode == 0 and "0 to render" in again.stderr


@requires_bpy
@pytest.mark.bpy
def test_builtin_clip_with_the_broken_pane_renders_alpha_cut_glass(tmp_path):
    """``props = ["broken_pane"]`` end to end: the clip records the prop, its material is flagged alpha and
    transmission, and the HR flags show the pane on the scene camera's frame."""
    from gbuffer_export.conventions import Flag
    spec = tmp_path / "pane.toml"
    spec.write_text("""
[dataset]
name = "pane"
[render]
frames = 1
hr_size = "64x32"
hr_spp = 2
lr_spp = 2
gbuffer_spp = 1
hr_denoise = false
[[source]]
name = "pane"
kind = "builtin"
props = ["broken_pane"]
seeds = "72:72"
cameras = ["scene"]
hdri = ["builtin:courtyard"]
""")
    out = tmp_path / "ds"
    proc = run_cli("dataset", spec, "-o", out, "--threads", "2", "--no-progress", timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    clip = out / "clips" / "pane-s0072"
    man = json.loads((clip / "manifest.json").read_text())
    assert man["scene"]["props"] == ["broken_pane"]
    assert {"alpha", "transmission"} <= set(man["materials"]["Broken Glass"]["features"])
    flags = read_exr_channels(clip / "hr" / "flags" / "000001.exr")["F"].astype(np.int64)
    pane = (flags & int(Flag.ALPHA)) > 0
    assert 0.03 < pane.mean() < 0.5 and ((flags[pane] & int(Flag.TRANSMISSION)) > 0).all()


@requires_bpy
@pytest.mark.bpy
def test_data_scaling_counts_clips_or_scenes_of_the_train_split(tiny, tmp_path):
    """benchmarks/data_scaling.py --by scene: every train clip once, grouped by the index's scene id."""
    import shutil
    sys.path.insert(0, str(REPO / "benchmarks"))
    from data_scaling import training_groups
    _, out = tiny
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    idx = json.loads((copy / "dataset.json").read_text())
    for c in idx["clips"]:
        if c["id"] == "objs-Box-00":
            c["scene_id"] = "builtin:0"  # two train clips of one scene
    (copy / "dataset.json").write_text(json.dumps(idx))
    by_clip = training_groups(copy, "clip")
    assert sorted(k for k, _ in by_clip) == ["builtin-s0000", "objs-Box-00"]
    by_scene = training_groups(copy, "scene")
    assert [(k, sorted(c.name for c in v)) for k, v in by_scene] == [("builtin:0", ["builtin-s0000", "objs-Box-00"])]


@requires_bpy
@pytest.mark.bpy
def test_validate_dataset_reports_a_missing_clip(tiny, tmp_path):
    import shutil
    _, out = tiny
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    shutil.rmtree(copy / "clips" / "objs-Box-00")
    proc = run_cli("validate", copy, "--no-progress")
    assert proc.returncode == 1
    assert "clip objs-Box-00 is pending" in proc.stdout and "FAILED" in proc.stdout


@requires_bpy
@pytest.mark.bpy
def test_dataset_resumes_after_kill_9(tiny, tmp_path):
    """kill -9 to the coordinator after the first frame of the tiny dataset's built-in clip (the spec's first
    source alone: the same clip id and seed, so the same clip), then the rerun finishes a clip that validates with
    the uninterrupted run's geometry. (One clip keeps it cheap: clips not started are what every run renders.)"""
    spec_all, reference = tiny
    spec = tmp_path / "one.toml"
    spec.write_text(spec_all.read_text().split('[[source]]\nname = "objs"')[0])
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "gbuffer_export.cli", "dataset", str(spec), "-o", str(out), "--workers", "1",
           "--threads", "1", "--no-progress"]
    proc = subprocess.Popen(cmd, cwd=REPO, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and not list((out / "clips").glob("*/frames/*.json")):
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)  # the coordinator; its worker dies with it (parent-death signal)
    proc.wait()
    time.sleep(0.5)
    assert len(list((out / "clips").glob("*/frames/*.json"))) == 1
    idx = read_index(out)
    assert [c["id"] for c in idx["clips"]] == ["builtin-s0000"]
    assert any(c["state"] != "done" for c in idx["clips"])
    done = run_cli("dataset", spec, "-o", out, "--no-progress", "--threads", "1", timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert all(c["state"] == "done" for c in read_index(out)["clips"])
    assert run_cli("validate", out, "--no-progress", "--quick").returncode == 0
    # the same clips as the uninterrupted run: the same geometry (depth bit-identical; Cycles' averaged normal
    # and vector passes may differ in the last bit of float32)
    for f in (1, 2):
        assert_same_geometry(out / "clips" / "builtin-s0000", reference / "clips" / "builtin-s0000", f)


@pytest.mark.heavy
@requires_bpy
@pytest.mark.bpy
def test_ray_local_cluster_gives_the_same_clips(tiny, tmp_path, monkeypatch):
    pytest.importorskip("ray")
    spec, reference = tiny
    code = f"""
import os, sys
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"   # loopback addresses only
from ray.cluster_utils import Cluster
cluster = Cluster(initialize_head=True, head_node_args={{"num_cpus": 1, "include_dashboard": False}})
cluster.add_node(num_cpus=1)                              # a second node: 2 workers in all
from gbuffer_export.cli import main
try:
    rc = main(["dataset", {str(spec)!r}, "-o", {str(tmp_path / 'ray')!r}, "--executor", "ray", "--address",
               cluster.address, "--threads", "1", "--no-progress"])
finally:
    cluster.shutdown()
sys.exit(rc)
"""
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=ENV, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    idx = read_index(tmp_path / "ray")
    ref = read_index(reference)
    assert [c["state"] for c in idx["clips"]] == ["done"] * 3
    strip = ("state", "frames_done", "error", "path")
    assert [{k: v for k, v in c.items() if k not in strip} for c in idx["clips"]] == \
        [{k: v for k, v in c.items() if k not in strip} for c in ref["clips"]]
    for clip in ("objs-Box-00", "objs-Ball-00"):
        assert_same_geometry(tmp_path / "ray" / "clips" / clip, reference / "clips" / clip, 2)


@requires_bpy
@pytest.mark.bpy
def test_for_models_renders_only_what_the_models_read(tmp_path):
    assets = make_assets(tmp_path / "assets")
    spec = write_spec(tmp_path / "s.toml", assets, name="formodels")
    text = spec.read_text().replace('seeds = "0:0"', 'seeds = "0:0"\nsplit = "train"')
    spec.write_text(text.split("[[source]]\nname = \"objs\"")[0])
    out = tmp_path / "o"
    proc = run_cli("dataset", spec, "-o", out, "--for-models", "bicubic", "--no-progress", "--threads", "1")
    assert proc.returncode == 0, proc.stderr[-2000:]
    m = json.loads((out / "clips" / "builtin-s0000" / "manifest.json").read_text())
    assert m["buffers"] == ["radiance", "motion"]
    assert read_index(out)["for_models"] == ["bicubic"]
    assert sorted(p.name for p in (out / "clips" / "builtin-s0000" / "hr").iterdir()) == ["motion", "radiance"]


@requires_bpy
@pytest.mark.bpy
@pytest.mark.torch
def test_train_and_evaluate_take_a_dataset(tiny, tmp_path):
    pytest.importorskip("torch")
    _, out = tiny
    run = tmp_path / "run"
    proc = run_cli("train", "--model", "fusesr-l", "--data", out, "-o", run, "--max-steps", "2",
                   "--set", "data.crop=8", "--set", "data.batch_size=2", "--set", "run.threads=1", timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    cfg = (run / "config.toml").read_text()
    assert "builtin-s0000" in cfg and "objs-Box-00" in cfg and "objs-Ball-00" not in cfg  # train split only
    ev = run_cli("evaluate", "--model", "bicubic", "--data", out, "--json", tmp_path / "e.json", "--no-flip",
                 "--threads", "1")
    assert ev.returncode == 0, ev.stderr[-2000:]
    result = json.loads((tmp_path / "e.json").read_text())
    assert [Path(c).name for c in result["clips"]] == ["objs-Ball-00"]  # the test split by default


@requires_bpy
@pytest.mark.bpy
def test_the_same_spec_renders_the_same_clips(tmp_path):
    """One Cycles thread per worker, the worker re-executed without address randomisation: rendering a spec twice
    into the same folder gives the same clips (G-buffers to float rounding, radiance in expectation; bit-identical
    on an idle machine, see docs/clip-format.md, "Reproducibility")."""
    from gbuffer_export import open_clip
    spec = tmp_path / "s.toml"
    spec.write_text('[dataset]\nname = "rep"\n[render]\nframes = 2\nhr_size = "64x32"\nhr_spp = 4\nlr_spp = 2\n'
                    'gbuffer_spp = 1\nhr_denoise = false\n[[source]]\nkind = "builtin"\nseeds = "3:3"\n'
                    'cameras = ["scene"]\nhdri = ["builtin:courtyard"]\n')
    out = tmp_path / "out"
    for run in ("a", "b"):
        proc = run_cli("dataset", spec, "-o", out, "--threads", "1", "--no-progress")
        assert proc.returncode == 0, proc.stderr[-2000:]
        out.rename(tmp_path / run)
    files = sorted((tmp_path / "a" / "clips").rglob("*.exr"))
    assert len(files) == 2 * 2 * 8  # 2 frames, 2 levels, the default buffers
    clips = sorted(p.parent for p in (tmp_path / "a" / "clips").rglob("manifest.json"))
    assert clips

    def buffers(clip):
        c = open_clip(clip)
        return {(f, f"{lvl}/{b}"): c.read(f, f"{lvl}/{b}") for f in c.frames for lvl in ("hr", "lr")
                for b in c.manifest["buffers"]}
    for clip in clips:
        assert_same_render(buffers(clip), buffers(tmp_path / "b" / clip.relative_to(tmp_path / "a")))


@requires_bpy
@pytest.mark.bpy
def test_render_scales_give_each_clip_an_lr_level_per_scale(tmp_path):
    """``scales = [4, 2]``: one clip, the same cameras and ground truth, LR levels at 4 ('lr') and 2 ('lr_x2')."""
    from gbuffer_export import open_clip
    spec = tmp_path / "s.toml"
    spec.write_text('[dataset]\nname = "sc"\n[render]\nframes = 2\nhr_size = "64x32"\nhr_spp = 2\nlr_spp = 2\n'
                    'gbuffer_spp = 1\nhr_denoise = false\nscales = [4, 2]\n[[source]]\nkind = "builtin"\n'
                    'seeds = "3:3"\ncameras = ["scene"]\nhdri = ["builtin:courtyard"]\n')
    out = tmp_path / "out"
    proc = run_cli("dataset", spec, "-o", out, "--threads", "1", "--no-progress")
    assert proc.returncode == 0, proc.stderr[-2000:]
    clip = open_clip(split_clips(out, "train")[0])
    assert clip.scales == [2.0, 4.0] and clip.scale == 4
    assert clip.sizes == {"hr": (64, 32), "lr": (16, 8), "lr_x2": (32, 16)}
    f = clip.frames[0]
    lr2 = clip.at_scale(2).read(f, "lr/radiance")
    assert lr2.shape[:2] == (16, 32) and np.isfinite(lr2).all()
    # the same view at both levels: lr_x2's depth pooled 2x2 follows lr's (0.89 when written), not lr's upside down
    d2, d4 = (np.nan_to_num(d.reshape(d.shape[:2]), posinf=0.0) for d in
              (clip.at_scale(2).read(f, "lr/depth"), clip.read(f, "lr/depth")))
    pooled = d2.reshape(8, 2, 16, 2).mean(axis=(1, 3)).ravel()
    assert np.corrcoef(pooled, d4.ravel())[0, 1] > 0.8 > 0.3 > abs(np.corrcoef(pooled, d4[::-1].ravel())[0, 1])


@pytest.mark.parametrize("spec_file", sorted((REPO / "examples").glob("dataset_*.toml"))
                         + [REPO / "benchmarks" / n for n in ("networks_dataset.toml", "nsrd_base_dataset.toml",
                                                              "zoo_dataset.toml", "zoo_scales_dataset.toml")],
                         ids=lambda p: p.name)
def test_shipped_specs_expand_with_test_assets_out_of_training(spec_file):
    """Every dataset spec the project ships parses, expands to uniquely named clips, and no training clip shows a
    test asset (as its main asset or as clutter). The medium spec contains the small one's clips exactly, plus its
    own, and holds out 6 built-in scenes as its val split."""
    if not (REPO.parent / "shared" / "scenes").is_dir():
        pytest.skip("../shared/scenes is not present")
    jobs = expand(load_spec(spec_file))
    assert len({j.id for j in jobs}) == len(jobs)
    # levels (kind = "scene") are split by region: their cells, not their files, are disjoint
    from gbuffer_export.dataset.check import region_errors
    assert region_errors({"clips": [j.to_json() for j in jobs]}) == []
    test_assets = {Path(j.asset).stem for j in jobs if j.split == "test" and j.asset and j.kind != "scene"}
    assert test_assets or {j.split for j in jobs if j.kind == "scene"} >= {"train", "test"}, spec_file
    for j in jobs:
        if j.split != "test":
            shown = [Path(p).stem for p in ([j.asset] if j.asset else []) + list(j.clutter)]
            assert not test_assets & set(shown), (j.id, shown)
    if spec_file.name == "dataset_medium.toml":
        small = {j.id: j for j in expand(load_spec(spec_file.parent / "dataset_small.toml"))}
        medium = {j.id: j for j in jobs}
        assert small.keys() <= medium.keys() and len(medium) == 67
        assert sorted(j.id for j in jobs if j.split == "val") == [f"builtin_val-s{s:04d}" for s in range(36, 42)]
        for cid, j in small.items():
            assert (medium[cid].seed, medium[cid].hdri, medium[cid].clutter, medium[cid].split) == \
                (j.seed, j.hdri, j.clutter, j.split)
        assert {j.id for j in jobs if j.split == "test"} == {c for c, j in small.items() if j.split == "test"}
    if spec_file.name == "dataset_large.toml":  # the medium dataset's clips, with the footprint HR F_beta, then its own
        medium = expand(load_spec(spec_file.parent / "dataset_medium.toml"))

        def but_hr_fbeta(j):
            d = j.to_json()
            return {**d, "render": {k: v for k, v in d["render"].items() if k != "hr_fbeta"}}
        assert [but_hr_fbeta(j) for j in jobs[:len(medium)]] == [but_hr_fbeta(j) for j in medium]
        assert {j.render["hr_fbeta"] for j in jobs} == {"footprint"}
        assert {j.render["hr_fbeta"] for j in medium} == {"point"}
        assert len(test_assets) >= 5 and "SheenCloth" not in test_assets  # sheen is also in training
        levels: dict[str, set] = {}
        for j in jobs:
            if j.kind == "scene":
                levels.setdefault(Path(j.asset).stem, set()).add(j.split)
        assert len(levels) == 3 and all(v == {"train", "val", "test"} for v in levels.values())
    if spec_file.name == "dataset_games.toml":  # the scale set's clips exactly, then the later families' own
        scale = expand(load_spec(spec_file.parent / "dataset_scale.toml"))
        assert [j.to_json() for j in jobs[:len(scale)]] == [j.to_json() for j in scale] and len(jobs) == 1148
    if spec_file.name == "zoo_scales_dataset.toml":  # the zoo clips, the same cameras, with an LR level at 2x
        zoo = expand(load_spec(spec_file.parent / "zoo_dataset.toml"))

        def but_scales(j):
            d = j.to_json()
            return {**d, "render": {k: v for k, v in d["render"].items() if k != "scales"}}
        assert [but_scales(j) for j in jobs] == [but_scales(j) for j in zoo]
        assert {tuple(j.render["scales"]) for j in jobs} == {(4.0, 2.0)}



def test_ray_task_no_node_can_hold_is_refused_in_one_line(tmp_path):
    """Issue 26: on a real local Ray cluster of one 1-CPU node, --threads 2 asks for a task Ray can never schedule:
    refused in one line before anything is submitted (it used to wait forever at 0%)."""
    pytest.importorskip("ray")
    spec = tmp_path / "s.toml"
    spec.write_text('[dataset]\nname = "r"\nseed = 1\n[render]\nframes = 1\nhr_size = "16x8"\nscale = 2\n'
                    '[[source]]\nname = "b"\nkind = "builtin"\nseeds = "0:0"\nsplit = "train"\n')
    code = f"""
import sys, ray
ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
from gbuffer_export.cli import main
try:
    rc = main(["dataset", {str(spec)!r}, "-o", {str(tmp_path / 'ds')!r}, "--executor", "ray", "--threads", "2",
               "--no-progress"])
finally:
    ray.shutdown()
sys.exit(rc)
"""
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=ENV, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    err = [ln for ln in proc.stderr.splitlines() if ln.startswith("blendsr: error:")]
    assert err == ["blendsr: error: --threads 2: no node of the local Ray cluster has 2 CPUs (the largest has 1), so "
                   "its tasks could never run; pass --threads 1 or fewer"], proc.stderr[-2000:]
    assert not list((tmp_path / "ds" / "clips").glob("*/manifest.json"))


def test_scale_problem_names_the_scales_a_model_takes():
    from gbuffer_export.dataset.buffers import MODEL_SCALES, scale_problem
    assert scale_problem("pretrained:fourier-sr", 3) == "" and scale_problem("bicubic", 5) == ""
    assert scale_problem("pretrained:fusesr", 4) == "" and scale_problem("demod-jbu", 8) == ""
    assert scale_problem("pretrained:fusesr", 2) == "pretrained:fusesr was trained for scale 4, not 2"
    assert scale_problem("fusesr", 3) == "fusesr takes scale 2 or 4 or 8, not 3"
    assert scale_problem("/some/checkpoint.pt", 3) == ""  # checked when it loads
    assert MODEL_SCALES["fourier-sr"] is None and MODEL_SCALES["pretrained:fourier-sr"] is None


@pytest.mark.torch
def test_model_scale_table_is_derived_from_the_models_and_the_shipped_weights():
    pytest.importorskip("torch")
    from gbuffer_export.dataset.buffers import MODEL_SCALES
    from training.commands.buffer_table import model_scale_table
    assert {k: None if v is None else tuple(v) for k, v in model_scale_table().items()} == MODEL_SCALES, (
        "gbuffer_export/dataset/model_buffers.json is stale: run make generate")
