"""Reliability of the torch layer: checkpoints never run code, the default crop fits small clips."""
import os
import pickle
import zipfile

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.synthetic import SyntheticLook, make_synthetic_clip  # noqa: E402
from training.checkpoint import CheckpointError, load_checkpoint  # noqa: E402
from tests.conftest import set_args  # noqa: E402


SMALL = ["data.batch_size=2", "model.width=8", "model.blocks=1", "run.progress=false", "run.amp=\"none\"",
         "run.threads=0"]


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)


class _Payload:
    """Unpickling this calls os.system: what a hostile checkpoint does."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def one_line_error(capsys) -> str:
    """The one line a refused command printed on stderr (fails when it printed more or nothing)."""
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def one_step_run(clip, tmp_path) -> tuple:
    """A fusesr run of one step on ``clip`` in tmp_path/run: (run folder, its train argv without --max-steps)."""
    run = tmp_path / "run"
    argv = ["train", "--model", "fusesr", "--data", str(clip), "-o", str(run), *set_args(SMALL)]
    assert main(argv + ["--max-steps", "1"]) == 0
    return run, argv


def test_a_malicious_checkpoint_is_refused_with_one_line_and_runs_nothing(clip, tmp_path, capsys):
    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.pt"
    torch.save({"format": "blendsr.checkpoint", "scale": 4, "model": _Payload(marker)}, evil)
    with pytest.raises(CheckpointError, match="refused.*system"):
        load_checkpoint(evil)
    for argv in (["evaluate", "--checkpoint", str(evil), "--data", str(clip), "--json", str(tmp_path / "e.json")],
                 ["upscale", "--checkpoint", str(evil), "--clip", str(clip), "-o", str(tmp_path / "sr")]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "refused" in err and str(evil) in err, err
    assert not marker.exists()
    # a plain pickle (not torch's zip) is refused too, without unpickling it
    raw = tmp_path / "raw.pt"
    raw.write_bytes(pickle.dumps(_Payload(marker)))
    with pytest.raises(CheckpointError, match="not a BlendSR checkpoint"):
        load_checkpoint(raw)
    assert not marker.exists()


def test_real_checkpoints_load_weights_only_including_version_1_numpy_rng(clip, tmp_path):
    run = tmp_path / "run"
    assert main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(run), "--max-steps", "1",
                 *set_args(SMALL + ["data.crop=8"])]) == 0
    last = run / "checkpoints" / "last.pt"
    ck = load_checkpoint(last)
    assert ck["version"] == 2 and isinstance(ck["rng"]["numpy"], dict)
    assert torch.serialization.get_unsafe_globals_in_checkpoint(str(last)) == []  # plain types only
    ck["rng"]["numpy"] = np.random.get_state()  # what version 1 wrote
    ck["version"] = 1
    old = tmp_path / "v1.pt"
    torch.save(ck, old)
    assert isinstance(load_checkpoint(old)["rng"]["numpy"][1], np.ndarray)
    # and a v1 run resumes
    (run / "checkpoints" / "last.pt").write_bytes(old.read_bytes())
    assert main(["train", "-o", str(run), "--resume", "--max-steps", "2"]) == 0


def test_a_file_that_is_not_a_checkpoint_is_one_line(clip, tmp_path, capsys):
    junk = tmp_path / "junk.pt"
    with zipfile.ZipFile(junk, "w") as z:
        z.writestr("a/data.pkl", b"not a pickle")
    assert main(["evaluate", "--checkpoint", str(junk), "--data", str(clip), "--json", str(tmp_path / "e.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(junk) in err


def test_any_crop_larger_than_the_clips_shrinks_with_a_one_line_note(clip, tmp_path, caplog):
    """Issue 31 item 7: the default crop and a crop the user set follow one rule (the note: logging, INFO)."""
    caplog.set_level("INFO", logger="training")
    for n, crop in enumerate((None, 20)):  # LR 16x9: neither the default 64 nor 20 fits
        run = tmp_path / f"run{n}"
        sets = SMALL + ([f"data.crop={crop}"] if crop else [])
        assert main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(run), "--max-steps", "1",
                     *set_args(sets)]) == 0
        notes = [r.getMessage() for r in caplog.records if "data.crop" in r.getMessage()]
        caplog.clear()
        assert notes == [f"note: data.crop {crop or 64} -> 9, the largest that fits {clip} (LR 16x9); set "
                         "data.crop to choose another"], notes
        ck = load_checkpoint(run / "checkpoints" / "last.pt")
        assert ck["config"]["data"]["crop"] == 9 and ck["resolved"]["crop"] == 9
        assert ck["user_config"]["data"]["crop"] == (crop or 64)  # the user's configuration is kept as given


def test_crop_below_one_or_off_the_grid_of_a_fractional_scale_is_refused(tmp_path, capsys):
    from gbuffer_export.config import ConfigError
    from training.run import fit_crop
    assert fit_crop(8, {"c": (2.5, (32, 16))}) == (8, None)
    assert fit_crop(64, {"c": (2.5, (32, 15))})[0] == 14  # shrunk onto the grid of 5/2
    with pytest.raises(ConfigError, match=r"data.crop = 7 is not a multiple of 2, the LR crop grid of scale\(s\) "
                                          r"2.5; set data.crop = 6 or 8"):
        fit_crop(7, {"a": (2, (40, 20)), "b": (2.5, (32, 16))})
    with pytest.raises(ConfigError, match="at least 1"):
        fit_crop(0, {"c": (4, (16, 9))})
    multi = make_synthetic_clip(tmp_path / "m", frames=range(1, 4), hr_size=(80, 40), scales=(2, 2.5))
    assert main(["train", "--model", "fourier-sr", "--data", str(multi), "-o", str(tmp_path / "r"), "--max-steps",
                 "1", "--set", "data.crop=7", "--set", "run.progress=false"]) == 2
    assert "data.crop = 7 is not a multiple of 2" in one_line_error(capsys)


def test_identical_resume_after_an_automatic_crop_is_accepted_and_a_change_is_named(clip, tmp_path, capsys):
    """Issue 26 item 3: the crop shrunk for LR 16x9 no longer makes the identical command 'differ'."""
    run, argv = one_step_run(clip, tmp_path)
    assert main(argv + ["--max-steps", "2", "--resume"]) == 0
    assert load_checkpoint(run / "checkpoints" / "last.pt")["step"] == 2
    capsys.readouterr()
    assert main(argv + ["--max-steps", "3", "--resume", "--set", "loss.fft_weight=0.2"]) == 2
    assert "loss.fft_weight = 0.2 differs from the checkpoint's 0.0" in one_line_error(capsys)
    assert main(argv + ["--max-steps", "3", "--resume", "--set", "data.crop=8"]) == 2
    assert "data.crop = 8 differs from the checkpoint's 64" in one_line_error(capsys)


def test_a_checkpoint_without_the_resolved_record_resumes_and_names_a_change(clip, tmp_path, capsys):
    """Checkpoints written before ResolvedRun hold only the resolved 'config' (crop 9, model.scale 4)."""
    run, argv = one_step_run(clip, tmp_path)
    last = run / "checkpoints" / "last.pt"
    ck = load_checkpoint(last)
    del ck["resolved"], ck["user_config"]
    torch.save(ck, last)
    assert main(argv + ["--max-steps", "2", "--resume"]) == 0  # the identical command
    assert main(["train", "-o", str(run), "--resume", "--max-steps", "3"]) == 0  # no configuration at all
    capsys.readouterr()
    ck = load_checkpoint(last)
    del ck["resolved"], ck["user_config"]
    torch.save(ck, last)
    assert main(argv + ["--max-steps", "4", "--resume", "--set", "data.crop=5"]) == 2
    assert "the resolved crop 9 -> 5 differs" in one_line_error(capsys)


def test_a_second_train_into_a_busy_run_folder_is_one_line(clip, tmp_path, capsys):
    from gbuffer_export.locks import FolderLock
    run = tmp_path / "run"
    argv = ["train", "--model", "fusesr", "--data", str(clip), "-o", str(run), "--max-steps", "1", *set_args(SMALL)]
    run.mkdir()
    with FolderLock(run, "held by the test"):
        assert main(argv) == 2
        assert "another 'blendsr train' is writing this run folder" in one_line_error(capsys)
        assert not (run / "checkpoints").exists()
    assert main(argv) == 0
    capsys.readouterr()
    with FolderLock(run, "held by the test"):
        assert main(argv + ["--resume"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "another 'blendsr train'" in err[-1], err


def test_implausible_radiance_falls_under_the_nonfinite_policy(tmp_path, capsys):
    from gbuffer_export.clip import open_clip
    from gbuffer_export.demod import RADIANCE_CAP
    from gbuffer_export.exr import write_exr
    from training.cache import ClipCache, NonFiniteError
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)
    c = open_clip(clip)
    a = c.read(2, "lr/radiance")
    a[3, 4, 0] = 1e30
    write_exr(c.path_of(2, "lr/radiance"), {ch: a[..., i] for i, ch in enumerate("RGB")})
    with pytest.raises(NonFiniteError, match=r"frame 2.*1 NaN/Inf or implausible"):
        ClipCache(clip).ensure(["lr/radiance"])
    assert main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(tmp_path / "run"), "--max-steps", "1",
                 *set_args(SMALL)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "implausible" in err[-1] and str(c.path_of(2, "lr/radiance")) in err[-1]
    with pytest.warns(RuntimeWarning, match="implausible"):
        cache = ClipCache(clip, nonfinite="sanitize").ensure(["lr/radiance"])
    assert cache.read(2, "lr/radiance")[3, 4, 0] == RADIANCE_CAP
    assert cache.index["sanitized"][0]["count"] == 1


# ------------------------------------------------------------------------------ issue 26: the cache's filesystem

def _no_space(fd, offset, length):
    raise OSError(28, "No space left on device")


def test_a_full_cache_filesystem_is_one_line_with_no_stray_file(clip, tmp_path, monkeypatch, capsys):
    """The cache reserves each array (posix_fallocate) before mapping it: a full filesystem is a one-line error
    (exit 2), not a SIGBUS while writing the map, and leaves no temporary file."""
    from gbuffer_export.clip import ClipError
    from training.cache import ClipCache
    monkeypatch.setattr(os, "posix_fallocate", _no_space)
    cache_dir = tmp_path / "cache"
    with pytest.raises(ClipError, match="no space left for the training cache") as err:
        ClipCache(clip, cache_dir=cache_dir).ensure(["lr/radiance"])
    assert "\n" not in str(err.value)
    assert not [p for p in cache_dir.rglob("*") if ".tmp" in p.name or p.suffix == ".npy"]
    assert main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(tmp_path / "run"), "--max-steps", "1",
                 *set_args(SMALL + [f'data.cache_dir="{cache_dir}"'])]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("blendsr: error: ") and "no space left" in err[-1]


def test_training_on_a_full_tmpfs_stops_with_one_line_not_sigbus(tmp_path):
    """A real small filesystem (a 1 MB tmpfs; needs root) holding the cache of a 1.8 MB array."""
    import subprocess
    import sys
    from tests.conftest import ENV, REPO
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("mounting a tmpfs is not permitted here (needs root); the monkeypatched test covers the logic")
    try:
        clip = make_synthetic_clip(tmp_path / "big", frames=range(1, 5), hr_size=(256, 144), scale=4,
                                   look=SyntheticLook(hr_supersample=1))
        proc = subprocess.run([sys.executable, "-m", "gbuffer_export.cli", "train", "--model", "fusesr",
                               "--data", str(clip), "-o", str(tmp_path / "run"), "--max-steps", "1",
                               *set_args(SMALL + [f'data.cache_dir="{mnt}"'])],
                              cwd=REPO, env=ENV, capture_output=True, text=True, timeout=300)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
        assert lines[-1].startswith("blendsr: error: ") and "no space left" in lines[-1], lines
        assert "Traceback" not in proc.stderr
        assert not [p for p in mnt.rglob("*") if ".tmp" in p.name]
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


# ------------------------------------------------------------------------------ issue 26: dataset index paths

def test_train_and_evaluate_refuse_an_index_path_outside_the_dataset(clip, tmp_path, capsys):
    import json
    import shutil
    from gbuffer_export.dataset.build import INDEX, SCHEMA
    outside = tmp_path / "outside_clip"
    shutil.copytree(clip, outside, ignore=shutil.ignore_patterns(".blendsr_cache"))
    ds = tmp_path / "ds" / "sub"
    ds.mkdir(parents=True)
    entries = [{"id": "evil", "path": "../../outside_clip", "split": s, "frames_planned": 3} for s in ("train", "test")]
    (ds / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": 1, "clips": entries}))
    assert main(["train", "--model", "fusesr", "--data", str(ds), "-o", str(tmp_path / "run"), "--max-steps", "1",
                 *set_args(SMALL)]) == 2
    assert main(["evaluate", "--model", "bicubic", "--data", str(ds), "--json", str(tmp_path / "e.json"),
                 "--no-flip"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(str(ds / INDEX) in e and "clip 'evil'" in e and "outside" in e for e in err), err
    assert not (outside / ".blendsr_cache").exists() and not (tmp_path / "e.json").exists()


def test_a_nan_loss_before_any_checkpoint_names_no_checkpoint(clip, tmp_path, monkeypatch):
    """Issue 26 item 12: the message must not name a last.pt that was never written."""
    from training.config import load_config
    from training.models.fusesr_l import FuseSRLight
    from training.train import TrainingError, train
    real = FuseSRLight.forward
    monkeypatch.setattr(FuseSRLight, "forward", lambda self, batch: real(self, batch) * float("nan"))
    cfg = load_config(None, SMALL + ["model.name=\"fusesr-l\"", "run.max_steps=3"])
    cfg.data.clips = [str(clip)]
    with pytest.raises(TrainingError) as err:
        train(cfg, tmp_path / "nan")
    assert "last.pt" not in str(err.value) and "no checkpoint was written" in str(err.value)
    assert not (tmp_path / "nan" / "checkpoints" / "last.pt").exists()


def test_the_progress_bar_of_a_minutes_run_counts_time_not_a_million_steps():
    """Issue 26 item 12: a --minutes run's bar counts the budget's seconds."""
    from training.config import load_config
    from training.hooks import progress_kwargs
    cfg = load_config(None, ["run.minutes=2"])
    assert progress_kwargs(cfg, 0) == {"total": 120, "initial": 0, "unit": "s"}
    cfg = load_config(None, ["run.max_steps=50"])
    assert progress_kwargs(cfg, 7) == {"total": 50, "initial": 7, "unit": "step"}


def test_a_clip_without_fbeta_names_the_missing_buffers_not_the_derived_one(tmp_path, capsys):
    """Issue 26 item 12: 'lr/irradiance' is computed from lr/radiance and lr/fbeta; the error names what is missing."""
    bare = make_synthetic_clip(tmp_path / "bare", frames=range(1, 3), hr_size=(64, 36), scale=4,
                               buffers=("radiance", "depth", "motion", "flags", "normal", "albedo", "roughness",
                                        "metallic", "emission"))
    assert main(["train", "--model", "fusesr", "--data", str(bare), "-o", str(tmp_path / "run"), "--max-steps", "1",
                 *set_args(SMALL)]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "'lr/fbeta'" in err and "from which 'lr/irradiance' is computed" in err, err


def test_bench_models_help_lists_each_compile_choice_once(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "models", "--help"])
    out = capsys.readouterr().out
    assert "{off,on,off,on}" not in out and "{off,on,both}" in out


def test_checkpoint_temporaries_of_a_dead_run_are_removed_by_the_next_save(tmp_path):
    """Issue 26 item 10: a run killed while saving leaves .last.pt.tmpPID; the next save removes it (a live
    process's temporary is kept)."""
    import subprocess
    from training.checkpoint import save_checkpoint
    dead = subprocess.Popen(["true"])
    dead.wait()
    d = tmp_path / "checkpoints"
    d.mkdir()
    stale = d / f".last.pt.tmp{dead.pid}"
    stale.write_bytes(b"half")
    live = d / f".step_00000002.pt.tmp{os.getppid()}"
    live.write_bytes(b"half")
    save_checkpoint(d / "last.pt", {"w": torch.zeros(3)})
    assert not stale.exists() and live.exists() and (d / "last.pt").is_file()
