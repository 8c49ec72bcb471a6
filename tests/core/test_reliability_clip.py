"""Reliability of the core (issue 26): one writer per clip, mixed clips caught by ``validate``, nothing outside a
dataset or clip folder read or written (index paths, links inside a clip), Ray requests no node can hold."""
from __future__ import annotations

import json
import shutil
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import edit_header, edit_record
from gbuffer_export.clip import ClipError, ClipWriter, load_manifest, open_clip
from gbuffer_export.conventions import pass_seed
from gbuffer_export.synthetic import make_synthetic_clip
from gbuffer_export.validate import validate_clip


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("base") / "clip", frames=(1, 2, 3), hr_size=(16, 8), scale=2)


@pytest.fixture
def clip(base, tmp_path):
    dst = tmp_path / "clip"
    shutil.copytree(base, dst)
    return dst


def header_of(clip: Path, **changes) -> dict:
    m = load_manifest(clip)
    h = {k: v for k, v in m.items() if k not in ("frame_data", "identity")}
    h.update(changes)
    return h


# ------------------------------------------------------------------------------------------ one writer per clip

def test_a_second_writer_of_a_clip_is_refused_until_the_first_closes(clip):
    h = header_of(clip)
    first = ClipWriter(clip, h)
    with pytest.raises(ClipError, match="another 'blendsr render' is writing this clip") as err:
        ClipWriter(clip, h)
    assert str(clip) in str(err.value) and "\n" not in str(err.value)
    first.close()
    with ClipWriter(clip, h) as again:  # released: a resumed render goes on
        assert again.is_frame_done(2)


def test_a_writer_with_other_settings_is_refused_even_before_the_first_frame(tmp_path, base):
    """The race of issue 26: two renders into one new folder. The first writer claims the folder (its header is on
    disk at once), so the second, with another seed, is refused although no frame is finished yet."""
    new = tmp_path / "new"
    a = ClipWriter(new, header_of(base, render={"seed": 0}))
    assert (new / "manifest.json").is_file() and open_clip(new).frames == []
    with pytest.raises(ClipError, match="holds a different clip"):
        ClipWriter(new, header_of(base, render={"seed": 5}))
    a.close()
    with pytest.raises(ClipError, match="holds a different clip"):
        ClipWriter(new, header_of(base, render={"seed": 5}))
    ClipWriter(new, header_of(base, render={"seed": 0})).close()  # the same render resumes


def test_shards_share_a_clip_but_two_writers_of_one_shard_or_of_two_splits_do_not(clip):
    one, two = ClipWriter(clip, header_of(clip, shard=[1, 2])), ClipWriter(clip, header_of(clip, shard=[2, 2]))
    with pytest.raises(ClipError, match="--shard 1/2"):
        ClipWriter(clip, header_of(clip, shard=[1, 2]))
    with pytest.raises(ClipError, match="another 'blendsr render'"):
        ClipWriter(clip, header_of(clip))  # an unsharded writer
    with pytest.raises(ClipError, match="same N"):
        ClipWriter(clip, header_of(clip, shard=[1, 3]))
    one.merge()
    two.merge()
    one.close()
    two.close()
    assert validate_clip(clip).ok


# ------------------------------------------------------------------------------------ validate: a mixed clip

def _as_rendered(clip: Path, seed: int = 7, hr_spp: int = 16, lr_spp: int = 2) -> None:
    """Give the synthetic clip a render header and records that follow it (what ``render`` writes)."""
    edit_header(clip, lambda m: m["render"].update(seed=seed, hr={**m["render"]["hr"], "spp": hr_spp},
                                                      lr={**m["render"]["lr"], "spp": lr_spp}))
    for f in (1, 2, 3):
        def fn(r, f=f):
            r["hr"].update(spp=hr_spp, seed=pass_seed(seed, f, 1), gbuffer_seed=pass_seed(seed, f, 0))
            r["lr"].update(spp=lr_spp, seed=pass_seed(seed, f, 2))
        edit_record(clip, f, fn)


def test_validate_accepts_records_that_follow_the_header(clip):
    _as_rendered(clip)
    r = validate_clip(clip)
    assert r.ok and not r.warnings, [f.line() for f in r.findings]


