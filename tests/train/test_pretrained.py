"""Shipped weights: the float16 safetensors release of a checkpoint, refusal of tampered or unfitting files,
``pretrained:NAME`` everywhere a checkpoint goes, fine-tuning from weights (``run.init_from``), and the installed
weights against their own metadata (size, sha256, parameter digest)."""
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training import pretrained  # noqa: E402
from training.config import load_config  # noqa: E402
from training.inference.loading import ClipFrames, load_model, upscale_frame  # noqa: E402
from training.checkpoint import load_checkpoint  # noqa: E402
from training.trainer import param_digest  # noqa: E402
from training.train import train  # noqa: E402
from tests.conftest import REPO  # noqa: E402

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


def test_release_is_float16_safetensors_small_and_matches_the_checkpoint(run, clip, tmp_path, monkeypatch):
    ck = run / "checkpoints" / "last.pt"
    from safetensors import safe_open

    from training.checkpoint import file_sha256
    from training.release import release
    meta = release(ck, tmp_path / "w.safetensors", {"model": "fusesr-l", "note": "test"})
    with safe_open(str(tmp_path / "w.safetensors"), framework="pt") as f:  # tensors and a JSON header, no pickle
        header = json.loads(f.metadata()["blendsr"])
        assert all(f.get_tensor(k).dtype == torch.float16 for k in f.keys())
    assert header["format"] == "blendsr.weights" and header["model_name"] == "fusesr-l" and header["scale"] == 4
    assert "optimizer" not in header and header["step"] == 3
    assert meta["bytes"] == (tmp_path / "w.safetensors").stat().st_size < pretrained.MAX_BYTES
    on_disk = json.loads((tmp_path / "w.json").read_text())
    assert on_disk["note"] == "test" and on_disk["sha256"] == file_sha256(tmp_path / "w.safetensors") == meta["sha256"]
    src = ClipFrames(str(clip))
    a = upscale_frame(load_model(str(ck), 4), src, 2)["sr"]
    b = upscale_frame(load_model(str(tmp_path / "w.safetensors"), 4), src, 2)["sr"]
    assert np.abs(a - b).max() <= 2e-3 * max(1.0, float(np.abs(a).max()))  # fp16 weights
    assert param_digest(load_model(str(tmp_path / "w.safetensors"), 4).module) == meta["param_digest"]
    # releasing the released file again changes no bit (how the shipped .pt files were converted)
    again = release(tmp_path / "w.safetensors", tmp_path / "again" / "w.safetensors", {"model": "fusesr-l"})
    assert again["param_digest"] == meta["param_digest"] and again["sha256"] == meta["sha256"]
    with pytest.raises(ValueError, match=r"w\.pt: shipped weights are written as \.safetensors"):
        release(ck, tmp_path / "w.pt", {})
    # pretrained:NAME resolves to the package's weights folder
    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", tmp_path)
    monkeypatch.setitem(pretrained.PRETRAINED, "fusesr-l", "w.safetensors")
    assert pretrained.resolve("pretrained:fusesr-l") == str(tmp_path / "w.safetensors")
    assert load_checkpoint("pretrained:fusesr-l")["scale"] == 4
    with pytest.raises(FileNotFoundError, match="no such pretrained model; shipped: pretrained:fusesr"):
        pretrained.resolve("pretrained:nope")
    assert main(["evaluate", "--checkpoint", "pretrained:nope", "--data", str(clip), "--json",
                 str(tmp_path / "e.json")]) == 2


