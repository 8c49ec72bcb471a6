"""Derive the core's model -> clip buffers table from every model's ``needs()``, and its model -> scales table
from every model's ``SCALES`` and shipped weights (torch layer).

``blendsr dataset/render --for-models`` must work without torch, so the core reads the table from
``gbuffer_export/dataset/model_buffers.json``; this module writes that file from the models themselves (each with
its default configuration and, when shipped, its ``pretrained:NAME`` weights' configuration), and ``tests/dataset/test_dataset.py`` fails when the file is stale. After adding a model or
changing what one reads: ``make generate``.
"""
from __future__ import annotations

from pathlib import Path

from gbuffer_export.clip import write_json_atomic
from gbuffer_export.conventions import ALL_BUFFERS
from gbuffer_export.dataset.buffers import TABLE_PATH, buffers_of_keys


def model_buffer_table() -> dict[str, list[str]]:
    """model name (in ``MODELS`` order) -> the clip buffers its default configuration reads, and those its shipped
    weights' configuration reads (``pretrained:NAME``, when shipped), in canonical order."""
    from training.config import ModelConfig
    from training.inference.loading import load_model
    from training.models import MODELS, build_model
    from training.pretrained import PREFIX, PRETRAINED
    table = {}
    for name in MODELS:
        keys = set(build_model(ModelConfig(name=name, scale=4), 4).needs())
        if name in PRETRAINED:
            keys |= set(load_model(PREFIX + name, 4).module.needs())
        need = buffers_of_keys(keys)
        table[name] = [b for b in ALL_BUFFERS if b in need]
    return table


def model_scale_table() -> dict[str, list[int] | None]:
    """model name and ``pretrained:NAME`` -> the integer scales it upscales by (None: any scale; a model's
    ``SCALES``; shipped weights of a fixed-scale model: only the scale they were trained for)."""
    from training.models import MODELS, model_class
    from training.pretrained import PREFIX, PRETRAINED, info
    table: dict[str, list[int] | None] = {}
    for name in MODELS:
        scales = model_class(name).SCALES
        table[name] = None if scales is None else sorted(scales)
    for name in PRETRAINED:
        table[PREFIX + name] = None if table[name] is None else [int(info(name)["scale"])]
    return table


def write_table(path: Path = TABLE_PATH) -> dict[str, list[str]]:
    """Write ``model_buffer_table()`` and ``model_scale_table()`` to ``path`` (atomic); return the buffer table."""
    table = model_buffer_table()
    write_json_atomic(path, {"generated_by": "make generate", "models": table,
                             "scales": model_scale_table()})
    return table


if __name__ == "__main__":
    print(f"{TABLE_PATH}: {len(write_table())} models")
