"""Scale-aware training on clips with several LR levels: SCALES declarations, aligned crops for non-integer scales,
mixed-scale batches, refusals, evaluation per scale."""
import csv
import dataclasses
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training.cache import ClipCache  # noqa: E402
from training.config import ConfigError, ModelConfig, config_from_checkpoint, load_config  # noqa: E402
from training.data import BatchSpec, TrainSampler, crop_grid  # noqa: E402
from training.evaluate import EvalOptions, evaluate_model  # noqa: E402
from training.inference.loading import load_model  # noqa: E402
from training.models import MODELS, ModelInfo, build_model  # noqa: E402
from training.models.resample import upsample  # noqa: E402
from training.checkpoint import load_checkpoint  # noqa: E402
from training.train import train  # noqa: E402

SCALES = (2, 2.5, 4)
SMALL = ["data.batch_size=2", "run.progress=false", "run.log_every=1", "run.amp=\"none\"", "run.threads=0",
         "model.width=16", "model.blocks=1"]


@pytest.fixture(scope="module")
def multi(tmp_path_factory):
    """80x40 HR; LR levels 40x20 (x2, 'lr'), 32x16 (x2.5), 20x10 (x4); jittered."""
    return make_synthetic_clip(tmp_path_factory.mktemp("multi") / "c", frames=range(1, 6), hr_size=(80, 40),
                               scales=SCALES, jitter=True)


@pytest.fixture
def tiny_model(monkeypatch):
    """A learned test-only model that takes any scale (tests/tiny_any_scale.py), registered for the test."""
    from tests import tiny_any_scale
    monkeypatch.setitem(MODELS, "tiny-any", ModelInfo("tests.tiny_any_scale", "TinyAnyScale", True, "test only"))
    tiny_any_scale.TinyAnyScale.seen = []
    return tiny_any_scale.TinyAnyScale


# ------------------------------------------------------------------------------------------- declarations

def test_models_declare_their_scales():
    with pytest.raises(ValueError, match="scale 2.5: model fusesr supports 2, 4 and 8"):
        build_model(ModelConfig(name="fusesr"), 2.5)
    with pytest.raises(ValueError, match="supports 2, 4 and 8"):
        build_model(ModelConfig(name="demod-bilinear"), 3)
    m = build_model(ModelConfig(name="bilinear"), 2.5)
    assert type(m).SCALES is None and m.scale == 2.5
    assert build_model(ModelConfig(name="fusesr"), 4).scale == 4
    with pytest.raises(ValueError):
        build_model(ModelConfig(name="bilinear"), 0.5)


@pytest.mark.parametrize("scale,jit", [(2.5, (0.0, 0.0)), (2.5, (0.3, -0.2)), (1.6, (0.1, 0.4)), (4, (0.25, 0.1))])
def test_upsample_at_non_integer_scales_is_exact_on_a_ramp(scale, jit):
    """Bilinear upsampling reproduces a linear function: the HR pixel centre u = (j + 0.5) / s (LR pixels) gets
    the ramp's value at u - jitter, where LR pixel centre p holds the ramp at p + jitter (away from the border)."""
    h, w = 10, 20
    d = torch.float64
    ys, xs = torch.meshgrid(torch.arange(h, dtype=d) + 0.5, torch.arange(w, dtype=d) + 0.5, indexing="ij")
    j = torch.tensor([jit], dtype=torch.float64)

    def ramp(x, y):
        return 0.7 * x - 1.3 * y + 2.0
    lr = ramp(xs + jit[0], ys + jit[1])[None, None]
    hr = upsample(lr, scale, "bilinear", j if any(jit) else None)
    hh, ww = round(h * scale), round(w * scale)
    assert hr.shape == (1, 1, hh, ww)
    uy, ux = torch.meshgrid((torch.arange(hh, dtype=d) + 0.5) / scale, (torch.arange(ww, dtype=d) + 0.5) / scale,
                            indexing="ij")
    inner = (ux > 1.5) & (ux < w - 1.5) & (uy > 1.5) & (uy < h - 1.5)
    assert torch.allclose(hr[0, 0][inner], ramp(ux, uy)[inner], atol=1e-9)


