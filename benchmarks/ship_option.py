"""Store an inference option with shipped weights (e.g. ``residual_clamp = "lr-guided"`` for fusesr-fast) when the
val rule (``training/selection.py``) chooses the weights run with it over the same weights as shipped.

    .venv/bin/python benchmarks/ship_option.py DATASET NAME KEY=VALUE [KEY=VALUE ...] [--force]

Only inference options (``training.models.options.INFERENCE_OPTIONS``: they leave the weights' meaning alone) can be
set; the float16 tensors are copied bit for bit, so the parameter digest does not change. The JSON beside the weights
keeps its training commands and training verdict (``val_rule``) and gains this command, the options set with this
verdict and the val scores before them (``inference_options``), and the model's scores on the dataset's val and test
splits with them. The test split is scored for the record only; it never enters the choice. Weights released with
``release_weights.py --defer-test`` keep their deferral: no test clip is read."""
from __future__ import annotations

import argparse
import importlib.util
import json
import shlex
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _release_weights():
    spec = importlib.util.spec_from_file_location("release_weights", REPO / "benchmarks" / "release_weights.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", type=Path, help="a dataset with val and test splits (blendsr dataset)")
    p.add_argument("name", help="a shipped network (training.pretrained.PRETRAINED)")
    p.add_argument("options", nargs="+", metavar="KEY=VALUE", help="inference options, TOML values")
    p.add_argument("--force", action="store_true", help="store the options even when the val rule keeps the weights")
    return p


def test_record(rw, meta: dict, name: str, spec: str, test: list[str]) -> dict:
    """The test-split keys of the JSON with the options: scored on ``test``, or none when the weights' release
    deferred the test split (``training.pretrained.test_deferred``: its round reads it once, at its end; the deferral
    stays)."""
    from training.pretrained import test_deferred
    if test_deferred(meta):
        return {"dataset": {**meta.get("dataset", {}), "test_clips": []}}
    scores = {m: rw.summary(rw.evaluate(m, test)) for m in (spec, "bicubic", "demod-bilinear", "demod-jbu")}
    scores[name] = scores.pop(spec)
    return {"dataset": {**meta.get("dataset", {}), "test_clips": [Path(c).name for c in test]},
            **rw.test_scores(name, scores[name], {k: v for k, v in scores.items() if k != name})}


def main(argv=None) -> int:
    a = parser().parse_args(argv)
    from gbuffer_export.dataset.build import split_clips
    from training.checkpoint import load_checkpoint
    from training.inference.loading import with_inference_options
    from training.pretrained import PRETRAINED, WEIGHTS_DIR
    from training.release import release
    from training.selection import choose
    rw = _release_weights()
    if a.name not in PRETRAINED:
        print(f"blendsr: error: {a.name!r} is not a shipped network ({', '.join(PRETRAINED)})", file=sys.stderr)
        return 2
    file = WEIGHTS_DIR / PRETRAINED[a.name]
    ck = load_checkpoint(file)
    ck = {**ck, "config": with_inference_options(ck["config"], a.options, str(file))}  # refuses other keys
    val = [str(c) for c in split_clips(a.dataset, "val")]
    spec = f"pretrained:{a.name}?{'&'.join(a.options)}"
    cand, inc = rw.evaluate(spec, val), rw.evaluate(f"pretrained:{a.name}", val)
    verdict = choose(cand, inc)
    print(verdict.line(spec), file=sys.stderr)
    if not verdict.replace and not a.force:
        return 0
    meta = json.loads(file.with_suffix(".json").read_text())
    for key in ("file", "bytes", "sha256", "step", "params", "param_digest"):
        meta.pop(key, None)  # release() writes them again
    command = " ".join(shlex.quote(w) for w in ["benchmarks/ship_option.py", str(a.dataset), a.name, *a.options])
    meta["commands"] = [*meta.get("commands", []), command]
    meta["inference_options"] = {"set": list(a.options), "command": command,
                                 "scores_on_val_split_before": rw.summary(inc),
                                 "val_rule": verdict.record(a.force)}
    meta.update(test_record(rw, meta, a.name, spec, [str(c) for c in split_clips(a.dataset, "test")]))
    meta["dataset"]["val_clips"] = [Path(c).name for c in val]  # the splits as scored now
    meta["scores_on_val_split"] = {"metric": rw.METRIC, a.name: rw.summary(cand),
                                   **{m: rw.summary(rw.evaluate(m, val)) for m in ("demod-bilinear", "demod-jbu")}}
    meta = release(ck, file, meta)
    test = (meta.get("scores_on_test_split") or {}).get(a.name)
    print(f"{a.name}: {', '.join(a.options)} stored with {file.name} ("
          + (f"test PSNR {test['psnr']:.2f} dB)" if test else "test split deferred)"), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
