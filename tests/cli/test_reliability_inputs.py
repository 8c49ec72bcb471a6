"""Issue 26 (items 5, 8, 10, 11, 12): refusals of bad specs, indexes and settings, before anything is built."""
from __future__ import annotations

import json
import time

import pytest
from tests.conftest import requires_bpy, run_cli

from gbuffer_export.config import MAX_SPP, ConfigError, RenderConfig
from gbuffer_export.dataset.build import INDEX, SCHEMA, SCHEMA_VERSION, DatasetError, read_index
from gbuffer_export.dataset.check import validate_dataset
from gbuffer_export.dataset.spec import MAX_CLIPS, SpecError, expand, load_spec


def _spec(tmp_path, text, name="spec.toml"):
    p = tmp_path / name
    p.write_text('[dataset]\nname = "t"\n[render]\nhr_size = "64x36"\nframes = 2\n' + text)
    return p


def _assets(tmp_path, *stems):
    d = tmp_path / "assets"
    d.mkdir(exist_ok=True)
    for s in stems:
        (d / f"{s}.gltf").write_text('{"asset": {"version": "2.0"}}')
    return d


# ------------------------------------------------------------------------------------------- item 5: leaks

def test_a_test_asset_in_a_train_source_is_refused(tmp_path):
    _assets(tmp_path, "Chair", "Lamp")
    spec = load_spec(_spec(tmp_path, '[splits]\ntest = ["Lamp"]\n[[source]]\nname = "train_assets"\n'
                                     'kind = "assets"\npaths = ["assets"]\nsplit = "train"\n'))
    with pytest.raises(SpecError) as info:
        expand(spec)
    msg = str(info.value)
    assert "\n" not in msg and "spec.toml" in msg and "train_assets" in msg and "'Lamp'" in msg and "test" in msg


def test_a_test_seed_in_a_train_builtin_source_is_refused(tmp_path):
    spec = load_spec(_spec(tmp_path, '[splits]\ntest = ["builtin:3"]\n[[source]]\nname = "b"\nkind = "builtin"\n'
                                     'seeds = "0:5"\nsplit = "train"\n'))
    with pytest.raises(SpecError, match="builtin:3"):
        expand(spec)


def test_listed_assets_without_a_forced_split_still_go_to_their_list(tmp_path):
    _assets(tmp_path, "Chair", "Lamp")
    spec = load_spec(_spec(tmp_path, '[splits]\ntest = ["Lamp"]\n[[source]]\nkind = "assets"\npaths = ["assets"]\n'))
    assert {j.scene_id: j.split for j in expand(spec)} == {"Chair": "train", "Lamp": "test"}


# ------------------------------------------------------------------------------------------- item 8: runaways

@pytest.mark.parametrize("source", ['kind = "builtin"\nseeds = "0:999999"\n',
                                    'kind = "assets"\npaths = ["assets"]\nclips_per_asset = 1000000\n'])
def test_a_spec_of_a_million_clips_is_refused_at_once(tmp_path, source):
    _assets(tmp_path, "Chair")
    spec = load_spec(_spec(tmp_path, "[[source]]\n" + source))
    t0 = time.process_time()  # this process's CPU: other work on the machine does not count
    with pytest.raises(SpecError, match=f"at most {MAX_CLIPS}"):
        expand(spec)
    assert time.process_time() - t0 < 2.0  # expanding them first would take minutes


def test_a_spec_of_a_million_clips_is_refused_by_dataset_dry_run(tmp_path):
    spec = _spec(tmp_path, '[[source]]\nkind = "builtin"\nseeds = "0:999999"\n')
    proc = run_cli("dataset", spec, "-o", tmp_path / "ds", "--dry-run", timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1].startswith("blendsr: error: ") and "at most" in proc.stderr


def test_the_duplicate_id_check_is_linear(tmp_path):
    """Ten times the clips cost about ten times the CPU (a quadratic check: a hundred). Compared with each other, in
    this process's CPU time, so the load of other work on the machine does not decide it."""
    def cpu_seconds(n: int) -> float:
        spec = load_spec(_spec(tmp_path, f'[[source]]\nkind = "builtin"\nseeds = "0:{n - 1}"\n', f"s{n}.toml"))
        t0 = time.process_time()
        assert len(expand(spec)) == n
        return time.process_time() - t0
    small = min(cpu_seconds(3000) for _ in range(2))
    assert cpu_seconds(30000) < 40 * small


