"""``python -m gbuffer_export.commands.generate``: rewrite every derived file of the repository in one command.

Derived files are written from one source each and never edited by hand; a test per file fails when it is stale.
This command runs every generator in order (``GENERATORS``); ``--check`` writes nothing and exits 1 naming each stale
file (what ``make generate-check`` runs). Generators of the torch layer (the training tables, the model table) are
imported inside their function, so the core's part runs without torch; without torch they are reported as skipped.

| generator | source | writes |
|---|---|---|
| render shells | ``RenderConfig``, the conventions | ``blender_addon/render_keys.json``, ``choices.json``, docs/configuration.md's render keys |
| training tables | the training configuration's sections | docs/configuration.md's training tables |
| model tables | every model's ``needs()``, ``SCALES`` and shipped weights | ``gbuffer_export/dataset/model_buffers.json`` |
| results page | ``docs/bench/results_page.toml`` and the records it names | ``docs/results.md`` |
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path


def render_shells() -> dict[Path, str]:
    from ..table_shells import derived_files
    return derived_files()


def training_tables() -> dict[Path, str]:
    from training.config_tables import derived_doc
    from ..table_shells import CONFIG_DOC
    # the render-key block of the same file is the render shells' part: start from their text
    text = render_shells()[CONFIG_DOC]
    return {Path(CONFIG_DOC): derived_doc(text)}


def model_tables() -> dict[Path, str]:
    from training.buffer_table import model_buffer_table, model_scale_table
    from ..dataset.buffers import TABLE_PATH
    table = {"generated_by": "python -m training.buffer_table", "models": model_buffer_table(),
             "scales": model_scale_table()}
    return {Path(TABLE_PATH): json.dumps(table, indent=1) + "\n"}


def results_page() -> dict[Path, str]:
    from ..results_page import PAGE, page_text
    return {PAGE: page_text()}


GENERATORS = {"render shells": (render_shells, False), "training tables": (training_tables, True),
              "model tables": (model_tables, True), "results page": (results_page, False)}


def derived() -> tuple[dict[Path, str], list[str]]:
    """{path: the text it should hold} of every derived file this environment can build, and the generators skipped
    (those that need torch where it is missing). A later generator's text for a path overrides an earlier one's."""
    files: dict[Path, str] = {}
    skipped = []
    have_torch = importlib.util.find_spec("torch") is not None
    for name, (make, needs_torch) in GENERATORS.items():
        if needs_torch and not have_torch:
            skipped.append(name)
            continue
        files.update(make())
    return files, skipped


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m gbuffer_export.commands.generate",
                                     description="Rewrite every derived file (render shells, training and model tables, "
                                                 "the results page) from its one source.")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 naming each stale file")
    args = parser.parse_args(argv)
    from ..results_page import PageError
    try:
        files, skipped = derived()
    except PageError as exc:
        print(f"generate: error: {exc}", file=sys.stderr)
        return 2
    stale = [p for p, text in files.items() if not p.is_file() or p.read_text() != text]
    for name in skipped:
        print(f"generate: skipped {name} (needs torch: pip install '.[train]')", file=sys.stderr)
    if args.check:
        for p in stale:
            print(f"stale: {p} (run python -m gbuffer_export.commands.generate)")
        return 1 if stale else 0
    for p in stale:
        tmp = p.with_name(f".{p.name}.tmp")
        tmp.write_text(files[p])
        tmp.replace(p)
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