@pytest.mark.parametrize("what", ["seed", "spp", "camera"])
def test_validate_reports_a_frame_of_another_render(clip, what):
    _as_rendered(clip)

    def other_render(r):  # frame 2 rendered by `--seed 5 --hr-spp 2`
        if what == "seed":
            r["hr"]["seed"], r["lr"]["seed"] = pass_seed(5, 2, 1), pass_seed(5, 2, 2)
        elif what == "spp":
            r["hr"]["spp"] = 2
        else:  # another camera path: frame 2's pose moves, so frame 3's previous camera no longer matches
            for lvl in r.values():
                lvl["world_from_camera"][1][3] += 0.5
    edit_record(clip, 2, other_render)
    r = validate_clip(clip, quick=True)
    hits = [f for f in r.findings if f.code == "mixed-clip"]
    assert hits and not r.ok, [f.line() for f in r.findings]
    assert {f.frame for f in hits} == ({3} if what == "camera" else {2})
    assert "another render" in hits[0].message and "\n" not in hits[0].line()


# ------------------------------------------------------------------------------ links inside a clip

def test_a_linked_buffer_is_never_read(clip, tmp_path):
    outside = tmp_path / "outside.exr"
    p = open_clip(clip).path_of(2, "hr/radiance")
    shutil.copyfile(p, outside)
    p.unlink()
    p.symlink_to(outside)
    with pytest.raises(ClipError, match="symbolic link"):
        open_clip(clip).read(2, "hr/radiance")
    r = validate_clip(clip)
    assert any(f.code == "unsafe-link" and f.frame == 2 for f in r.findings) and not r.ok


def test_a_resumed_writer_never_writes_through_a_linked_folder(clip, tmp_path):
    """hr/radiance is a link to a folder outside the clip: rewriting frame 3 is refused and nothing lands there."""
    outside = tmp_path / "outside"
    shutil.copytree(clip / "hr" / "radiance", outside)
    before = sorted(p.name for p in outside.iterdir())
    shutil.rmtree(clip / "hr" / "radiance")
    (clip / "hr" / "radiance").symlink_to(outside, target_is_directory=True)
    (clip / "frames" / "000003.json").unlink()
    with ClipWriter(clip, header_of(clip)) as w:
        assert not w.is_frame_done(3)
        with pytest.raises(ClipError, match="symbolic link"):
            w.write_buffer(3, "hr", "radiance", np.zeros((8, 16, 3), np.float32))
    assert sorted(p.name for p in outside.iterdir()) == before


def test_a_linked_manifest_or_record_is_never_read(clip, tmp_path):
    (tmp_path / "m.json").write_text((clip / "manifest.json").read_text())
    (clip / "manifest.json").unlink()
    (clip / "manifest.json").symlink_to(tmp_path / "m.json")
    with pytest.raises(ClipError, match="symbolic link"):
        open_clip(clip)
    assert [f.code for f in validate_clip(clip).findings] == ["unsafe-link"]


# ------------------------------------------------------------------------------ paths in a dataset index

def make_dataset(root: Path, clip: Path, paths: list) -> Path:
    """A dataset folder whose index lists ``paths`` (the first is the real clip copied inside)."""
    from gbuffer_export.dataset.build import INDEX, SCHEMA
    (root / "clips").mkdir(parents=True)
    shutil.copytree(clip, root / "clips" / "good")
    entries = [{"id": f"c{i}", "path": p, "split": "test", "scene_id": f"s{i}", "frames_planned": 3,
                "licence": {"licence": "CC0-1.0"}} for i, p in enumerate(paths)]
    (root / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": 1, "name": "t", "seed": 0,
                                          "splits": {}, "clips": entries}))
    return root


@pytest.mark.parametrize("bad", ["../outside", "ABS", "clips/../../outside", "clips/link", "", None])
def test_an_index_path_outside_the_dataset_is_refused_in_one_line(clip, tmp_path, bad):
    from gbuffer_export.dataset.build import expand_data_paths, split_clips
    from gbuffer_export.dataset.check import validate_dataset
    outside = tmp_path / "outside"
    shutil.copytree(clip, outside)
    ds = tmp_path / "ds"
    bad = str(outside) if bad == "ABS" else bad
    make_dataset(ds, clip, ["clips/good", bad])
    (ds / "clips" / "link").symlink_to(outside, target_is_directory=True)
    from gbuffer_export.dataset.build import DatasetError
    with pytest.raises((ClipError, DatasetError)) as err:
        split_clips(ds, "test")
    msg = str(err.value)
    assert str(ds / "dataset.json") in msg and "c1" in msg and "\n" not in msg
    with pytest.raises((ClipError, DatasetError)):
        expand_data_paths([ds], "test")
    if not bad:  # an empty or missing path: the index itself is malformed (read_index refuses it, one line)
        with pytest.raises(DatasetError, match="c1"):
            validate_dataset(ds, progress=False)
        return
    rep = validate_dataset(ds, progress=False)
    assert not rep.ok and list(rep.clips) == ["c0"] and any("c1" in e for e in rep.index_errors)
    assert not list(outside.glob(".*cache*"))