def test_samples_above_the_cycles_cap_are_refused(tmp_path):
    with pytest.raises(ConfigError, match=str(MAX_SPP)):
        RenderConfig(output=tmp_path / "c", hr_spp=1_000_000_000)
    RenderConfig(output=tmp_path / "c", hr_spp=MAX_SPP)
    with pytest.raises(SpecError, match="hr_spp"):
        load_spec(_spec(tmp_path, 'hr_spp = 1000000000\n[[source]]\nkind = "builtin"\nseeds = "0:1"\n'))


@requires_bpy
def test_a_million_frames_are_refused_before_the_scene_is_built(tmp_path):
    from tests.conftest import make_blend
    blend = make_blend("basic", tmp_path / "s.blend")  # a scene file: the built-in scene refuses frames > 1000 first
    t0 = time.perf_counter()
    proc = run_cli("render", blend, "-o", tmp_path / "c", "--hr-size", "64x36", "--frames", "1:100000000",
                   "--camera-path", "orbit", "--hr-spp", "2", "--lr-spp", "1", "--threads", "1", timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "100000000 frame(s)" in proc.stderr.strip().splitlines()[-1]
    assert time.perf_counter() - t0 < 60
    assert not (tmp_path / "c" / "manifest.json").exists()


# ------------------------------------------------------------------------------------------- item 11: values

@pytest.mark.parametrize("key,value", [("hdri_strength", "inf"), ("hdri_strength", "[0.5, nan]"),
                                       ("target_size_m", "nan"), ("target_size_m", "inf")])
def test_non_finite_floats_are_refused_naming_the_key(tmp_path, key, value):
    _assets(tmp_path, "Chair")
    with pytest.raises(SpecError) as info:
        load_spec(_spec(tmp_path, f'[[source]]\nkind = "assets"\npaths = ["assets"]\n{key} = {value}\n'))
    assert f"source[0].{key}" in str(info.value) and "finite" in str(info.value)


def test_non_finite_split_fractions_are_refused(tmp_path):
    with pytest.raises(SpecError, match="splits.val_fraction"):
        load_spec(_spec(tmp_path, '[splits]\nval_fraction = nan\n[[source]]\nkind = "builtin"\nseeds = "0:1"\n'))


def test_a_folder_named_like_an_hdri_is_refused_at_spec_expansion(tmp_path):
    hd = tmp_path / "hdri"
    (hd / "sky.hdr").mkdir(parents=True)
    spec = load_spec(_spec(tmp_path, '[[source]]\nkind = "builtin"\nseeds = "0:1"\nhdri = ["hdri"]\n'))
    with pytest.raises(SpecError, match="sky.hdr: not a file"):
        expand(spec)


def _index(root, clips):
    root.mkdir(parents=True, exist_ok=True)
    (root / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "name": "x",
                                          "clips": clips}))
    return root


@pytest.mark.parametrize("entry,words", [({"id": "a", "split": "train"}, "lacks 'path'"),
                                         ({"id": "a", "path": "clips/a", "split": "train", "frames_planned": "abc"},
                                          "frames_planned = 'abc'"),
                                         ({"id": "a", "path": "clips/a"}, "lacks 'split'"),
                                         ("clip", "not an object")])
