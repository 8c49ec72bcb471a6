"""Shipped weights: the float16 release of a checkpoint, ``pretrained:NAME`` everywhere a checkpoint goes,
fine-tuning from weights (``run.init_from``), and the installed weights against their own metadata."""
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training import pretrained  # noqa: E402
from training.config import load_config  # noqa: E402
from training.inference import ClipFrames, load_model, upscale_frame  # noqa: E402
from training.checkpoint import load_checkpoint  # noqa: E402
from training.train import param_digest, train  # noqa: E402

pytestmark = pytest.mark.torch
SMALL = ["data.crop=8", "data.batch_size=2", "model.width=16", "model.blocks=1", "run.progress=false",
         "run.amp=\"none\"", "run.threads=0"]


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 5), hr_size=(64, 36), scale=4)


@pytest.fixture(scope="module")
def run(clip, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "r"
    cfg = load_config(None, SMALL + ['model.name="fusesr-l"', "run.max_steps=3"])
    cfg.data.clips = [str(clip)]
    train(cfg, out)
    return out


def test_release_is_float16_small_and_matches_the_checkpoint(run, clip, tmp_path, monkeypatch):
    ck = run / "checkpoints" / "last.pt"
    from training.release import release
    meta = release(ck, tmp_path / "w.pt", {"model": "fusesr-l", "note": "test"})
    slim = torch.load(tmp_path / "w.pt", map_location="cpu", weights_only=True)
    assert "optimizer" not in slim and all(v.dtype == torch.float16 for v in slim["model"].values()
                                           if v.is_floating_point())
    assert meta["bytes"] == (tmp_path / "w.pt").stat().st_size < pretrained.MAX_BYTES
    assert json.loads((tmp_path / "w.json").read_text())["note"] == "test"
    src = ClipFrames(str(clip))
    a = upscale_frame(load_model(str(ck), 4), src, 2)["sr"]
    b = upscale_frame(load_model(str(tmp_path / "w.pt"), 4), src, 2)["sr"]
    assert np.abs(a - b).max() <= 2e-3 * max(1.0, float(np.abs(a).max()))  # fp16 weights
    # pretrained:NAME resolves to the package's weights folder
    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", tmp_path)
    monkeypatch.setitem(pretrained.PRETRAINED, "fusesr-l", "w.pt")
    assert pretrained.resolve("pretrained:fusesr-l") == str(tmp_path / "w.pt")
    assert load_checkpoint("pretrained:fusesr-l")["scale"] == 4
    with pytest.raises(FileNotFoundError, match="no such pretrained model; shipped: pretrained:fusesr"):
        pretrained.resolve("pretrained:nope")
    assert main(["evaluate", "--checkpoint", "pretrained:nope", "--data", str(clip), "--json",
                 str(tmp_path / "e.json")]) == 2


def test_init_from_starts_a_fresh_run_at_the_given_weights(run, clip, tmp_path):
    cfg = load_config(None, SMALL + ['model.name="fusesr-l"', "run.max_steps=1", "optim.lr=1e-12",
                                     f'run.init_from="{run / "checkpoints" / "last.pt"}"'])
    cfg.data.clips = [str(clip)]
    train(cfg, tmp_path / "ft")
    a = load_model(str(run / "checkpoints" / "last.pt"), 4)
    b = load_model(str(tmp_path / "ft" / "checkpoints" / "last.pt"), 4)
    for (k, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items()):
        assert torch.allclose(x, y, atol=1e-6), k
    bad = load_config(None, SMALL + ['model.name="fusesr"', "run.max_steps=1",
                                     f'run.init_from="{run / "checkpoints" / "last.pt"}"'])
    bad.data.clips = [str(clip)]
    with pytest.raises(ValueError, match="do not fit model fusesr"):
        train(bad, tmp_path / "bad")


@pytest.mark.parametrize("name", list(pretrained.PRETRAINED))
def test_installed_weights_match_their_metadata(name):
    path = pretrained.WEIGHTS_DIR / pretrained.PRETRAINED[name]
    if not path.is_file():
        pytest.skip(f"{path} not shipped")
    meta = pretrained.info(name)
    assert path.stat().st_size == meta["bytes"] <= pretrained.MAX_BYTES
    model = load_model(f"pretrained:{name}", 4)
    assert param_digest(model) == meta["param_digest"]
    assert meta["commands"] and meta["dataset"]["test_clips"]
    scores = meta["scores_on_test_split"]
    assert scores[name]["psnr"] - scores["demod-jbu"]["psnr"] == pytest.approx(meta["gain_over_demod_jbu_db"],
                                                                                abs=1e-3)
    ds = meta["dataset"]
    splits = [set(ds["train_clips"]), set(ds.get("val_clips", [])), set(ds["test_clips"])]
    assert all(not (a & b) for i, a in enumerate(splits) for b in splits[i + 1:]), "a clip in two splits"
    if ds.get("val_clips"):
        val = meta["scores_on_val_split"]
        assert set(val[name]["per_clip"]) == set(ds["val_clips"]) == set(val["demod-jbu"]["per_clip"])
