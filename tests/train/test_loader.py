"""The loader benchmark runs and reports consistent numbers; training.commands.bench_loader/commands import no torch."""
import argparse
import json
import subprocess
import sys

import pytest

from gbuffer_export.synthetic import make_synthetic_clip



def test_bench_loader_reports_load_and_step_times(tmp_path):
    pytest.importorskip("torch")
    from training.commands import bench_loader
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 5), hr_size=(64, 36), scale=4)
    p = argparse.ArgumentParser()
    bench_loader.add_arguments(p)
    out = tmp_path / "bl.json"
    args = p.parse_args(["--data", str(clip), "--model", "fusesr-l", "--batch", "2", "--crop", "8",
                         "--batches", "3", "--steps", "1", "--threads", "1", "--json", str(out)])
    assert bench_loader.run(args) == 0
    res = json.loads(out.read_text())
    assert res["batch"] == 2 and res["crop_lr"] == 8 and res["load_ms_median"] > 0 and res["step_ms_median"] > 0
    assert res["ratio"] == pytest.approx(res["load_ms_median"] / res["step_ms_median"])


def test_bench_loader_refuses_clips_of_two_scales_and_a_crop_larger_than_a_frame(tmp_path):
    pytest.importorskip("torch")
    from gbuffer_export.errors import BlendSRError
    from training.commands import bench_loader
    x4 = make_synthetic_clip(tmp_path / "x4", frames=range(1, 3), hr_size=(64, 36), scale=4)
    x2 = make_synthetic_clip(tmp_path / "x2", frames=range(1, 3), hr_size=(64, 36), scale=2)
    p = argparse.ArgumentParser()
    bench_loader.add_arguments(p)
    with pytest.raises(BlendSRError, match=r"x2: scale 2 differs from .*x4's 4; benchmark clips of one scale"):
        bench_loader.run(p.parse_args(["--data", str(x4), str(x2), "--crop", "4", "--threads", "1"]))
    with pytest.raises(BlendSRError, match=r"x4: LR size 16x9 is smaller than --crop 12; pass --crop 9 or less"):
        bench_loader.run(p.parse_args(["--data", str(x4), "--crop", "12", "--threads", "1"]))


def test_command_modules_do_not_import_torch():
    code = ("import sys, argparse\n"
            "import training.commands.cli, training.commands.bench_loader, training.commands.bench_models, training.config\n"
            "import training.models, training.cache, training.data, training.augment\n"
            "p = argparse.ArgumentParser(); s = p.add_subparsers(); training.commands.cli.register(s)\n"
            "training.commands.bench_loader.add_arguments(argparse.ArgumentParser())\n"
            "training.commands.bench_models.add_arguments(argparse.ArgumentParser())\n"
            "assert 'torch' not in sys.modules, 'torch imported'\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_bench_loader_with_workers_reports_samples_per_second(tmp_path):
    pytest.importorskip("torch")
    from training.commands import bench_loader
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)
    p = argparse.ArgumentParser()
    bench_loader.add_arguments(p)
    out = tmp_path / "bl.json"
    args = p.parse_args(["--data", str(clip), "--model", "fusesr-fast", "--batch", "2", "--crop", "8",
                         "--batches", "4", "--steps", "1", "--threads", "1", "--workers", "2", "--json", str(out)])
    assert bench_loader.run(args) == 0
    res = json.loads(out.read_text())
    assert res["workers"] == 2 and res["device"] == "cpu" and res["loader_samples_per_s"] > 0
    assert res["step_samples_per_s"] == pytest.approx(2 / (res["step_ms_median"] / 1000))
    assert res["loader_over_step"] == pytest.approx(res["loader_samples_per_s"] / res["step_samples_per_s"])
