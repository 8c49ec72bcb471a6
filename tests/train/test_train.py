"""Training: a few steps through the CLI, bit-identical resume, NaN stops, losses, perceptual weights file."""
import csv
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)  # 2 threads on a shared 2-core machine can be 10x slower

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training.config import config_from_checkpoint, load_config  # noqa: E402
from training.checkpoint import load_checkpoint  # noqa: E402
from training.train import TrainingError, train  # noqa: E402
from tests.conftest import set_args  # noqa: E402


SMALL = ["data.crop=8", "data.batch_size=2", "model.width=16", "model.blocks=1", "run.progress=false",
         "run.log_every=1", "run.amp=\"none\"", "run.threads=0"]


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 6), hr_size=(64, 36), scale=4)


def test_train_cli_writes_config_log_checkpoint_and_summary(clip, tmp_path):
    run = tmp_path / "run"
    rc = main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(run), "--max-steps", "3",
               *set_args(SMALL + ["run.checkpoint_every=2", "loss.temporal_weight=0.5", "loss.fft_weight=0.1",
                               "loss.pixel=\"charbonnier\""])])
    assert rc == 0
    cfg = load_config(run / "config.toml")
    # the user's configuration (model.scale 0: the clips' scale), the derived scale in its header comment
    assert cfg.model.name == "fusesr" and cfg.model.scale == 0 and cfg.data.clips == [str(clip)]
    assert "model.scale = 4 (LR levels 4)" in (run / "config.toml").read_text()
    rows = list(csv.DictReader(open(run / "log.csv")))
    assert [int(r["step"]) for r in rows] == [1, 2, 3]
    for r in rows:
        for k in ("loss", "pixel", "ssim", "fft", "temporal"):
            assert np.isfinite(float(r[k])), k
        total = float(r["pixel"]) + 0.05 * float(r["ssim"]) + 0.1 * float(r["fft"]) + 0.5 * float(r["temporal"])
        assert float(r["loss"]) == pytest.approx(total, rel=1e-5)
    ck = load_checkpoint(run / "checkpoints" / "last.pt")
    assert ck["step"] == 3 and ck["model_name"] == "fusesr" and ck["scale"] == 4
    assert {"torch", "numpy", "python"} <= set(ck["rng"]) and ck["sampler"]["seed"] == 0
    assert ck["data"][0]["manifest_sha256"] and {"model", "optimizer", "scheduler", "config"} <= set(ck)
    assert (run / "checkpoints" / "step_00000002.pt").is_file()
    summary = json.loads((run / "summary.json").read_text())
    assert summary["step"] == 3 and summary["stopped_by"] == "max_steps" and summary["params"] > 0
    # an existing run is not overwritten without --resume
    assert main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(run), "--max-steps", "3"]) == 2


def test_resume_is_bit_identical(clip, tmp_path):
    over = SMALL + ["optim.decay_steps=4", "run.max_steps=4", "run.checkpoint_every=100", "data.prefetch=1"]
    straight = tmp_path / "straight"
    cfg = load_config(None, over + ["model.name=\"fusesr\""])
    cfg.data.clips = [str(clip)]
    train(cfg, straight)
    split = tmp_path / "split"
    cfg2 = load_config(None, over + ["model.name=\"fusesr\""])
    cfg2.data.clips = [str(clip)]
    s1 = train(cfg2, split, stop_at=2)
    assert s1["step"] == 2 and s1["stopped_by"] == "stop_at"
    # a log begun by an older version (no 'baseline' column) keeps its columns when the run resumes
    old = list(csv.reader(open(split / "log.csv")))
    drop = old[0].index("baseline")
    (split / "log.csv").write_text("".join(",".join(r[:drop] + r[drop + 1:]) + "\n" for r in old))
    # a step logged after the last checkpoint (the run was killed there) is run and logged again, once
    with open(split / "log.csv", "a") as f:
        f.write(",".join(["3"] + ["9"] * (len(old[0]) - 2)) + "\n")
    half = load_checkpoint(split / "checkpoints" / "last.pt")
    assert half["step"] == 2
    assert main(["train", "-o", str(split), "--resume"]) == 0
    a = load_checkpoint(straight / "checkpoints" / "last.pt")
    b = load_checkpoint(split / "checkpoints" / "last.pt")
    assert a["step"] == b["step"] == 4
    for k, v in a["model"].items():
        assert torch.equal(v, b["model"][k]), k
    assert not torch.equal(half["model"]["head.weight"], a["model"]["head.weight"])
    sa, sb = a["optimizer"]["state"], b["optimizer"]["state"]
    for i in sa:
        assert torch.equal(sa[i]["exp_avg_sq"], sb[i]["exp_avg_sq"])
    rows = list(csv.DictReader(open(split / "log.csv")))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4]
    assert "baseline" not in rows[0] and all(None not in r and float(r["lr"]) > 0 for r in rows)
    # a changed configuration is refused on resume
    assert main(["train", "-o", str(split), "--resume", "--max-steps", "5", "--set", "data.crop=12"]) == 2


