"""The add-on's render settings derived from ``RenderConfig``'s fields: ``render_keys.json`` (written by
``make generate`` from each field's type, default, choices, range, label, help and unit;
a test fails while it is stale) is read here, because the add-on never imports the library when it registers.

A key whose rule names the shell ``clip_panel`` becomes a property of ``Scene.blendsr`` (the clip export) and one
that names ``dataset_panel`` a property of ``Scene.blendsr.dataset`` (a key of the dataset spec's ``[render]``
table); ``mapping`` hands them to the library, and the panels draw the ones they do not place themselves. No bpy at
import (bpy.props is imported where a property is made).
"""
from __future__ import annotations

import json
from pathlib import Path

CLIP_PANEL, DATASET_PANEL = "clip_panel", "dataset_panel"
TABLE: dict[str, dict] = {e["name"]: e for e in json.loads((Path(__file__).parent / "render_keys.json").read_text())}
#: Properties named otherwise than their key (saved .blend files keep the name they were written with).
ALIASES = {"fbeta": "fbeta_source"}


def prop_name(key: str) -> str:
    return ALIASES.get(key, key)


def keys(shell: str) -> list[str]:
    """The keys the shell derives, in ``RenderConfig``'s field order."""
    return [k for k, e in TABLE.items() if shell in e["shells"]]


def _description(e: dict) -> str:
    text = e["help"][:1].upper() + e["help"][1:]
    return f"{text} ({e['unit']})" if e["unit"] and e["unit"] not in text else text


def render_property(key: str):
    """The Blender property of the render key ``key``: its type, default, range or items, label and help."""
    from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty
    e = TABLE[key]
    kw = {"name": e["label"], "description": _description(e), "default": e["default"]}
    bounds = {k: e[k] for k in ("min", "max") if k in e}
    if e["kind"] == "int":
        return IntProperty(**kw, **{k: int(v) for k, v in bounds.items()})
    if e["kind"] == "float":
        return FloatProperty(**kw, **bounds, precision=4)
    if e["kind"] == "bool":
        return BoolProperty(**kw)
    if e["kind"] == "enum":
        items = tuple((c, c.replace("-", " ").capitalize(), kw["description"]) for c in e["items"])
        return EnumProperty(items=items, **kw)
    return StringProperty(**kw)  # text: read back by the library's value_from_text (a union, a list, none)


def properties(shell: str) -> dict:
    """{property name: property} of the keys ``shell`` derives."""
    return {prop_name(k): render_property(k) for k in keys(shell)}


def value(settings, key: str):
    """The value of ``key`` in the settings as ``RenderConfig`` takes it: a float property (float32) as the shortest
    decimal it came from (0.01, not 0.009999999776), text read as the key's type. Needs the library."""
    v = getattr(settings, prop_name(key))
    kind = TABLE[key]["kind"]
    if kind == "float":
        return float(f"{v:.7g}")
    if kind == "text":
        import typing

        from gbuffer_export.config import RenderConfig
        from gbuffer_export.table_shells import value_from_text
        return value_from_text(v, typing.get_type_hints(RenderConfig)[key], key)
    return v


def values(settings, shell: str) -> dict:
    """{key: value} of every key ``shell`` derives."""
    return {k: value(settings, k) for k in keys(shell)}


#: The menus' and checkboxes' choices (``choices.json``, written with ``render_keys.json`` by
#: ``make generate``): camera paths, buffers, default buffers, models, scales.
CHOICES: dict = json.loads((Path(__file__).parent / "choices.json").read_text())


def flag_list(selected, order) -> list[str]:
    """The members of an enum-flag value (a set) in the items' order (``order``: the identifiers)."""
    return [k for k in order if k in selected]