# ------------------------------------------------------------------------------------------- batches

def test_crop_grid():
    assert crop_grid(4, 9) == (1, 9) and crop_grid(2.5, 9) == (2, 8) and crop_grid(3.75, 9) == (4, 8)
    assert crop_grid(1.6, 12) == (5, 10)


def test_mixed_scale_batches_are_aligned(multi):
    caches = [ClipCache(multi, scale=s).ensure(["lr/radiance", "hr/radiance", "lr/depth", "hr/depth"])
              for s in SCALES]
    assert [c.sizes["lr"] for c in caches] == [(40, 20), (32, 16), (20, 10)]
    assert {p.name for p in caches[0].path.glob("*.npy")} >= {"lr__radiance.npy", "lr_x2.5__radiance.npy",
                                                               "lr_x4__radiance.npy", "hr__radiance.npy"}
    spec = BatchSpec(lr_keys=("lr/radiance", "lr/depth"), hr_keys=("hr/radiance", "hr/depth"), lr_window=1,
                     hr_window=1, crop=7, depth_ref=True, jitter=True)
    sampler = TrainSampler(caches, spec, batch_size=3, seed=5)
    seen = set()
    for step in range(30):
        batch, samples = sampler.batch(step)
        s = float(batch["scale"][0])
        seen.add(s)
        assert batch["scale"].shape == (3,) and np.all(batch["scale"] == s) and batch["scale"].dtype == np.float32
        q, c = crop_grid(s, 7)
        assert batch["lr/radiance"].shape == (3, 1, 3, c, c)
        assert batch["hr/radiance"].shape[-2:] == (round(s * c), round(s * c)) and s * c == round(s * c)
        ci = SCALES.index(s if s != 2.5 else 2.5)
        cache = caches[ci]
        for b, smp in enumerate(samples):
            assert smp.x0 % q == 0 and smp.y0 % q == 0
            assert (s * smp.x0).is_integer() and (s * smp.y0).is_integer()
            row = cache.index_of[smp.frames[-1]]
            hx, hy, hc = int(s * smp.x0), int(s * smp.y0), int(s * c)
            ref_hr = np.asarray(cache.array("hr/depth")[row, hy:hy + hc, hx:hx + hc]).transpose(2, 0, 1)
            ref_lr = np.asarray(cache.array("lr/depth")[row, smp.y0:smp.y0 + c, smp.x0:smp.x0 + c]).transpose(2, 0, 1)
            assert np.array_equal(batch["hr/depth"][b, 0], ref_hr) and np.array_equal(batch["lr/depth"][b, 0], ref_lr)
            assert np.allclose(batch["lr_jitter"][b, 0], cache.jitter(smp.frames[-1]))
    assert seen == {2.0, 2.5, 4.0}
    again, _ = sampler.batch(7)
    first, _ = sampler.batch(7)
    assert all(np.array_equal(again[k], first[k]) for k in first)


def test_single_scale_batches_unchanged(tmp_path):
    """A one-level clip: batch k is what it was before scales existed (no extra random draw), plus 'scale'."""
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)
    cache = ClipCache(clip).ensure(["lr/radiance", "hr/radiance"])
    spec = BatchSpec(lr_keys=("lr/radiance",), hr_keys=("hr/radiance",), lr_window=1, hr_window=1, crop=5,
                     depth_ref=False)
    batch, samples = TrainSampler([cache], spec, batch_size=2, seed=3).batch(4)
    rng = np.random.default_rng([3, 0, 4])
    i = int(rng.integers(3))
    y0, x0 = int(rng.integers(9 - 5 + 1)), int(rng.integers(16 - 5 + 1))
    assert (samples[0].x0, samples[0].y0, samples[0].frames) == (x0, y0, [cache.frames[i]])
    assert batch["scale"].tolist() == [4.0, 4.0] and batch["hr/radiance"].shape == (2, 1, 3, 20, 20)


# ------------------------------------------------------------------------------------------- training

