"""Derive the core's model -> clip buffers table from every model's ``needs()`` (torch layer).

``blendsr dataset/render --for-models`` must work without torch, so the core reads the table from
``gbuffer_export/dataset/model_buffers.json``; this module writes that file from the models themselves (each with
its default configuration), and ``tests/test_dataset.py`` fails when the file is stale. After adding a model or
changing what one reads: ``python -m training.models.buffer_table``.
"""
from __future__ import annotations

from pathlib import Path

from gbuffer_export.clip import write_json_atomic
from gbuffer_export.conventions import ALL_BUFFERS
from gbuffer_export.dataset.buffers import TABLE_PATH, buffers_of_keys


def model_buffer_table() -> dict[str, list[str]]:
    """model name (in ``MODELS`` order) -> the clip buffers its default configuration reads, in canonical order."""
    from training.config import ModelConfig
    from training.models import MODELS, build_model
    table = {}
    for name in MODELS:
        need = buffers_of_keys(build_model(ModelConfig(name=name, scale=4), 4).needs())
        table[name] = [b for b in ALL_BUFFERS if b in need]
    return table


def write_table(path: Path = TABLE_PATH) -> dict[str, list[str]]:
    """Write ``model_buffer_table()`` to ``path`` (atomic) and return it."""
    table = model_buffer_table()
    write_json_atomic(path, {"generated_by": "python -m training.models.buffer_table", "models": table})
    return table


if __name__ == "__main__":
    print(f"{TABLE_PATH}: {len(write_table())} models")
