"""Pretrained weights shipped in the package (torch layer).

``training/weights/<file>.safetensors`` holds the model's weights in float16 with a JSON header (format,
configuration, scale, step; no optimiser state, no pickle: loading cannot run code), and ``<file>.json`` beside it the
file's sha256 (checked on every load), the dataset spec, the commands that made it and its scores. Anywhere a
checkpoint path is accepted (``evaluate``, ``upscale``, ``export``, ``bench models``, ``make demo``, the add-on),
``pretrained:NAME`` names one of them. ``benchmarks/pretrain.sh`` remakes fusesr and fusesr-l, ``benchmarks/zoo.sh``
the seed networks (``training.release.release`` writes a
file). This module imports nothing of the trainer: the checkpoint loader resolves names through it.
"""
from __future__ import annotations

import json
from pathlib import Path

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
PREFIX = "pretrained:"

#: name -> weight file (scale 4) in ``training/weights``.
PRETRAINED: dict[str, str] = {
    "fusesr": "fusesr_x4.safetensors",
    "fusesr-l": "fusesr_l_x4.safetensors",
    "rdg-s": "rdg_s_x4.safetensors",
    "nsrd": "nsrd_x4.safetensors",
    "nsrr-fec": "nsrr_fec_x4.safetensors",
    "fourier-sr": "fourier_sr_x4.safetensors",
    "fusesr-fast": "fusesr_fast_x4.safetensors",
}
MAX_BYTES = 10 * 1024 * 1024


def resolve(spec) -> str:
    """``pretrained:NAME`` -> the path of its weight file (FileNotFoundError naming the known ones); anything else
    is returned unchanged."""
    spec = str(spec)
    if not spec.startswith(PREFIX):
        return spec
    name = spec[len(PREFIX):]
    if name not in PRETRAINED:
        raise FileNotFoundError(f"{spec}: no such pretrained model; shipped: "
                                f"{', '.join(PREFIX + n for n in PRETRAINED)}")
    path = WEIGHTS_DIR / PRETRAINED[name]
    if not path.is_file():
        raise FileNotFoundError(f"{path}: pretrained weights missing from this installation (run "
                                "benchmarks/pretrain.sh to make them)")
    return str(path)


def available() -> list[str]:
    """``pretrained:NAME`` specs whose weight file is installed."""
    return [PREFIX + n for n, f in PRETRAINED.items() if (WEIGHTS_DIR / f).is_file()]


def info(name: str) -> dict:
    """The JSON beside a pretrained weight file (spec, commands, scores)."""
    path = WEIGHTS_DIR / PRETRAINED[name]
    return json.loads(path.with_suffix(".json").read_text())


#: The guided non-learned baseline every shipped network is measured against (issue: "never worse than it").
BASELINE = "demod-jbu"


#: What a weights JSON released without reading its test split says under ``test_split`` (``release_weights.py
#: --defer-test``; ``--record-test`` replaces it with the test scores at the round's end).
TEST_DEFERRED = ("deferred: released without reading the test split, which its round reads once, at its end "
                 "(benchmarks/release_weights.py --record-test)")


def test_deferred(doc: dict) -> bool:
    """True when a weights JSON says its test split is deferred (``TEST_DEFERRED``) and its test scores are not
    recorded yet."""
    return str(doc.get("test_split", "")).startswith("deferred")


#: The JSON key of a shipped network's scores on wider val sets than the one it was chosen on
#: (``benchmarks/worst_case.py --record``): ``{val set: record}``, one record per dataset spec's val split (each
#: recorded again replaces its own only), each kept only while its ``sha256`` is the weights' own.
WORST_CASE_VAL = "worst_case_val"


def all_val_records(doc: dict) -> dict[str, dict]:
    """``{val set: record}`` of a weights JSON's ``WORST_CASE_VAL``, whatever weights they speak for (a JSON of
    before 2026-11-30 holds one record, read as keyed by its own val set; anything else reads as none)."""
    records = doc.get(WORST_CASE_VAL)
    if not isinstance(records, dict):
        return {}
    if "margin" in records:
        return {records.get("dataset", "wide val"): records}
    return {where: r for where, r in records.items() if isinstance(r, dict)}


def val_records(doc: dict) -> dict[str, dict]:
    """``all_val_records`` that speak for these weights (the record's ``sha256`` is the JSON's) and hold a margin."""
    return {where: r for where, r in all_val_records(doc).items()
            if r.get("sha256") == doc.get("sha256") and isinstance(r.get("margin"), (int, float))}


def val_margins(name: str) -> dict[str, float]:
    """The shipped network's PSNR minus ``demod-jbu``'s on each val set on record, in dB, from the JSON beside its
    weights: ``scores_on_val_split`` (the split its training was chosen on; both scored on the same frames) and
    each of ``val_records`` (wider val sets: over all of one and over each of its groups, objects and levels);
    empty when the JSON holds neither."""
    try:
        doc = info(name)
    except (OSError, ValueError, KeyError):
        return {}
    out = {}
    try:
        scores = doc.get("scores_on_val_split") or {}
        out["val split"] = float(scores[name]["psnr"]) - float(scores[BASELINE]["psnr"])
    except (ValueError, KeyError, TypeError):
        pass
    for where, record in val_records(doc).items():
        out[where] = float(record["margin"])
        for group, margin in (record.get("per_group") or {}).items():  # objects and levels: each a val set of its own
            out[f"{where}, {group}"] = float(margin)
    return out


def val_margin(name: str) -> float | None:
    """The smallest of ``val_margins`` (dB): a network is as good as its worst val set; None without scores."""
    margins = val_margins(name)
    return min(margins.values()) if margins else None


def below_baseline(name: str) -> bool:
    """True when the shipped network scores below ``demod-jbu`` on a val set on record (``val_margin`` < 0)."""
    margin = val_margin(name)
    return margin is not None and margin < 0


def below_baseline_note(name: str) -> str:
    """'below demod-jbu on val' for a shipped network that is (``below_baseline``), else ''."""
    return f"below {BASELINE} on val" if below_baseline(name) else ""