def test_validate_dataset_cli_fails_on_an_outside_path(clip, tmp_path, capsys):
    from gbuffer_export.cli import main
    outside = tmp_path / "outside"
    shutil.copytree(clip, outside)
    ds = make_dataset(tmp_path / "ds", clip, ["clips/good", "../outside"])
    assert main(["validate", str(ds), "--no-progress"]) == 1
    out = capsys.readouterr().out
    assert "FAILED" in out and "leads outside" in out


# ------------------------------------------------------------------------------ Ray: infeasible requests

class FakeRay(types.ModuleType):
    """A Ray cluster of 2-CPU nodes whose scheduler, like Ray's, never runs a task asking for more."""

    def __init__(self, cpus=(2.0, 2.0)):
        super().__init__("ray")
        self.cpus = cpus
        self.asked: list[float] = []

    def is_initialized(self):
        return True

    def nodes(self):
        return [{"Alive": True, "Resources": {"CPU": c}} for c in self.cpus] + [{"Alive": False,
                                                                                  "Resources": {"CPU": 64.0}}]

    def remote(self, num_cpus=1):
        self.asked.append(num_cpus)

        def wrap(fn):
            return types.SimpleNamespace(remote=lambda *a: ("ref", num_cpus, a))
        return wrap

    def wait(self, pending, num_returns=1):
        if any(r[1] > max(self.cpus) for r in pending):
            raise TimeoutError("infeasible task: it would wait forever")
        return pending[:1], pending[1:]

    def get(self, ref):
        return 0, ""


def test_ray_refuses_threads_no_node_has_and_fits_the_automatic_choice(tmp_path, monkeypatch):
    from gbuffer_export.dataset.build import DatasetError, _ray_map
    fake = FakeRay()
    monkeypatch.setitem(sys.modules, "ray", fake)
    job = types.SimpleNamespace(id="c0")
    done = []
    with pytest.raises(DatasetError, match=r"--threads 4: no node of the Ray cluster at h:1 has 4 CPUs \(the "
                                           r"largest has 2\)") as err:
        _ray_map([job], tmp_path, 4, "h:1", lambda *a: done.append(a), explicit=True)
    assert "\n" not in str(err.value) and fake.asked == [] and done == []
    _ray_map([job], tmp_path, 4, "h:1", lambda *a: done.append(a), explicit=False)  # automatic: fitted
    assert fake.asked == [2] and done == [(job, 0, "")]


def test_dataset_cli_refuses_an_infeasible_ray_request_in_one_line(tmp_path, monkeypatch, capsys):
    from gbuffer_export.cli import main
    monkeypatch.setitem(sys.modules, "ray", FakeRay())
    spec = tmp_path / "s.toml"
    spec.write_text('[dataset]\nname = "r"\nseed = 1\n[render]\nframes = 1\nhr_size = "16x8"\nscale = 2\n'
                    '[[source]]\nname = "b"\nkind = "builtin"\nseeds = "0:0"\nsplit = "train"\n')
    rc = main(["dataset", str(spec), "-o", str(tmp_path / "ds"), "--executor", "ray", "--address", "h:1",
               "--threads", "4", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "blendsr: error: --threads 4: no node" in err and "Traceback" not in err


def test_a_dataset_folder_with_links_out_is_refused_before_rendering(tmp_path):
    """Resuming a dataset folder whose clips/, .lock or a log links out: refused, nothing written outside."""
    from gbuffer_export.dataset.build import RunOptions, build_dataset
    from gbuffer_export.dataset.spec import load_spec
    spec = tmp_path / "s.toml"
    spec.write_text('[dataset]\nname = "r"\nseed = 1\n[render]\nframes = 1\nhr_size = "16x8"\nscale = 2\n'
                    '[[source]]\nname = "b"\nkind = "builtin"\nseeds = "0:0"\nsplit = "train"\n')
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "precious").write_text("keep")
    for i, (name, target) in enumerate((("clips", outside), (".lock", outside / "precious"),
                                        ("logs/b-s0000.log", outside / "precious"))):
        ds = tmp_path / f"ds{i}"
        (ds / name).parent.mkdir(parents=True, exist_ok=True)
        (ds / name).symlink_to(target)
        with pytest.raises(ClipError, match="symbolic link") as err:
            build_dataset(load_spec(spec), ds, RunOptions(progress=False, limit=0))
        assert "\n" not in str(err.value)
        assert sorted(p.name for p in outside.iterdir()) == ["precious"]
        assert (outside / "precious").read_text() == "keep"
