"""Issue 31, interface: Ray threads as the help says, frames of the built-in scene checked, commands write only
where asked, errors that name the flag or the option to use."""
from __future__ import annotations

import argparse
import os
import re

import pytest

from gbuffer_export.cli import main


# ------------------------------------------------------------------------------------------ Ray --threads 0
def test_threads_zero_is_one_per_ray_task_and_cores_over_workers_locally():
    from gbuffer_export.dataset.build import RunOptions
    assert RunOptions(executor="ray", threads=0, workers=4).clip_threads() == 1
    assert RunOptions(executor="ray", threads=3).clip_threads() == 3
    assert RunOptions(executor="local", threads=0, workers=2).clip_threads() == max(1, (os.cpu_count() or 1) // 2)
    assert RunOptions(executor="local", threads=5, workers=2).clip_threads() == 5


def test_dataset_help_says_what_threads_zero_does():
    from gbuffer_export.cli import build_parser
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    text = " ".join(sub.choices["dataset"].format_help().split())
    assert "0: this machine's cores / --workers locally, 1 on Ray" in text


# ---------------------------------------------------------------------------------- built-in scene frames
@pytest.mark.parametrize("frames", ["0:1", "1:100000", "-3:2"])
def test_frames_outside_the_builtin_scene_are_refused_in_one_line(frames, tmp_path, capsys):
    code = main(["render", "-o", str(tmp_path / "r"), f"--frames={frames}", "--hr-size", "64x36"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "outside the built-in scene's range 1:1000" in err[0]
    assert not (tmp_path / "r").exists()


def test_builtin_scene_range_edges_are_accepted_and_open_scenes_keep_theirs(tmp_path):
    from gbuffer_export.config import BUILTIN_SCENE_FRAMES, ConfigError, RenderConfig, check_builtin_frames
    lo, hi = BUILTIN_SCENE_FRAMES
    check_builtin_frames((lo, lo))
    check_builtin_frames((hi - 1, hi))
    check_builtin_frames(None)
    with pytest.raises(ConfigError, match="outside the built-in scene's range"):
        check_builtin_frames((hi, hi + 1))
    # scene=None also stands for a scene already open (the add-on, dataset jobs): its own range is not checked here
    assert RenderConfig(output=tmp_path / "a", frames=(0, 2500)).frames == (0, 2500)


# --------------------------------------------------------------------------------- writing where asked
def test_bench_brdf_rewrites_no_docs_by_default():
    from gbuffer_export.commands import bench_brdf
    p = argparse.ArgumentParser()
    bench_brdf.add_arguments(p)
    assert p.parse_args([]).docs is None
    assert str(p.parse_args(["--docs", "docs/brdf.md"]).docs) == "docs/brdf.md"


@pytest.mark.torch
def test_bench_models_without_output_writes_nothing(tmp_path, monkeypatch, capsys):
    pytest.importorskip("torch")
    monkeypatch.chdir(tmp_path)
    assert main(["bench", "models", "--models", "nosuchmodel"]) == 2
    assert main(["bench", "models", "--models", "bilinear", "--size", "64x36", "--repeats", "1",
                 "--warmup", "0", "--device", "cpu", "--peak-tflops", "1", "--bandwidth-gbs", "1"]) == 0
    assert "bilinear" in capsys.readouterr().out
    assert list(tmp_path.iterdir()) == [], "nothing written without -o"
    assert main(["bench", "models", "--models", "bilinear", "--size", "64x36", "--repeats", "1", "--warmup", "0",
                 "--device", "cpu", "--peak-tflops", "1", "--bandwidth-gbs", "1", "-o", "b"]) == 0
    assert (tmp_path / "b" / "bench_speed.json").is_file()


# ---------------------------------------------------------------------------- errors naming what to use
@pytest.mark.torch
def test_device_cuda_without_a_gpu_names_the_flag():
    torch = pytest.importorskip("torch")
    if torch.cuda.is_available():
        pytest.skip("a CUDA device is available")
    from gbuffer_export.config import ConfigError
    from training.device import resolve_device
    with pytest.raises(ConfigError, match=r"^--device cuda: no CUDA device"):
        resolve_device("cuda")
    with pytest.raises(ConfigError, match=r"^run.device cuda: no CUDA device"):
        resolve_device("cuda", "run.device")


@pytest.mark.torch
def test_nsrr_fec_on_default_clips_names_for_models(tmp_path, capsys):
    pytest.importorskip("torch")
    from gbuffer_export.conventions import DEFAULT_BUFFERS
    from gbuffer_export.synthetic import make_synthetic_clip
    assert "metallic" not in DEFAULT_BUFFERS
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), buffers=DEFAULT_BUFFERS)
    code = main(["train", "--model", "nsrr-fec", "--data", str(clip), "-o", str(tmp_path / "run"),
                 "--max-steps", "1", "--set", "data.val_frames=0", "--set", "data.window=2",
                 "--set", "data.crop=8", "--set", "data.batch_size=1"])
    err = capsys.readouterr().err
    assert code == 2, err[-2000:]
    assert "--for-models nsrr-fec" in err.strip().splitlines()[-1]


# ------------------------------------------------------------------------------- Cycles' device warnings
PROBE = """
import bpy
from gbuffer_export.blender.devices import probe_devices
if {probe}:
    probe_devices()
bpy.context.preferences.addons["cycles"].preferences.get_devices()
"""


@pytest.mark.bpy
def test_cycles_gpu_library_warnings_never_reach_the_progress_bar():
    """Cycles logs 'CUEW initialization failed' on stdout the first time it enumerates devices; the render probes
    once before its progress bar, with the absent-GPU-library warnings dropped, and Cycles does not log them again."""
    import subprocess
    import sys

    from tests.conftest import HAVE_BPY, REPO
    if not HAVE_BPY:
        pytest.skip("bpy is not installed")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    plain = subprocess.run([sys.executable, "-c", PROBE.format(probe=False)], capture_output=True, text=True,
                           env=env, timeout=120)
    probed = subprocess.run([sys.executable, "-c", PROBE.format(probe=True)], capture_output=True, text=True,
                            env=env, timeout=120)
    assert probed.returncode == 0, probed.stderr[-2000:]
    assert "initialization failed" not in probed.stdout + probed.stderr
    if "initialization failed" not in plain.stdout + plain.stderr:
        pytest.skip("Cycles found every GPU library here (nothing to drop)")
    from gbuffer_export.blender.devices import ABSENT_GPU_LIBRARY
    assert all(ABSENT_GPU_LIBRARY.search(ln) for ln in (plain.stdout + plain.stderr).splitlines()
               if "initialization failed" in ln)


@pytest.mark.torch
def test_export_of_a_fixed_scale_baseline_matches(tmp_path, capsys):
    """bicubic's graph never reads its 'scale' input; the exporter drops it and the check feeds only the graph's
    inputs (it failed with 'Invalid input name: scale')."""
    pytest.importorskip("onnxruntime")
    assert main(["export", "--model", "bicubic", "--onnx", str(tmp_path / "b.onnx"), "--hr-size", "32x16"]) == 0
    import json
    report = json.loads((tmp_path / "b.onnx.json").read_text())
    assert report["match"] and "scale" not in report["inputs"]


# ---------------------------------------------------------------------------------------- progress
@pytest.mark.torch
def test_upscale_evaluate_and_bench_models_show_progress_unless_told(tmp_path, capsys):
    """Progress bars on stderr (not only in a terminal), per frame of each clip and model; --no-progress: none."""
    pytest.importorskip("torch")
    from gbuffer_export.synthetic import make_synthetic_clip
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36))
    runs = {"upscale": ["upscale", "--model", "bilinear", "--clip", str(clip), "-o", str(tmp_path / "u")],
            "evaluate": ["evaluate", "--model", "bilinear", "--data", str(clip), "--json", str(tmp_path / "e.json"),
                         "--no-flip", "--warmup", "0"],
            "bench": ["bench", "models", "--models", "bilinear", "--data", str(clip), "--warmup", "0",
                      "--peak-tflops", "1", "--bandwidth-gbs", "1"]}
    for name, args in runs.items():
        assert main(args) == 0, name
        err = capsys.readouterr().err
        assert re.search(r"[0-3]/3 \[", err) and "frame" in err, (name, err[-500:])
        assert main([*args, "--no-progress"]) == 0, name
        assert not re.search(r"[0-3]/3 \[", capsys.readouterr().err), name



