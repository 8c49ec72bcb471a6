"""Which clip buffers each model reads (pure Python): ``blendsr dataset --for-models`` and ``blendsr render
--for-models`` render only these (plus what evaluation needs).

The core may not import the torch layer, so the table is derived from every model's ``needs()`` by
``make generate`` into ``model_buffers.json`` beside this file; ``tests/dataset/test_dataset.py``
fails when the file differs from the models, so a model that starts reading a new buffer fails the suite until the
table is regenerated. Buffers apply to both levels of a clip (a buffer read at HR only is also
written at LR). Derived keys map to their sources: ``irradiance`` and ``fbeta_used`` are computed from radiance,
emission, fbeta and flags; ``depth_ref`` from LR depth.
"""
from __future__ import annotations

import json
from pathlib import Path

from ..errors import BlendSRError
from ..conventions import ALL_BUFFERS

#: Buffers every clip keeps: the ground truth (radiance) and HR motion for tPSNR and the warping error.
EVALUATION_BUFFERS: tuple[str, ...] = ("radiance", "motion")

#: The table, written by ``make generate`` from every model's ``needs()``.
TABLE_PATH = Path(__file__).resolve().parent / "model_buffers.json"

#: model name -> buffers it reads with its default configuration and with its shipped weights' (``pretrained:NAME``:
#: e.g. the residual demod-bilinear base of ``rdg-s`` and ``nsrr-fec`` reads L_D and remodulates, docs/models/).
_TABLE = json.loads(TABLE_PATH.read_text(encoding="utf-8"))
MODEL_BUFFERS: dict[str, tuple[str, ...]] = {name: tuple(bufs) for name, bufs in _TABLE["models"].items()}

#: model name or ``pretrained:NAME`` -> the integer scales it upscales by (None: any scale), from every model's
#: ``SCALES``; shipped weights of a fixed-scale model upscale by the one scale they were trained for.
MODEL_SCALES: dict[str, tuple[int, ...] | None] = {
    name: None if scales is None else tuple(scales) for name, scales in _TABLE["scales"].items()}

#: batch key (without level) -> the clip buffers it is made from.
KEY_SOURCES: dict[str, tuple[str, ...]] = {
    "irradiance": ("radiance", "emission", "fbeta", "flags"),
    "fbeta_used": ("fbeta", "flags"),
}


def scale_problem(spec: str, scale: int) -> str:
    """'' when model ``spec`` (a name or ``pretrained:NAME``; a checkpoint path is checked when it loads) upscales
    by ``scale``, else one line saying which scales it takes."""
    scales = MODEL_SCALES.get(str(spec), None)
    if scales is None or int(scale) in scales:
        return ""
    what = "was trained for" if str(spec).startswith("pretrained:") else "takes"
    return f"{spec} {what} scale {' or '.join(map(str, scales))}, not {scale}"


def buffers_of_keys(keys) -> set[str]:
    """Clip buffers behind batch keys such as 'lr/irradiance', 'hr/normal', 'depth_ref' (lr_jitter needs none)."""
    out: set[str] = set()
    for k in keys:
        if k == "depth_ref":
            out.add("depth")
        elif "/" in k:
            name = k.split("/", 1)[1]
            out.update(KEY_SOURCES.get(name, (name,)))
    return out


def buffers_for_models(models) -> tuple[str, ...]:
    """The buffers to render for ``models`` (names, or 'name:checkpoint' as ``bench models`` takes them), in the
    canonical order, evaluation buffers included; ValueError naming an unknown model."""
    need = set(EVALUATION_BUFFERS)
    for m in models:
        name = m.split(":", 1)[0].strip()
        if name not in MODEL_BUFFERS:
            raise BlendSRError(f"--for-models: unknown model {name!r}; known: {', '.join(MODEL_BUFFERS)}")
        need.update(MODEL_BUFFERS[name])
    return tuple(b for b in ALL_BUFFERS if b in need)
