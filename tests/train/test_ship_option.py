"""Storing an inference option with shipped weights (benchmarks/ship_option.py): the tensors are copied bit for bit,
the option is in the header and the loaded model runs with it; any other key is refused in one line."""
import pytest

from gbuffer_export.errors import BlendSRError


def test_an_inference_option_is_stored_with_the_same_tensors(tmp_path):
    from training.checkpoint import load_checkpoint
    from training.inference.loading import load_model, with_inference_options
    from training.pretrained import PRETRAINED, WEIGHTS_DIR
    from training.release import release
    from training.trainer import param_digest
    src = WEIGHTS_DIR / PRETRAINED["fusesr-fast"]
    ck = load_checkpoint(src)
    ck = {**ck, "config": with_inference_options(ck["config"], ['residual_clamp="none"'], str(src))}
    meta = release(ck, tmp_path / "w.safetensors", {"model": "fusesr-fast"})
    new, old = load_model(str(tmp_path / "w.safetensors"), 4), load_model(str(src), 4)
    assert meta["param_digest"] == param_digest(old.module) == param_digest(new.module)
    assert load_checkpoint(tmp_path / "w.safetensors")["config"]["model"]["fusesr-fast"]["residual_clamp"] == "none"
    assert new.module.clamp is None and not new.module.clamp_guided  # runs without a clamp (clamp: its margin)
    assert old.module.clamp is not None  # the shipped weights carry one


def test_a_key_that_changes_the_weights_meaning_is_refused():
    from training.inference.loading import with_inference_options
    with pytest.raises(BlendSRError, match="inference options"):
        with_inference_options({"model": {"name": "fusesr-fast", "fusesr-fast": {}}}, ["width=64"], "w.safetensors")


def test_ship_option_end_to_end_stores_the_option_and_its_verdict(tmp_path, monkeypatch, capsys):
    """benchmarks/ship_option.py on a copy of the shipped weights: the val rule's verdict is printed; with --force
    the option is stored in the header, the tensors are unchanged, and the JSON keeps its earlier commands and gains
    this command, the verdict, the val scores before and the splits as scored; an unknown name is one line, exit 2."""
    import importlib.util
    import json
    import shutil
    from pathlib import Path

    from gbuffer_export.dataset import build
    from gbuffer_export.synthetic import make_synthetic_clip
    from training import pretrained
    from training.checkpoint import load_checkpoint
    from training.inference.loading import load_model
    from training.trainer import param_digest
    pytest.importorskip("torch")
    name = "fusesr-fast"
    src = pretrained.WEIGHTS_DIR / pretrained.PRETRAINED[name]
    if not src.is_file():
        pytest.skip(f"{name} not shipped")
    weights = tmp_path / "weights"
    weights.mkdir()
    shutil.copy(src, weights / src.name)
    shutil.copy(src.with_suffix(".json"), weights / src.with_suffix(".json").name)
    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", weights)
    clips = {s: make_synthetic_clip(tmp_path / s, frames=range(1, 3), hr_size=(64, 36), scale=4, jitter=True)
             for s in ("val", "test")}
    monkeypatch.setattr(build, "split_clips", lambda root, split, done_only=True: [clips[split]])
    spec = importlib.util.spec_from_file_location("ship_option", Path(__file__).resolve().parents[2] / "benchmarks"
                                                  / "ship_option.py")
    ship = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ship)
    before = json.loads((weights / src.with_suffix(".json").name).read_text())
    assert ship.main([str(tmp_path), name, 'residual_clamp="none"', "--force"]) == 0
    err = capsys.readouterr().err
    assert f"pretrained:{name}?residual_clamp=\"none\"" in err and "stored with" in err
    meta = json.loads((weights / src.with_suffix(".json").name).read_text())
    assert meta["commands"][:-1] == before.get("commands", []) and "ship_option.py" in meta["commands"][-1]
    assert meta["inference_options"]["set"] == ['residual_clamp="none"']
    assert meta["inference_options"]["val_rule"]["forced"] is True
    assert meta["dataset"]["val_clips"] == ["val"] and meta["dataset"]["test_clips"] == ["test"]
    assert set(meta["scores_on_test_split"]) >= {name, "demod-jbu", "bicubic", "demod-bilinear", "metric"}
    stored = load_checkpoint(weights / src.name)["config"]["model"][name]
    assert stored["residual_clamp"] == "none"
    assert param_digest(load_model(f"pretrained:{name}", 4).module) == param_digest(load_model(str(src), 4).module)
    assert ship.main([str(tmp_path), "nope", 'residual_clamp="none"']) == 2
    assert capsys.readouterr().err.strip().count("\n") == 0
    # weights whose release deferred the test split (release_weights.py --defer-test) keep the deferral
    js = weights / src.with_suffix(".json").name
    for key in ("scores_on_test_split", "gain_over_demod_jbu_db"):
        meta.pop(key)
    js.write_text(json.dumps({**meta, "test_split": pretrained.TEST_DEFERRED}))
    assert ship.main([str(tmp_path), name, 'residual_clamp="lr-guided"', "--force"]) == 0
    assert "test split deferred" in capsys.readouterr().err
    meta = json.loads(js.read_text())
    assert "scores_on_test_split" not in meta and meta["test_split"] == pretrained.TEST_DEFERRED
    assert meta["dataset"]["test_clips"] == [] and meta["dataset"]["val_clips"] == ["val"]