# ------------------------------------------------------------------------------------------ -q / -v (logging)
def test_quiet_hides_an_info_note_and_verbose_shows_a_debug_note(tmp_path, monkeypatch, capsys):
    """The library's notes are log records on stderr: INFO by default and hidden by -q, DEBUG only with -v."""
    import gbuffer_export.commands.lut as lut
    from gbuffer_export.brdf_common import load_or_generate_file
    real_run = lut.run

    def run_with_a_cold_cache(args):  # a table missing from the cache: the library notes it at INFO
        load_or_generate_file(tmp_path / "table.exr", None, lambda: 1, lambda path, value: None, ())
        return real_run(args)
    monkeypatch.setattr(lut, "run", run_with_a_cold_cache)

    def stderr_of(*flags):
        assert main([*flags, "lut", "-o", str(tmp_path / "l.exr"), "--size", "4", "--samples", "16"]) == 0
        return capsys.readouterr().err

    default = stderr_of()
    assert "computing table.exr (cached for later runs)" in default and "split-sum table" not in default
    assert "computing table.exr" not in stderr_of("-q")
    verbose = stderr_of("-v")
    assert "split-sum table: 4x4 texels, 16 samples each" in verbose and "computing table.exr" in verbose
    assert "split-sum table" not in stderr_of("--quiet")


def test_output_cut_short_by_a_closed_pipe_stops_quietly(tmp_path):
    """``blendsr dataset SPEC --dry-run | head -1``: no traceback, no 'internal error', exit 141 as a shell's."""
    import subprocess
    import sys
    from tests.conftest import ENV, REPO, builtin_spec
    spec = builtin_spec(tmp_path / "spec.toml", seeds="0:199")
    proc = subprocess.Popen([sys.executable, "-m", "gbuffer_export.cli", "dataset", str(spec),
                             "-o", "unused", "--dry-run"], cwd=REPO, env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    proc.stdout.close()  # before the command prints its first line (it starts Python and expands the spec first)
    err = proc.stderr.read()
    assert proc.wait(timeout=60) == 141, err
    assert "Traceback" not in err and "internal error" not in err, err