def test_nonfinite_loss_stops_training_and_names_the_batch(clip, tmp_path, monkeypatch):
    from training.models.fusesr_l import FuseSRLight
    real = FuseSRLight.forward
    calls = {"n": 0}

    def poisoned(self, batch):
        calls["n"] += 1
        out = real(self, batch)
        return out * float("nan") if calls["n"] == 2 else out
    monkeypatch.setattr(FuseSRLight, "forward", poisoned)
    cfg = load_config(None, SMALL + ["model.name=\"fusesr-l\"", "run.max_steps=5"])
    cfg.data.clips = [str(clip)]
    with pytest.raises(TrainingError) as err:
        train(cfg, tmp_path / "nan")
    msg = str(err.value)
    assert "step 2" in msg and "model output" in msg and str(clip) in msg and "frames" in msg
    assert not (tmp_path / "nan" / "checkpoints" / "last.pt").exists()  # nothing after the bad step


def test_perceptual_loss_needs_a_user_file_and_uses_it(clip, tmp_path, monkeypatch):
    from training import perceptual
    from training.checkpoint import file_sha256
    from training.perceptual import VGGFeatures, vgg16_features
    assert main(["train", "--model", "fusesr-l", "--data", str(clip), "-o", str(tmp_path / "r0"),
                 "--set", "loss.perceptual_weight=0.5"]) == 2
    torch.manual_seed(0)
    weights = tmp_path / "vgg16.pt"  # random weights in place of torchvision's (tests/train/test_perceptual.py)
    torch.save({f"features.{k}": v for k, v in vgg16_features().state_dict().items()}, weights)
    monkeypatch.setattr(perceptual, "VGG16_SHA256", file_sha256(weights))
    v = VGGFeatures.from_file(weights)
    a = torch.rand(1, 3, 32, 32)
    assert float(v.distance(a, a)) == 0.0 and float(v.distance(a, a.flip(-1))) > 0
    bad = tmp_path / "bad.pt"
    torch.save({"x": torch.zeros(1)}, bad)
    with pytest.raises(ValueError, match="is not that of vgg16-397923af.pth"):
        VGGFeatures.from_file(bad)
    monkeypatch.setattr(perceptual, "VGG16_SHA256", file_sha256(bad))
    with pytest.raises(ValueError, match="not a VGG-16"):
        VGGFeatures.from_file(bad)
    monkeypatch.setattr(perceptual, "VGG16_SHA256", file_sha256(weights))
    run = tmp_path / "r1"
    assert main(["train", "--model", "fusesr-l", "--data", str(clip), "-o", str(run), "--max-steps", "1",
                 *set_args(SMALL + ["loss.perceptual_weight=0.5", f"loss.vgg_weights=\"{weights}\""])]) == 0
    row = next(csv.DictReader(open(run / "log.csv")))
    assert float(row["perceptual"]) > 0


def test_untrainable_model_and_missing_data_are_usage_errors(clip, tmp_path):
    assert main(["train", "--model", "bicubic", "--data", str(clip), "-o", str(tmp_path / "a")]) == 2
    assert main(["train", "--model", "fusesr", "-o", str(tmp_path / "b")]) == 2
    assert main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(tmp_path / "c"),
                 "--set", "data.crop=0"]) == 2  # a crop too large for LR 16x9 shrinks with a note (crop rule)


