"""The val rule that chooses between trainings (training/selection.py), on evaluate_model results of real models
and on hand-made results for each line of the rule."""
import pytest

from gbuffer_export.synthetic import make_synthetic_clip
from training.selection import choose


def _result(**mean):
    base = {"margin_min": 0.5, "psnr": 30.0, "ssim": 0.9, "tpsnr": 28.0, "artifact_pixels": 10}
    return {"mean": {**base, **mean}}


def test_each_line_of_the_rule():
    inc = _result()
    assert choose(_result(), inc).replace  # the same scores: not worse
    assert choose(_result(psnr=30.2, margin_min=0.6, artifact_pixels=8), inc).replace
    for worse, words in ((dict(margin_min=0.3), "smallest per-clip margin"), (dict(psnr=29.9), "mean PSNR"),
                         (dict(ssim=0.89), "mean SSIM"), (dict(tpsnr=27.5), "mean tPSNR"),
                         (dict(artifact_pixels=11), "artifact pixels rise")):
        c = choose(_result(**{"psnr": 31.0, **worse}), inc)  # a better mean does not buy a worse worst case
        assert not c.replace and any(words in r for r in c.reasons), (worse, c.reasons)
    missing = choose(_result(artifact_pixels=None), inc)
    assert not missing.replace and "missing" in missing.reasons[0]
    # how the scripts print and record a verdict
    two = choose(_result(psnr=29.0, artifact_pixels=12), inc)
    assert two.line("fusesr") == ("fusesr: val rule keeps the shipped weights: mean PSNR falls: 29 against 30; "
                                  "artifact pixels rise: 12 against 10")
    assert choose(_result(), inc).line("x") == "x: val rule replaces the shipped weights"
    assert two.record(True) == {"replace": False, "reasons": list(two.reasons), "forced": True}


def test_the_rule_on_evaluated_models(tmp_path):
    from training.evaluate import EvalOptions, evaluate_model
    from training.inference.loading import load_model
    clip = str(make_synthetic_clip(tmp_path / "c", frames=range(1, 4), hr_size=(64, 36), scale=4))
    jbu = evaluate_model(load_model("demod-jbu", 4), [clip], EvalOptions(flip=False))
    bil = evaluate_model(load_model("bicubic", 4), [clip], EvalOptions(flip=False))
    assert jbu["mean"]["margin_min"] == pytest.approx(0.0, abs=1e-9)
    assert choose(jbu, bil).replace and not choose(bil, jbu).replace
    assert choose(jbu, jbu).replace
