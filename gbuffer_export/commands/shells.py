"""The file-writing half of the shells derived from ``RenderConfig`` (``gbuffer_export.table_shells`` holds the
derivations): the add-on's render keys and menus and the docs' render-key table. ``make generate``
(``training.commands.generate``) writes them with every other derived file; a test fails while one is stale."""
from __future__ import annotations

import json
from pathlib import Path

from ..table_shells import CONFIG_DOC, DOC_BEGIN, DOC_END, ROOT, render_keys_doc, render_property_table, replace_between

#: The add-on's copy of the render keys it derives properties from (the add-on never imports the library when it
#: registers, so it reads this file).
ADDON_TABLE = ROOT / "blender_addon" / "render_keys.json"
#: The add-on's menus and checkboxes (``addon_choices``), read without importing the library.
ADDON_CHOICES = ROOT / "blender_addon" / "choices.json"


def addon_choices() -> dict:
    """What the add-on's menus and checkboxes offer, from the one place each lives: camera paths
    (``config.CAMERA_PATHS`` and ``scene:*``; ``LEVEL_CAMERA_PATHS``), buffers (``conventions.BUFFERS``, ``DEFAULT_BUFFERS``), models
    (the model-buffer table's, for *For models*), the integer scales the fixed-scale models take (its
    ``scales``; any-scale models take these too) and the export formats with what each needs (*For formats*,
    ``format_limits``)."""
    from ..config import CAMERA_PATHS, LEVEL_CAMERA_PATHS
    from ..conventions import BUFFERS, DEFAULT_BUFFERS
    from ..dataset.buffers import MODEL_BUFFERS, MODEL_SCALES
    from ..format_limits import FORMATS
    scales = sorted({k for v in MODEL_SCALES.values() if v for k in v})
    return {"camera_paths": [*CAMERA_PATHS, "scene:*"], "level_camera_paths": list(LEVEL_CAMERA_PATHS),
            "buffers": [{"name": b.name, "help": b.meaning} for b in BUFFERS.values()],
            "default_buffers": list(DEFAULT_BUFFERS), "models": list(MODEL_BUFFERS), "scales": scales,
            "formats": [{"name": f.name, "title": f.title, "needs": f.needs()} for f in FORMATS.values()]}


def derived_files() -> dict[Path, str]:
    """{path: the text it should hold} of every file derived from RenderConfig and the conventions."""
    table = json.dumps(render_property_table(), indent=1) + "\n"
    doc = replace_between(CONFIG_DOC.read_text(), DOC_BEGIN, DOC_END, render_keys_doc())
    return {ADDON_TABLE: table, CONFIG_DOC: doc, ADDON_CHOICES: json.dumps(addon_choices(), indent=1) + "\n"}