def test_any_scale_model_trains_on_a_mix_of_scales(multi, tmp_path, tiny_model):
    cfg = load_config(None, SMALL + ["model.name=\"tiny-any\"", "data.crop=6", "run.max_steps=8",
                                     "data.val_frames=1", "run.eval_every=8"])
    cfg.data.clips = [str(multi)]
    summary = train(cfg, tmp_path / "run")
    assert summary["scales"] == [2.0, 2.5, 4.0]
    assert set(tiny_model.seen) >= {2.0, 2.5, 4.0}  # training batches of every scale, and validation at each
    ck = load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")
    assert ck["scales"] == [2.0, 2.5, 4.0]
    val = json.loads((tmp_path / "run" / "val.json").read_text())
    assert set(val["per_scale"]) == {"2", "2.5", "4"}
    assert {r["scale"] for r in val["per_frame"]} == {2.0, 2.5, 4.0}
    # the checkpoint loads at any scale and is evaluated at every level of the clip
    model = load_model(str(tmp_path / "run" / "checkpoints" / "last.pt"), 2)
    res = evaluate_model(model, [str(multi)], EvalOptions(flip=False, warmup=0))
    assert set(res["per_scale"]) == {"2", "2.5", "4"} and res["mean"]["frames"] == 15


def test_the_baseline_loss_follows_each_batchs_scale(tmp_path, tiny_model, monkeypatch):
    """Each batch's baseline is demod-jbu at that batch's scale: its SR equals a fresh demod-jbu's at that scale
    (with the run's effective shared model keys)."""
    from training.trainer import Trainer
    seen, baseline_sr = [], Trainer.baseline_sr

    def recorded(self, batch):
        out = baseline_sr(self, batch)
        seen.append((float(batch["scale"].reshape(-1)[0]), out.clone(), {k: v.clone() for k, v in batch.items()
                                                                  if torch.is_tensor(v)}))
        return out

    monkeypatch.setattr(Trainer, "baseline_sr", recorded)
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(80, 40), scales=(2, 4), jitter=True)
    cfg = load_config(None, SMALL + ["model.name=\"tiny-any\"", "data.crop=6", "run.max_steps=8",
                                     "loss.baseline_weight=1.0"])
    cfg.data.clips = [str(clip)]
    assert train(cfg, tmp_path / "run")["scales"] == [2.0, 4.0]
    assert set(tiny_model.seen) >= {2.0, 4.0}  # batches of both scales, each against demod-jbu at its scale
    assert {s for s, _, _ in seen} == {2.0, 4.0}
    # the run's effective shared model keys (model.remod_filter resolved from the clip's ground truth)
    effective = config_from_checkpoint(load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")["config"])
    for scale, out, batch in seen:
        with torch.no_grad():
            jbu = build_model(dataclasses.replace(effective.model, name="demod-jbu", options=None), scale).eval()
            want = jbu(batch).float()
        assert out.shape == want.shape and torch.allclose(out, want, rtol=1e-5, atol=1e-6), scale
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    assert len(rows) == 8 and all(float(r["baseline"]) >= 0 for r in rows)
    assert any(float(r["baseline"]) > 0 for r in rows)


def test_the_baseline_loss_refuses_a_scale_its_baseline_cannot_take(multi, tmp_path, tiny_model):
    cfg = load_config(None, SMALL + ["model.name=\"tiny-any\"", "data.crop=6", "run.max_steps=1",
                                     "loss.baseline_weight=1.0"])
    cfg.data.clips = [str(multi)]
    with pytest.raises(ConfigError, match="trains at scale 2.5 and its baseline demod-jbu takes 2, 4 and 8"):
        train(cfg, tmp_path / "run")
    assert not (tmp_path / "run" / "checkpoints" / "last.pt").exists()


def test_integer_model_trains_on_one_level_of_a_multi_level_clip(multi, tmp_path):
    cfg = load_config(None, SMALL + ["model.name=\"fusesr-l\"", "model.scale=4", "data.crop=6", "run.max_steps=2"])
    cfg.data.clips = [str(multi)]
    summary = train(cfg, tmp_path / "run")
    assert summary["scales"] == [4.0] and load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")["scale"] == 4


@pytest.mark.parametrize("sets,needle", [
    ([], "the training clips have LR levels at scales 2, 2.5, 4 and model fusesr-l trains on one scale "
         "(2, 4 and 8); set model.scale"),
    (["model.scale=2.5"], "scale 2.5, which model fusesr-l cannot take (it supports 2, 4 and 8)"),
    (["model.scale=3"], "model.scale = 3 but the clip has LR levels at scale(s) 2, 2.5, 4"),
])
def test_refusals_are_one_line_exit_2(multi, tmp_path, capsys, sets, needle):
    args = ["train", "--model", "fusesr-l", "--data", str(multi), "-o", str(tmp_path / "run"), "--max-steps", "1"]
    for s in SMALL + sets:
        args += ["--set", s]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
    with pytest.raises(ConfigError, match="set model.scale"):
        cfg = load_config(None, SMALL + ["model.name=\"fusesr-l\""])
        cfg.data.clips = [str(multi)]
        train(cfg, tmp_path / "run2")


# ------------------------------------------------------------------------------------------- evaluation

def test_evaluation_reports_per_scale(multi):
    res = evaluate_model(load_model("bilinear", 2), [str(multi)], EvalOptions(flip=False, warmup=0))
    assert set(res["per_scale"]) == {"2", "2.5", "4"} and res["mean"]["frames"] == 15
    ps = res["per_scale"]
    assert all(ps[k]["frames"] == 5 for k in ps)
    assert ps["2"]["psnr"] > ps["2.5"]["psnr"] > ps["4"]["psnr"]  # fewer LR pixels, worse bilinear
    # an integer-scale model is scored at its own level only; a level the clip lacks is one clear line
    res4 = evaluate_model(load_model("demod-bilinear", 4), [str(multi)], EvalOptions(flip=False, warmup=0))
    assert set(res4["per_scale"]) == {"4"}
    with pytest.raises(ValueError, match="no LR level at scale 8 .has 2, 2.5, 4"):
        evaluate_model(load_model("demod-bilinear", 8), [str(multi)], EvalOptions(flip=False, warmup=0))
    # scale=: one level only, scored exactly as that level is within the evaluation of every level
    one = evaluate_model(load_model("bilinear", 2), [str(multi)], EvalOptions(flip=False, warmup=0, scale=2.5))
    assert set(one["per_scale"]) == {"2.5"} and one["mean"]["frames"] == 5
    assert one["mean"]["psnr"] == pytest.approx(ps["2.5"]["psnr"], abs=1e-9)
    with pytest.raises(ValueError, match="give scales or scale, not both"):
        evaluate_model(load_model("bilinear", 2), [str(multi)], EvalOptions(scale=2.5, scales={str(multi): [2.5]}))


def test_fourier_sr_trains_on_scales_2_and_4_and_is_scored_at_2_5(multi, tmp_path):
    """The issue's acceptance: fourier-sr trains on a mix of scales and evaluates at a scale it never trained on."""
    train_clip = make_synthetic_clip(tmp_path / "c24", frames=range(1, 6), hr_size=(80, 40), scales=(2, 4),
                                     jitter=True)
    cfg = load_config(None, ["data.batch_size=2", "run.progress=false", "run.amp=\"none\"", "run.threads=0",
                             "model.name=\"fourier-sr\"", "data.crop=4", "data.window=2", "run.max_steps=4",
                             "data.val_frames=0"])
    cfg.data.clips = [str(train_clip)]
    summary = train(cfg, tmp_path / "run")
    assert summary["scales"] == [2.0, 4.0]
    model = load_model(str(tmp_path / "run" / "checkpoints" / "last.pt"), 2.5)
    res = evaluate_model(model, [str(multi)], EvalOptions(flip=False, warmup=0))
    assert set(res["per_scale"]) == {"2", "2.5", "4"}
    assert np.isfinite(res["per_scale"]["2.5"]["psnr"]) and res["per_scale"]["2.5"]["frames"] == 5
