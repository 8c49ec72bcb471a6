"""``python -m training.commands.generate`` (``make generate``): rewrite every derived file of the repository in one command.

Derived files are written from one source each and never edited by hand; a test per file fails when it is stale.
This command runs every generator in order (``GENERATORS``); ``--check`` writes nothing and exits 1 naming each stale
file. It lives in the torch layer because two of its generators read the models and the training configuration.

| generator | source | writes |
|---|---|---|
| render shells | ``RenderConfig``, the conventions | ``blender_addon/render_keys.json``, ``choices.json``, docs/configuration.md's render keys |
| training tables | the training configuration's sections | docs/configuration.md's training tables |
| model tables | every model's ``needs()``, ``SCALES`` and shipped weights | ``gbuffer_export/dataset/model_buffers.json`` |
| model cards | each shipped weights JSON, ../shared/scenes/README.md's licences | ``docs/models/cards/*.md`` |
| results page | ``docs/bench/results_page.toml`` and the records it names | ``docs/results.md`` |
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def render_shells() -> dict[Path, str]:
    from gbuffer_export.commands.shells import derived_files
    return derived_files()


def training_tables() -> dict[Path, str]:
    from training.commands.config_tables import derived_doc
    from gbuffer_export.table_shells import CONFIG_DOC
    # the render-key block of the same file is the render shells' part: start from their text
    text = render_shells()[CONFIG_DOC]
    return {Path(CONFIG_DOC): derived_doc(text)}


def model_tables() -> dict[Path, str]:
    from training.commands.buffer_table import model_buffer_table, model_scale_table
    from gbuffer_export.dataset.buffers import TABLE_PATH
    table = {"generated_by": "make generate", "models": model_buffer_table(),
             "scales": model_scale_table()}
    return {Path(TABLE_PATH): json.dumps(table, indent=1) + "\n"}


def model_cards() -> dict[Path, str]:
    from training.commands.model_cards import cards
    return cards()


def results_page() -> dict[Path, str]:
    from gbuffer_export.results_page import PAGE, page_text
    return {PAGE: page_text()}


GENERATORS = {"render shells": render_shells, "training tables": training_tables, "model tables": model_tables,
              "model cards": model_cards, "results page": results_page}


def derived() -> dict[Path, str]:
    """{path: the text it should hold} of every derived file; a later generator's text for a path overrides an
    earlier one's (the training tables start from the render shells' docs/configuration.md)."""
    files: dict[Path, str] = {}
    for make in GENERATORS.values():
        files.update(make())
    return files


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m training.commands.generate",
                                     description="Rewrite every derived file (render shells, training and model tables, "
                                                 "the results page) from its one source.")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 naming each stale file")
    args = parser.parse_args(argv)
    from gbuffer_export.results_page import PageError
    try:
        files = derived()
    except PageError as exc:
        print(f"generate: error: {exc}", file=sys.stderr)
        return 2
    stale = [p for p, text in files.items() if not p.is_file() or p.read_text() != text]
    if args.check:
        for p in stale:
            print(f"stale: {p} (run make generate)")
        return 1 if stale else 0
    for p in stale:
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(f".{p.name}.tmp")
        tmp.write_text(files[p])
        tmp.replace(p)
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