def test_a_broken_index_entry_is_one_line_naming_dataset_json(tmp_path, entry, words):
    root = _index(tmp_path / "ds", [entry])
    with pytest.raises(DatasetError) as info:
        read_index(root)
    assert str(root / INDEX) in str(info.value) and words in str(info.value) and "\n" not in str(info.value)
    proc = run_cli("validate", root, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert words in proc.stderr


# ------------------------------------------------------------------------------------------- item 10: validate

def test_an_index_listing_no_clips_fails_validation(tmp_path):
    rep = validate_dataset(_index(tmp_path / "ds", []), progress=False)
    assert not rep.ok and "lists no clips" in rep.lines()[0]


def test_a_failed_clip_is_reported_as_failed(tmp_path):
    root = _index(tmp_path / "ds", [{"id": "b-s0000", "path": "clips/b-s0000", "split": "train", "state": "failed",
                                     "error": "blendsr: error: the scene is empty", "frames_planned": 2,
                                     "licence": {"licence": "MIT"}}])
    rep = validate_dataset(root, progress=False)
    assert not rep.ok
    assert rep.index_errors == ["clip b-s0000 failed: blendsr: error: the scene is empty (fix it and rerun "
                                "'blendsr dataset')"]


# ------------------------------------------------------------------------------------------- item 12: LR size

def test_an_lr_size_under_blenders_minimum_is_refused_up_front(tmp_path):
    with pytest.raises(ConfigError, match="under 4 pixels"):
        RenderConfig(output=tmp_path / "c", hr_size=(12, 12), scale=4)
    with pytest.raises(ConfigError, match="4x2"):
        RenderConfig(output=tmp_path / "c", hr_size=(64, 32), scales=(2, 16))
    with pytest.raises(SpecError, match=r"source\[0\]\.hr_size 12x12 at scale 4 .*under 4 pixels"):
        load_spec(_spec(tmp_path, 'scale = 4\n[[source]]\nkind = "builtin"\nseeds = "0:1"\nhr_size = "12x12"\n'))


@requires_bpy
def test_the_next_render_removes_scratch_folders_of_dead_renders(tmp_path):
    """Issue 26 item 10: .render-PID-* folders of a render that died are removed; a live shard's are kept."""
    import os
    import subprocess
    from gbuffer_export.blender.render import remove_stale_scratch
    dead = subprocess.Popen(["true"])
    dead.wait()
    clip = tmp_path / "c"
    (clip / f".render-{dead.pid}-abc").mkdir(parents=True)
    (clip / f".render-{dead.pid}-abc" / "hr_radiance.exr").write_bytes(b"x")
    (clip / f".render-{os.getppid()}-def").mkdir()
    assert remove_stale_scratch(clip) == [clip / f".render-{dead.pid}-abc"]
    assert sorted(p.name for p in clip.iterdir()) == [f".render-{os.getppid()}-def"]


def test_a_million_frames_per_clip_are_refused_by_dataset_before_anything_starts(tmp_path):
    spec = _spec(tmp_path, '[[source]]\nkind = "builtin"\nseeds = "0:1"\nframes = 100000000\n')
    proc = run_cli("dataset", spec, "-o", tmp_path / "ds", timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert "spec.toml: clip builtin-s0000:" in last and "100000000 frame(s)" in last
    assert not (tmp_path / "ds").exists()


def test_only_frames_picks_a_subset_of_the_range_and_of_the_shard(tmp_path):
    """``only_frames``: the frames rendered, inside ``frames`` (a frame keeps its index in the whole range); with a
    shard, the shard's frames among them. Bad values are one-line errors naming the key."""
    cfg = RenderConfig(output=tmp_path / "c", frames=(1, 10), only_frames=(7, 3))
    assert cfg.only_frames == (3, 7) and cfg.my_frames(range(1, 11)) == [3, 7]
    assert RenderConfig(output=tmp_path / "c", frames=(1, 10), shard=(2, 2),
                        only_frames=(3, 4, 6)).my_frames(range(1, 11)) == [4, 6]
    assert RenderConfig(output=tmp_path / "c", frames=(1, 10), shard=(2, 3)).my_frames(range(1, 11)) == range(2, 11, 3)
    assert RenderConfig(output=tmp_path / "c", only_frames=[5]).only_frames == (5,)  # JSON list -> tuple
    for bad, detail in (((11,), "frame 11 is outside the range 1:10"), ((2, 2), "a frame is given twice"),
                        ((), "no frame given"), (("a",), "expected an integer")):
        with pytest.raises(ConfigError, match="only_frames") as e:
            RenderConfig(output=tmp_path / "c", frames=(1, 10), only_frames=bad)
        assert detail in str(e.value) and "\n" not in str(e.value), str(e.value)
    late = RenderConfig(output=tmp_path / "c", only_frames=(60,))  # the scene's range is known after loading it
    with pytest.raises(ConfigError, match="only_frames '60': frame 60 is outside the range 1:48"):
        late.check_frames_subset(range(1, 49))


def test_dataset_clips_that_name_no_clip_are_refused_before_anything_is_written(tmp_path):
    """``--clips``: a typo would render nothing and report success; it is one line naming the entry, exit 2, and
    no dataset folder. ``--split`` names a split the spec has or is refused."""
    spec = _spec(tmp_path, '[[source]]\nkind = "builtin"\nseeds = "0:2"\nframes = 2\n')
    proc = run_cli("dataset", spec, "-o", tmp_path / "ds", "--clips", "builtin-s0000,builtin-s9*", timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "--clips 'builtin-s9*': names no clip of the spec" in proc.stderr.strip().splitlines()[-1]
    proc = run_cli("dataset", spec, "-o", tmp_path / "ds", "--split", "train,tset", timeout=120)
    assert proc.returncode == 2 and "--split 'tset': choose from train, val, test" in proc.stderr, proc.stderr
    proc = run_cli("dataset", spec, "-o", tmp_path / "ds", "--split", "test", timeout=120)  # no test clip
    assert proc.returncode == 2 and "--split: the spec has no clip in split test" in proc.stderr, proc.stderr
    proc = run_cli("dataset", spec, "-o", tmp_path / "ds", "--status", "--split", "", timeout=120)
    assert proc.returncode == 2 and "not with --status or --dry-run" in proc.stderr, proc.stderr
    assert not (tmp_path / "ds").exists()