def test_bf16_autocast_step_on_cpu(clip, tmp_path):
    over = [s for s in SMALL if not s.startswith("run.amp")] + ["model.name=\"fusesr-l\"", "run.max_steps=2",
                                                               "run.amp=\"bf16\""]
    cfg = load_config(None, over)
    cfg.data.clips = [str(clip)]
    s = train(cfg, tmp_path / "bf16")
    assert s["amp"] == "bfloat16" and s["step"] == 2
    rows = list(csv.DictReader(open(tmp_path / "bf16" / "log.csv")))
    assert all(np.isfinite(float(r["loss"])) for r in rows)


def test_max_steps_and_minutes_combine_whichever_comes_first(clip, tmp_path, caplog):
    caplog.set_level("INFO", logger="training")
    run = tmp_path / "run"
    rc = main(["train", "--model", "fusesr-l", "--data", str(clip), "-o", str(run), "--max-steps", "2",
               "--minutes", "30", *set_args(SMALL)])
    assert rc == 0
    cfg = load_config(run / "config.toml")
    assert cfg.run.max_steps == 2 and cfg.run.minutes == 30
    assert json.loads((run / "summary.json").read_text())["stopped_by"] == "max_steps"
    assert "cosine schedule decays over 2 steps" in caplog.text


def test_checkpoints_that_predate_jitter_and_norm_load_with_their_old_behaviour(clip, tmp_path):
    import torch
    from training.inference.loading import load_model
    run = tmp_path / "run"
    assert main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(run), "--max-steps", "1",
                 *set_args(SMALL + ["model.norm=\"batch\"", "model.jitter=false"])]) == 0
    ck = load_checkpoint(run / "checkpoints" / "last.pt")
    model = ck["config"]["model"]
    from training.config import LEGACY_FLAT_KEYS  # the flat [model] table of checkpoints before per-model tables,
    model.update({k: v for k, v in model.pop("fusesr").items() if k in LEGACY_FLAT_KEYS})  # which predate later keys
    for key in ("jitter", "norm", "remod_filter", "remod_filter_px", "upsample_by_class", "guided_upsample"):
        del model[key]
    del ck["config"]["data"]["reflectance_range"]
    old = tmp_path / "old.pt"
    torch.save(ck, old)
    model = load_model(str(old), 4, fast=False).module  # fast=True folds the BatchNorm layers into the convolutions
    assert not model.use_jitter and "lr_jitter" not in model.needs()
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())
    assert model.remod_kernel is None  # remodulated without the ground truth's pixel filter, as before session 3
    assert not model.by_class and not model.guided  # plain bilinear residual base, as before sessions 4 and 5
    assert config_from_checkpoint(ck["config"]).data.reflectance_range == [1.0, 1.0]  # no tint before session 3


def test_training_refuses_a_remodulation_filter_other_than_the_ground_truths(clip, tmp_path, capsys):
    code = main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(tmp_path / "run"), "--max-steps", "1",
                 *set_args(SMALL + ['model.remod_filter="BLACKMAN_HARRIS"', "model.remod_filter_px=2.0"])])
    err = capsys.readouterr().err
    assert code != 0 and f"{clip}: the ground truth was rendered with the BOX 1 px pixel filter" in err
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_reference_filter_is_resolved_from_the_clips_into_the_checkpoint(clip, tmp_path):
    run = tmp_path / "run"
    assert main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(run), "--max-steps", "1",
                 *set_args(SMALL)]) == 0
    saved = load_checkpoint(run / "checkpoints" / "last.pt")["config"]["model"]
    assert (saved["remod_filter"], saved["remod_filter_px"]) == ("BOX", 1.0)  # the synthetic clip's 2x2 supersampling


