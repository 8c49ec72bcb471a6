"""Storing an inference option with shipped weights (benchmarks/ship_option.py): the tensors are copied bit for bit,
the option is in the header and the loaded model runs with it; any other key is refused in one line."""
import pytest

from gbuffer_export.errors import BlendSRError


def test_an_inference_option_is_stored_with_the_same_tensors(tmp_path):
    from training.checkpoint import load_checkpoint
    from training.inference import load_model, with_inference_options
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
    from training.inference import with_inference_options
    with pytest.raises(BlendSRError, match="inference options"):
        with_inference_options({"model": {"name": "fusesr-fast", "fusesr-fast": {}}}, ["width=64"], "w.safetensors")