def _one_line_refusal(capsys, path, *args) -> str:
    assert main(["evaluate", "--checkpoint", str(path), "--data", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "Traceback" not in err[0], err
    return err[0]


def test_tampered_or_unfitting_weights_are_refused_in_one_line(run, clip, tmp_path, capsys):
    """The sha256 recorded in the JSON is checked on every load; a file whose tensors do not fit the model (missing
    or unexpected names) is refused naming the file; so is one without its JSON."""
    from safetensors.torch import save_file

    from training.checkpoint import CheckpointError, file_sha256, load_weights_file
    from training.release import release
    w = tmp_path / "w.safetensors"
    release(run / "checkpoints" / "last.pt", w, {"model": "fusesr-l"})
    good = w.read_bytes()
    args = (str(clip), "--json", str(tmp_path / "e.json"))
    bad = bytearray(good)
    bad[-1] ^= 1  # one bit of one weight
    w.write_bytes(bytes(bad))
    assert "differs from the recorded" in _one_line_refusal(capsys, w, *args)
    w.write_bytes(good[: len(good) // 2])
    assert "differs from the recorded" in _one_line_refusal(capsys, w, *args)
    # a consistent file and JSON whose tensors do not fit: one missing, one unexpected
    w.write_bytes(good)
    (tmp_path / "w.json").rename(tmp_path / "x.json")
    assert "no w.json beside it" in _one_line_refusal(capsys, w, *args)
    (tmp_path / "x.json").rename(tmp_path / "w.json")
    with pytest.raises(CheckpointError, match="differs from the recorded"):
        load_weights_file(w, sha256="0" * 64)
    ck = load_weights_file(w)
    header = {k: ck[k] for k in ("model_name", "config", "scale", "step")}
    for name, tensors in (("missing", dict(list(ck["model"].items())[1:])),
                          ("unexpected", {**ck["model"], "extra.weight": torch.zeros(1)})):
        f = tmp_path / f"{name}.safetensors"
        save_file(tensors, f, metadata={"blendsr": json.dumps({"format": "blendsr.weights", **header})})
        (tmp_path / f"{name}.json").write_text(json.dumps({"sha256": file_sha256(f)}))
        line = _one_line_refusal(capsys, f, *args)
        assert f"do not fit model fusesr-l: {name}" in line, line
    # not BlendSR's header
    f = tmp_path / "plain.safetensors"
    save_file(ck["model"], f)
    (tmp_path / "plain.json").write_text(json.dumps({"sha256": file_sha256(f)}))
    assert "not BlendSR weights" in _one_line_refusal(capsys, f, *args)


def test_init_from_starts_a_fresh_run_at_the_given_weights(run, clip, tmp_path):
    cfg = load_config(None, SMALL + ['model.name="fusesr-l"', "run.max_steps=1", "optim.lr=1e-12",
                                     f'run.init_from="{run / "checkpoints" / "last.pt"}"'])
    cfg.data.clips = [str(clip)]
    train(cfg, tmp_path / "ft")
    a = load_model(str(run / "checkpoints" / "last.pt"), 4)
    b = load_model(str(tmp_path / "ft" / "checkpoints" / "last.pt"), 4)
    for (k, x), (_, y) in zip(a.module.state_dict().items(), b.module.state_dict().items()):
        assert torch.allclose(x, y, atol=1e-6), k
    from training.checkpoint import file_sha256  # what it started from, for release_weights.check_origin
    assert load_checkpoint(tmp_path / "ft" / "checkpoints" / "last.pt")["init"] == {
        "from": str(run / "checkpoints" / "last.pt"), "sha256": file_sha256(run / "checkpoints" / "last.pt")}
    assert load_checkpoint(run / "checkpoints" / "last.pt")["init"] is None
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
    from training.checkpoint import file_sha256
    assert path.suffix == ".safetensors" and not list(pretrained.WEIGHTS_DIR.glob("*.pt")), "no pickles shipped"
    assert path.stat().st_size == meta["bytes"] <= pretrained.MAX_BYTES
    assert file_sha256(path) == meta["sha256"]
    model = load_model(f"pretrained:{name}", 4)
    assert param_digest(model.module) == meta["param_digest"]
    assert meta["commands"]
    ds = meta["dataset"]
    if "scores_on_test_split" not in meta:  # released by the val rule before its round read the test split
        assert pretrained.test_deferred(meta) and not ds["test_clips"] and ds["val_clips"]
    else:
        scores = meta["scores_on_test_split"]
        assert ds["test_clips"] and scores[name]["psnr"] - scores["demod-jbu"]["psnr"] == pytest.approx(
            meta["gain_over_demod_jbu_db"], abs=1e-3)
        assert scores[name]["psnr"] >= scores["bicubic"]["psnr"] + 1.0  # issue 28's acceptance, on the test split
    splits = [set(ds["train_clips"]), set(ds.get("val_clips", [])), set(ds["test_clips"])]
    assert all(not (a & b) for i, a in enumerate(splits) for b in splits[i + 1:]), "a clip in two splits"
    if ds.get("val_clips"):
        val = meta["scores_on_val_split"]
        assert set(val[name]["per_clip"]) == set(ds["val_clips"]) == set(val["demod-jbu"]["per_clip"])


@pytest.mark.parametrize("name", list(pretrained.PRETRAINED))
def test_every_consumer_takes_each_shipped_network(name, tmp_path):
    """``pretrained:NAME`` in evaluate, upscale, export --onnx (onnxruntime matches torch) and bench models, on a tiny
    jittered synthetic clip with every buffer (recurrent networks carry their state through its frames). HDR-FLIP,
    which scores any network's output alike, is computed for one of them (fusesr-fast); no warm-up runs."""
    if not (pretrained.WEIGHTS_DIR / pretrained.PRETRAINED[name]).is_file():
        pytest.skip(f"{name} not shipped")
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(48, 32), scale=4, jitter=True)
    spec = f"pretrained:{name}"
    flip = [] if name == "fusesr-fast" else ["--no-flip"]
    assert main(["evaluate", "--checkpoint", spec, "--data", str(clip), "--json", str(tmp_path / "e.json"),
                 "--warmup", "0", *flip]) == 0
    assert np.isfinite(json.loads((tmp_path / "e.json").read_text())["mean"]["psnr"])
    assert main(["upscale", "--checkpoint", spec, "--clip", str(clip), "-o", str(tmp_path / "up"),
                 "--no-progress"]) == 0
    assert len(list((tmp_path / "up").glob("*.exr"))) == 3
    assert main(["export", "--checkpoint", spec, "--onnx", str(tmp_path / "m.onnx"), "--clip", str(clip)]) == 0
    assert json.loads((tmp_path / "m.onnx.json").read_text())["match"]
    assert main(["bench", "models", "--data", str(clip), "--models", spec, "--threads", "1", "--no-progress",
                 "--warmup", "0", "-o", str(tmp_path / "bench")]) == 0
    rows = json.loads((tmp_path / "bench" / "bench_models.json").read_text())
    assert name in json.dumps(rows)


def test_bench_models_scores_an_any_scale_network_at_the_clips_lr_level_only(tmp_path):
    """A clip with LR levels at 4 ('lr') and 2: every row of the table is at 4, fourier-sr's too (not averaged
    with its scores at 2, which evaluate reports per scale)."""
    if not (pretrained.WEIGHTS_DIR / pretrained.PRETRAINED["fourier-sr"]).is_file():
        pytest.skip("fourier-sr not shipped")
    clip = make_synthetic_clip(tmp_path / "c", frames=range(1, 3), hr_size=(64, 32), scale=4, scales=(4, 2))
    assert main(["bench", "models", "--data", str(clip), "--models", "pretrained:fourier-sr,bicubic", "--threads",
                 "1", "--no-progress", "--warmup", "0", "-o", str(tmp_path / "bench")]) == 0
    out = json.loads((tmp_path / "bench" / "bench_models.json").read_text())
    assert main(["evaluate", "--checkpoint", "pretrained:fourier-sr", "--data", str(clip), "--json",
                 str(tmp_path / "e.json"), "--no-flip", "--no-progress"]) == 0
    per_scale = json.loads((tmp_path / "e.json").read_text())["per_scale"]
    row = next(r for r in out["rows"] if r["model"] == "pretrained:fourier-sr")
    assert set(per_scale) == {"2", "4"} and per_scale["2"]["psnr"] != per_scale["4"]["psnr"]
    assert row["psnr"] == pytest.approx(per_scale["4"]["psnr"], abs=1e-3)


def _release_round(run, tmp_path, monkeypatch) -> SimpleNamespace:
    """benchmarks/release_weights.py loaded, its scores stubbed (``asked`` lists every (model, clips) scored: the
    candidate beats the shipped weights on every line of the rule), a dataset index with held-out-family val clips
    (the shipped weights trained on ``vr``'s family), the run copied with its command and unbounded shipped weights
    of fusesr-l in a temporary weights folder."""
    import importlib.util

    from gbuffer_export.dataset import build
    from training.release import release
    spec = importlib.util.spec_from_file_location("release_weights", REPO / "benchmarks" / "release_weights.py")
    rw = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rw)
    ds = tmp_path / "ds"
    ds.mkdir()
    splits = {"val": ["vh", "vr", "vi"], "test": ["t"], "train": ["a"]}
    groups = {"vh": "held-out", "vr": "held-out"}
    (ds / build.INDEX).write_text(json.dumps({
        "schema": build.SCHEMA, "schema_version": build.SCHEMA_VERSION, "name": "ds",
        "spec": {"file": "spec.toml", "sha256": "abc"},
        "clips": [{"id": n, "path": f"clips/{n}", "split": sp, "family_group": groups.get(n, "in-family"),
                   "families": [f"level:{n}"]} for sp, names in splits.items() for n in names]}))
    from gbuffer_export.dataset import family_gap  # the shipped weights trained on vr's level (the wide set's room)
    monkeypatch.setattr(family_gap, "lineage_families", lambda js, repo: ({"level:vr"}, []))
    run = Path(shutil.copytree(run, tmp_path / "run"))
    (run / "command.txt").write_text("blendsr train --model fusesr-l\n")
    monkeypatch.setattr(build, "split_clips", lambda root, split, done_only=True: [
        Path(root) / "clips" / n for n in splits[split]])
    asked = []

    def evaluate(model, clips):
        asked.append((model, [Path(c).name for c in clips]))
        better = "last.pt" in model
        return {"mean": {"psnr": 30.0 + better, "ssim": 0.9, "psnr_hdr": 30.0, "tpsnr": 30.0 + better, "frames": 1,
                         "margin_min": 0.5 + better, "artifact_pixels": 0},
                "per_frame": [{"clip": c, "psnr": 30.0} for c in clips]}
    monkeypatch.setattr(rw, "evaluate", evaluate)
    weights = tmp_path / "weights"
    weights.mkdir()
    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", weights)
    file = pretrained.PRETRAINED["fusesr-l"]
    release(run / "checkpoints" / "last.pt", weights / file, {"model": "fusesr-l"})  # the incumbent: no bound
    runs = tmp_path / "runs"
    runs.mkdir()
    return SimpleNamespace(rw=rw, ds=ds, run=run, runs=runs, asked=asked, json=(weights / file).with_suffix(".json"),
                           file=weights / file, splits=splits)


def test_release_weights_scores_the_run_with_its_options_on_held_out_val_and_ships_them(run, clip, tmp_path,
                                                                                        monkeypatch, capsys):
    """benchmarks/release_weights.py end to end, its scores stubbed: ``--run`` names the run, ``--options`` is what the
    val rule (on the held-out-family val clips only) and the test scores read and what the released file runs with;
    the JSON names the clips the run trained on."""
    o = _release_round(run, tmp_path, monkeypatch)
    rw, ds, run, runs, asked = o.rw, o.ds, o.run, o.runs, o.asked
    base = [str(ds), str(runs), "--models", "fusesr-l", "--run", f"fusesr-l={run}", "--script", ""]
    assert rw.main(base + ["--options", "fusesr-l?residual_clamp=lr-guidd"]) == 2  # checked before any score
    assert "'lr-guidd': choose one of" in capsys.readouterr().err and not asked
    assert rw.main(base + ["--options", "fusesr-l?residual_clamp=lr-range"]) == 0
    err = capsys.readouterr().err
    assert "the candidate runs with residual_clamp 'lr-range' (shipped: 'none')" in err, err
    assert "fusesr-l: val rule replaces the shipped weights" in err, err
    assert "fusesr-l: 1 of the 2 held-out-family val clips hold only families the shipped weights" in err, err
    cand = f"{run / 'checkpoints' / 'last.pt'}?residual_clamp=lr-range"
    assert (cand, ["vh"]) in asked and ("pretrained:fusesr-l", ["vh"]) in asked and (cand, ["t"]) in asked
    assert ("demod-jbu", ["vh"]) in asked and not any("vr" in clips for _, clips in asked)
    assert not any(m.endswith("last.pt") for m, _ in asked)  # never scored without its options
    meta = json.loads(o.json.read_text())
    assert meta["inference_options"] == ["residual_clamp=lr-range"] and meta["val_rule"]["replace"]
    assert meta["dataset"]["val_clips"] == ["vh"] and meta["scores_on_val_split"]["val_group"] == "held-out"
    assert meta["dataset"]["val_clips_left_out"] == ["vr"]
    assert meta["val_rule"]["shipped_before"]["psnr"] == 30.0 and meta["scores_on_val_split"]["fusesr-l"]["psnr"] == 31.0
    rules = json.loads((runs / "release.json").read_text())["val_rules"]["fusesr-l"]
    assert rules["replace"] and rules["shipped"]["psnr"] == 30.0 and rules["candidate"]["psnr"] == 31.0
    (run / "command.txt").unlink()  # --script '': the command that made the run is required, before any score
    asked.clear()
    assert rw.main(base) == 2 and "no command.txt" in capsys.readouterr().err and not asked
    assert meta["dataset"]["train_clips"] == [clip.name]  # the run's own clips, not the split's "a"
    assert load_model(str(o.file), 4).config.model.options.residual_clamp == "lr-range"
    assert json.loads((runs / "release.json").read_text())["val_group"] == "held-out"


def test_release_weights_can_release_before_the_test_split_is_read_and_record_it_at_the_end(run, clip, tmp_path,
                                                                                           monkeypatch, capsys):
    """``--defer-test``: the val rule releases without scoring any test clip and the JSON says so (the model card
    too); ``--record-test``: only once every planned test clip is finished, only weights released from this dataset's
    spec, the shipped weights and the baselines are scored on the test split and written into the JSON, the weights
    unchanged."""
    from gbuffer_export.dataset import build
    from training.checkpoint import file_sha256
    from training.commands import model_cards
    o = _release_round(run, tmp_path, monkeypatch)
    base = [str(o.ds), str(o.runs), "--models", "fusesr-l", "--run", f"fusesr-l={o.run}", "--script", ""]
    val = o.splits["val"]
    o.splits["val"] = []  # no val clip: the val rule would read nothing, and no test clip either
    assert o.rw.main(base + ["--defer-test", "--val-group", "all"]) == 2
    assert "no finished val clip" in capsys.readouterr().err and not o.asked
    o.splits["val"] = val
    assert o.rw.main(base + ["--defer-test"]) == 0
    assert "test split not read (--defer-test)" in capsys.readouterr().out
    assert o.asked and not any(c == ["t"] for _, c in o.asked)  # no test clip read
    meta = json.loads(o.json.read_text())
    assert "scores_on_test_split" not in meta and meta["test_split"] == pretrained.TEST_DEFERRED
    assert meta["scores_on_val_split"]["fusesr-l"] and meta["val_rule"]["replace"]
    card = model_cards.card_text("fusesr_l_x4", meta, None, None, {})
    assert f"- Test split: {pretrained.TEST_DEFERRED}." in card and "- Metric: PSNR/SSIM" in card
    assert "val and test clips not read yet (see Margins)" in card
    assert "- The weights these replaced, on the same val clips: PSNR 30.00 dB, margin +0.00 dB over `demod-jbu` " \
           "(smallest per clip +0.50 dB)." in card
    sha = file_sha256(o.file)
    o.asked.clear()
    assert o.rw.main(base) == 2  # a release that would read the test split of a round that defers it
    assert "its round defers the test split" in capsys.readouterr().err and not o.asked
    assert o.rw.main(base[:4] + ["--record-test", "--options", "fusesr-l?residual_clamp=none"]) == 2
    assert "--options would be ignored" in capsys.readouterr().err and not o.asked
    o.splits["test"] = []  # the test clip not finished: nothing is scored
    assert o.rw.main(base[:4] + ["--record-test"]) == 2
    assert "1 of its 1 test clips are not finished" in capsys.readouterr().err and not o.asked
    o.splits["test"] = ["t"]
    (o.ds / build.INDEX).write_text((o.ds / build.INDEX).read_text().replace('"abc"', '"other"'))
    assert o.rw.main(base[:4] + ["--record-test"]) == 2  # released from another spec: its test split is another
    assert "released from another dataset spec" in capsys.readouterr().err and not o.asked
    (o.ds / build.INDEX).write_text((o.ds / build.INDEX).read_text().replace('"other"', '"abc"'))
    wide = o.json.with_name(Path(pretrained.PRETRAINED["fusesr"]).with_suffix(".json").name)
    wide.write_text(json.dumps({"dataset": {"spec_sha256": "wide"}}))  # fusesr kept weights of another spec
    shipped, scored = o.json.read_text(), o.rw.evaluate

    def meanwhile(edit):  # the JSON edited while the shipped weights are scored (scoring takes hours)
        def evaluate(model, clips):
            if model == "pretrained:fusesr-l":
                o.json.write_text(json.dumps(edit(json.loads(o.json.read_text()))))
            return scored(model, clips)
        return evaluate
    monkeypatch.setattr(o.rw, "evaluate", meanwhile(lambda d: {**d, "sha256": "released again"}))
    assert o.rw.main([str(o.ds), str(o.runs), "--models", "fusesr-l", "--record-test"]) == 2
    assert "were released again or their test split recorded while they were scored" in capsys.readouterr().err
    assert "scores_on_test_split" not in json.loads(o.json.read_text())  # the other release's JSON kept as it is
    o.json.write_text(shipped)
    monkeypatch.setattr(o.rw, "evaluate", meanwhile(lambda d: {**d, pretrained.WORST_CASE_VAL: {"s val": {"margin": 1.0}}}))
    assert o.rw.main([str(o.ds), str(o.runs), "--models", "fusesr,fusesr-l", "--record-test"]) == 0
    assert json.loads(o.json.read_text())[pretrained.WORST_CASE_VAL] == {"s val": {"margin": 1.0}}  # kept
    assert f"note: {wide}: released from another dataset spec" in capsys.readouterr().err
    assert {m for m, c in o.asked} == {"bicubic", "demod-bilinear", "demod-jbu", "pretrained:fusesr-l"}
    assert all(c == ["t"] for _, c in o.asked)
    meta = json.loads(o.json.read_text())
    assert meta["scores_on_test_split"]["fusesr-l"]["psnr"] == 30.0 and meta["gain_over_demod_jbu_db"] == 0.0
    assert meta["dataset"]["test_clips"] == ["t"] and meta["test_split"].startswith("recorded ")
    assert meta["scores_on_test_split"]["fusesr-l"]["steps"] == meta["step"] and "fusesr,fusesr-l" in meta["test_split"]
    assert file_sha256(o.file) == sha == meta["sha256"]
    o.asked.clear()
    assert o.rw.main(base[:4] + ["--record-test"]) == 2  # read once
    assert "its test split is recorded already" in capsys.readouterr().err and not o.asked
    assert o.rw.main(base) == 0  # the round's end: a later release reads the test split again