def test_ema_weights_are_the_moving_average_and_resume_bit_identically(clip, tmp_path):
    """optim.ema_decay: the checkpoint's ema_model equals the average recomputed from every step's trained
    weights; resume keeps it bit-identical; inference and release use it."""
    d = 0.75
    over = SMALL + ["optim.decay_steps=4", "run.max_steps=4", "run.checkpoint_every=1", "run.keep_checkpoints=10",
                    "data.prefetch=1", f"optim.ema_decay={d}", "model.name=\"fusesr\""]
    straight = tmp_path / "straight"
    cfg = load_config(None, over)
    cfg.data.clips = [str(clip)]
    summary = train(cfg, straight)
    assert summary["weights"] == "ema"
    steps = [load_checkpoint(straight / "checkpoints" / f"step_{k:08d}.pt") for k in range(1, 5)]
    last = load_checkpoint(straight / "checkpoints" / "last.pt")
    assert last["ema_updates"] == 4
    for name, v in last["ema_model"].items():
        if not v.is_floating_point():
            continue
        expect = steps[0]["model"][name].double()
        for ck in steps[1:]:
            expect = d * expect + (1 - d) * ck["model"][name].double()
        assert torch.allclose(v.double(), expect, rtol=1e-5, atol=1e-6), name
    assert not torch.equal(last["ema_model"]["head.weight"], last["model"]["head.weight"])
    # interrupted at step 2 and resumed: the same average, bit for bit
    split = tmp_path / "split"
    cfg2 = load_config(None, over)
    cfg2.data.clips = [str(clip)]
    train(cfg2, split, stop_at=2)
    assert main(["train", "-o", str(split), "--resume"]) == 0
    b = load_checkpoint(split / "checkpoints" / "last.pt")
    for k, v in last["ema_model"].items():
        assert torch.equal(v, b["ema_model"][k]), k
    # what inference and the shipped-weights writer read
    from training.inference.loading import load_model
    model = load_model(str(straight / "checkpoints" / "last.pt"), 4)
    for k, v in model.module.state_dict().items():
        assert torch.equal(v, last["ema_model"][k]), k
    from training.release import release
    release(straight / "checkpoints" / "last.pt", tmp_path / "w.safetensors", {})
    slim = load_checkpoint(tmp_path / "w.safetensors")
    assert torch.equal(slim["model"]["head.weight"], last["ema_model"]["head.weight"].half())


def test_ema_decay_out_of_range_is_refused():
    from gbuffer_export.config import ConfigError
    with pytest.raises(ConfigError, match="optim.ema_decay"):
        load_config(None, ["optim.ema_decay=1.0", "model.name=\"fusesr\""])


def test_window_on_a_feed_forward_model_names_every_recurrent_model(clip, tmp_path, capsys):
    """The list comes from the model classes (recurrent = True), not from a list kept by hand."""
    assert main(["train", "--model", "fusesr", "--data", str(clip), "-o", str(tmp_path / "r"), "--max-steps", "1",
                 *set_args(SMALL + ["data.window=3"])]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "(rdg, rdg-s, nsrd, nsrr-fec, fourier-sr), not 'fusesr'" in err[0], err


def test_the_users_configuration_is_never_rewritten_and_the_resolved_run_round_trips(clip, tmp_path):
    from training.run import ResolvedRun, open_clips, resolve_run
    cfg = load_config(None, SMALL + ["model.name=\"fusesr\"", "run.max_steps=1", "data.crop=64"])
    cfg.data.clips = [str(clip)]
    before = cfg.to_dict()
    train(cfg, tmp_path / "run")
    assert cfg.to_dict() == before  # crop 64, model.scale 0 and remod_filter REFERENCE stay as given
    run = resolve_run(cfg, open_clips(cfg.data.clips))
    assert (run.crop, run.scale, run.window, run.remod_filter) == (9, 4, 0, ("BOX", 1.0))
    ck = load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")
    assert ResolvedRun.from_dict(ck["resolved"]) == run and ck["user_config"] == before
    other = ResolvedRun.from_dict({**run.to_dict(), "crop": 8})
    assert other.differs(run) == "crop 9 -> 8" and run.differs(run) is None


def test_a_resumed_log_drops_the_rows_after_its_checkpoint_and_a_torn_last_row(tmp_path):
    from training.hooks import drop_rows_after
    log = tmp_path / "log.csv"
    log.write_text("step,loss\n10,0.5\n20,0.4\n30,0.3\n")
    assert drop_rows_after(log, 20) == ["step", "loss"]
    assert log.read_text() == "step,loss\n10,0.5\n20,0.4\n"
    log.write_text("step,loss\n10,0.5\n20,0.")  # killed while writing its last row
    drop_rows_after(log, 20)
    assert log.read_text() == "step,loss\n10,0.5\n"
    log.write_text("step,loss\n10,0.5\n")
    before = log.stat().st_mtime_ns
    drop_rows_after(log, 20)  # nothing to drop: not rewritten
    assert log.read_text() == "step,loss\n10,0.5\n" and log.stat().st_mtime_ns == before
