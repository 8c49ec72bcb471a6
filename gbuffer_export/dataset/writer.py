"""Write a dataset spec back as TOML (pure Python, no bpy): ``spec_to_toml(spec)`` gives a text that
``parse_spec(tomllib.loads(text))`` reads back into an equal spec, so a spec built in code (the add-on's panel) can
be saved as ``DATASET/spec.toml`` and re-run or extended with ``blendsr dataset DATASET/spec.toml -o DATASET``.

``[render]`` holds the first source's render settings; every source lists only the render keys where it differs.
Relative ``paths`` and ``hdri`` entries are written as given: they resolve against the folder of the file the text
is written to. TOML is written with ``tomli_w`` when it is installed (the ``[train]`` extra), else with the small
writer below (strings, booleans, integers, finite floats, arrays and inline tables: all a spec holds).
"""
from __future__ import annotations

import dataclasses
import math
import re

from .spec import DatasetSpec, RenderSettings, Source, Splits, Variation

_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")
_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


# ----------------------------------------------------------------------------------------------
# Spec -> TOML document (a dict of plain values)
# ----------------------------------------------------------------------------------------------

def render_table(r: RenderSettings, base: RenderSettings | None = None) -> dict:
    """The ``[render]`` keys of ``r`` (all of them, or only those differing from ``base``; TOML has no None: a key
    left at None is left out)."""
    out = {}
    for f in dataclasses.fields(RenderSettings):
        v = getattr(r, f.name)
        if base is not None and v == getattr(base, f.name):
            continue
        if v is None and f.name == "scales" and base is not None:
            v = [r.scale]  # one level, where [render] has several (read back as None)
        elif v is None:
            continue
        if f.name == "hr_size":
            v = f"{v[0]}x{v[1]}"
        elif f.name in ("buffers", "scales"):
            v = list(v)
        out[f.name] = v
    return out


def _pair(v) -> list:
    return [v[0], v[1]]


def _scene_keys(src: Source) -> dict:
    t = {"paths": list(src.paths), "clips_per_scene": src.clips_per_scene, "light": src.light,
         "regions": _pair(src.regions), "region_val": src.region_val, "region_test": src.region_test}
    var = src.variation or Variation()
    for k in ("world_strength", "light_strength", "sun_elevation_deg"):
        if getattr(var, k) is not None:
            t[k] = _pair(getattr(var, k))
    if var.hdri:
        t["hdri"] = list(var.hdri)
    if src.licence:
        t["licence"] = {k: dict(v) for k, v in src.licence.items()}
    return t


def _other_keys(src: Source) -> dict:
    t: dict = {}
    if src.kind == "builtin":
        t["seeds"] = _pair(src.seeds)
        t["sun"] = src.sun
        if src.props:
            t["props"] = list(src.props)
    else:
        t.update(paths=list(src.paths), clips_per_asset=src.clips_per_asset, clutter=src.clutter,
                 target_size_m=src.target_size_m)
        if src.licence:
            t["licence"] = {k: dict(v) for k, v in src.licence.items()}
    if src.environment.hdri:
        t["hdri"] = list(src.environment.hdri)
    t["hdri_strength"] = _pair(src.environment.strength)
    return t


def source_table(src: Source, base: RenderSettings) -> dict:
    """One ``[[source]]`` table: its keys, then the render keys where it differs from ``base``."""
    t = {"name": src.name, "kind": src.kind, "cameras": list(src.cameras)}
    if src.split is not None:
        t["split"] = src.split
    t.update(_scene_keys(src) if src.kind == "scene" else _other_keys(src))
    t.update(render_table(src.render, base))
    return t


def splits_table(s: Splits) -> dict:
    out = {"val": list(s.val), "test": list(s.test), "val_fraction": s.val_fraction,
           "test_fraction": s.test_fraction}
    for k in ("val_families", "test_families"):   # only when set: a spec written before them reads the same
        if getattr(s, k):
            out[k] = list(getattr(s, k))
    return out


def spec_to_dict(spec: DatasetSpec) -> dict:
    """The TOML document of ``spec`` as a dict (what ``tomllib.loads`` would give for the written text)."""
    base = spec.sources[0].render if spec.sources else RenderSettings()
    head = {"name": spec.name, "seed": spec.seed, **({"for_formats": list(spec.for_formats)} if spec.for_formats
                                                      else {})}
    return {"dataset": head, "render": render_table(base),
            "splits": splits_table(spec.splits), "source": [source_table(s, base) for s in spec.sources]}


def spec_to_toml(spec: DatasetSpec, header: str = "") -> str:
    """TOML text of ``spec`` (``header``: comment lines put first, each prefixed with ``# ``)."""
    head = "".join(f"# {line}".rstrip() + "\n" for line in header.splitlines())
    return head + dumps_toml(spec_to_dict(spec))


# ----------------------------------------------------------------------------------------------
# TOML text
# ----------------------------------------------------------------------------------------------

def dumps_toml(doc: dict) -> str:
    """``tomli_w.dumps(doc)`` when tomli-w is installed, else :func:`dumps_small`."""
    try:
        import tomli_w
    except ImportError:
        return dumps_small(doc)
    return tomli_w.dumps(doc)


def dumps_small(doc: dict) -> str:
    """TOML text of ``doc``: top-level scalars, then one ``[table]`` per dict and one ``[[table]]`` per list of
    dicts; deeper dicts are inline tables. ValueError on a value TOML cannot hold (None, non-finite floats)."""
    lines = [f"{_key(k)} = {_value(v)}" for k, v in doc.items() if not _is_table(v) and not _is_table_array(v)]
    for k, v in doc.items():
        if _is_table(v):
            lines += ["", f"[{_key(k)}]", *(f"{_key(a)} = {_value(b)}" for a, b in v.items())]
        elif _is_table_array(v):
            for t in v:
                lines += ["", f"[[{_key(k)}]]", *(f"{_key(a)} = {_value(b)}" for a, b in t.items())]
    return "\n".join(lines).lstrip("\n") + "\n"


def _is_table(v) -> bool:
    return isinstance(v, dict)


def _is_table_array(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _key(k: str) -> str:
    return k if _BARE_KEY.match(k) else _string(k)


def _string(s: str) -> str:
    out = []
    for c in s:
        if c in _ESCAPES:
            out.append(_ESCAPES[c])
        elif ord(c) < 0x20 or ord(c) == 0x7F:
            out.append(f"\\u{ord(c):04x}")
        else:
            out.append(c)
    return '"' + "".join(out) + '"'


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"TOML value {v!r}: only finite numbers are written")
        return repr(v)
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + "}"
    raise ValueError(f"TOML value {v!r}: a {type(v).__name__} cannot be written")
