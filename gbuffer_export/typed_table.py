"""One typed-table helper for every configuration and spec (pure Python, no bpy, no torch).

A table is a dataclass: each field's annotation is its type (``int``, ``float``, ``bool``, ``str``, ``list[X]``,
``tuple[X, ...]``, ``X | None``, a word or a number such as ``str | float``; ``Any`` is left to the class) and
``option(...)`` adds its rule (range, choices, allowed items, a ``[low, high]`` pair) and what the shells derive
from it (help, unit, label, shells; ``gbuffer_export.table_shells``). ``from_table`` parses a TOML table into the dataclass (frozen or not):
unknown keys, wrong types and values out of range are one-line errors that name the config key (``data.crop``,
``render.hr_spp``); ``set_checked`` checks an instance built in code (``RenderConfig(hr_spp=0)``). Rules that tie
several keys together stay in the class (``validate``).

Messages name keys, never command-line flags: ``ConfigError.key`` lets a shell (the CLI) name its own flag instead
(``gbuffer_export.commands.flags_named``). Used by ``gbuffer_export.config``, ``gbuffer_export.dataset.spec``,
``training.config`` and ``training.models.options``.
"""
from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass
from typing import Any, get_args, get_origin, get_type_hints

from .errors import BlendSRError

RULE = "blendsr_rule"


class _AsDefault:
    def __repr__(self) -> str:
        return "AS_DEFAULT"


#: ``Rule.legacy`` when data written before the key was made as its default makes it.
AS_DEFAULT = _AsDefault()


class ConfigError(BlendSRError):
    """An invalid configuration value; the message names the key. ``key``: the key's path (``data.crop``), None
    for a message about several keys; ``detail``: the message after the key (a shell may put its flag there)."""

    def __init__(self, message: str, key: str | None = None, detail: str | None = None):
        super().__init__(message)
        self.key, self.detail = key, detail


@dataclass(frozen=True)
class Rule:
    """A key's checks beyond its type. ``lo``/``hi``: inclusive bounds (``lo_open``/``hi_open``: exclusive);
    ``choices``: allowed values; ``items``: allowed items of a list; ``unique``: no repeated item; ``pair``: a
    ``[low, high]`` with 0 < low <= high (one number x means [x, x]); ``why``: appended to a range message.

    What the shells derive from the field (``gbuffer_export.table_shells``): ``help``, what the key means (a CLI
    flag's help, an add-on property's tooltip, the docs' table); ``unit`` (e.g. "pixels"); ``label``, a panel's short
    name (default: the key); ``metavar``, the CLI's name of the value; ``shells``, the shells that derive the key
    from the field (None: every shell of its table; ``()``: each shell writes it by hand); ``legacy``, what data
    written before the key existed was made with (default: the field's default)."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple | None = None
    items: tuple | None = None
    unique: bool = False
    pair: bool = False
    unit: str = ""
    why: str = ""
    help: str = ""
    label: str = ""
    metavar: str = ""
    shells: tuple[str, ...] | None = None
    legacy: Any = AS_DEFAULT


def option(default=dataclasses.MISSING, *, factory=dataclasses.MISSING, **rule) -> Any:
    """A dataclass field with a ``Rule`` (keyword arguments: ``Rule``'s fields); ``factory`` for a mutable default."""
    return dataclasses.field(default=default, default_factory=factory, metadata={RULE: Rule(**rule)})


def rule_of(f: dataclasses.Field) -> Rule:
    return f.metadata.get(RULE, Rule())


def _path(where: str, name: str) -> str:
    return f"{where}.{name}" if where else name


def key_error(path: str, value, detail: str, error=ConfigError, prefix: str = "") -> ConfigError:
    """``error`` with the message ``PREFIX PATH VALUE: DETAIL`` (``prefix``: e.g. the spec file, ``"spec.toml: "``)."""
    return error(f"{prefix}{path} {value!r}: {detail}", key=path, detail=f"{value!r}: {detail}")


# ----------------------------------------------------------------------------------------------
# Types
# ----------------------------------------------------------------------------------------------

_KINDS = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}


def coerce(path: str, value, typ, error=ConfigError, prefix: str = ""):
    """``value`` checked against the annotation ``typ`` (an int is accepted as a float; a bool is never a number;
    a list or tuple becomes the annotated container)."""
    origin, args = get_origin(typ), get_args(typ)
    if typ is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        for typ_ in inner[:-1]:  # int | float: the first that takes the value, else the last one's error
            try:
                return coerce(path, value, typ_, error, prefix)
            except BlendSRError:
                pass
        return coerce(path, value, inner[-1], error, prefix)
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise error(f"{prefix}{path}: expected a list, got {value!r}", key=path, detail="expected a list")
        item = args[0] if args else Any
        if origin is tuple and args and (len(args) != 2 or args[1] is not Ellipsis):  # tuple[int, int]: fixed
            if len(value) != len(args):
                raise error(f"{prefix}{path}: expected {len(args)} items, got {value!r}", key=path)
            return tuple(coerce(f"{path}[{i}]", v, a, error, prefix) for i, (v, a) in enumerate(zip(value, args)))
        out = [coerce(f"{path}[{i}]", v, item, error, prefix) for i, v in enumerate(value)]
        return tuple(out) if origin is tuple else out
    if typ in _KINDS:
        ok = isinstance(value, typ) and (typ is bool or not isinstance(value, bool))
        if typ is float and isinstance(value, int) and not isinstance(value, bool):
            return float(value)
        if not ok:
            raise error(f"{prefix}{path}: expected {_KINDS[typ]}, got {value!r}", key=path,
                        detail=f"expected {_KINDS[typ]}")
        return value
    return value  # another class (a nested table): left to its owner


# ----------------------------------------------------------------------------------------------
# Rules
# ----------------------------------------------------------------------------------------------

def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else f"{x:g}"


def _bounds_text(r: Rule, integer: bool) -> str:
    lo, hi = (_num(x) if x is not None else None for x in (r.lo, r.hi))
    if integer and lo is not None and hi is not None and not (r.lo_open or r.hi_open):
        return f"must be an integer in {lo}..{hi}"
    if integer and r.lo == 1 and r.hi is None:
        return "must be a positive integer"
    if lo is not None and hi is not None:
        return f"must lie in {'(' if r.lo_open else '['}{lo}, {hi}{')' if r.hi_open else ']'}"
    if lo is not None:
        return f"must be {'an integer' if integer else 'a number'} {'>' if r.lo_open else '>='} {lo}"
    return f"must be {'<' if r.hi_open else '<='} {hi}"


def _in_bounds(v: float, r: Rule) -> bool:
    if r.lo is not None and (v <= r.lo if r.lo_open else v < r.lo):
        return False
    return r.hi is None or (v < r.hi if r.hi_open else v <= r.hi)


def _pair(path: str, v, error, prefix: str) -> list[float]:
    """A [low, high] of finite numbers with 0 < low <= high; one number x is [x, x]."""
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        v = [v, v]
    if not (isinstance(v, (list, tuple)) and len(v) == 2
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
        raise key_error(path, v, "expected [low, high]", error, prefix)
    lo, hi = float(v[0]), float(v[1])
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
        raise key_error(path, v, "need 0 < low <= high (finite)", error, prefix)
    return [lo, hi]


def check(path: str, value, r: Rule, error=ConfigError, prefix: str = ""):
    """``value`` (already typed) against the rule ``r``; returns it (a pair as two floats)."""
    if value is None:
        return value
    numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
    if r.choices is not None and value not in r.choices and not (numeric and all(isinstance(c, str) for c in
                                                                                  r.choices)):
        # (a number where the choices are words: a "word or number" key such as "auto" | float, bounds below)
        raise key_error(path, value, f"choose one of {', '.join(map(str, r.choices))}", error, prefix)
    if r.items is not None:
        for x in value:
            if x not in r.items:
                raise error(f"{prefix}{path} item {x!r}: choose one of {', '.join(map(str, r.items))}", key=path)
    if r.unique and len(set(value)) != len(value):
        raise key_error(path, value, "an item is repeated", error, prefix)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if isinstance(value, float) and not math.isfinite(value):
            raise key_error(path, value, "must be a finite number", error, prefix)
        if (r.lo is not None or r.hi is not None) and not _in_bounds(value, r):
            text = _bounds_text(r, isinstance(value, int))
            raise key_error(path, value, f"{text}{' ' + r.why if r.why else ''}", error, prefix)
    return value


def _is_tuple(typ) -> bool:
    """``typ`` is a tuple annotation, or ``tuple[...] | None``."""
    if get_origin(typ) in (typing.Union, types.UnionType):
        return any(_is_tuple(a) for a in get_args(typ))
    return get_origin(typ) is tuple


def typed_value(path: str, value, typ, r: Rule, error=ConfigError, prefix: str = ""):
    """``value`` type-checked against ``typ`` and then checked against ``r``: the one check of one key. A pair
    (``r.pair``) becomes two floats, a tuple when ``typ`` is one."""
    if r.pair:
        if value is None:
            return None
        lo_hi = _pair(path, value, error, prefix)
        return tuple(lo_hi) if _is_tuple(typ) else lo_hi
    return check(path, coerce(path, value, typ, error, prefix), r, error, prefix)


# ----------------------------------------------------------------------------------------------
# Tables
# ----------------------------------------------------------------------------------------------

def legacy_values(cls, names) -> dict[str, Any]:
    """{key: what data written before the key existed was made with} (``Rule.legacy``, else the field's default)."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    out = {}
    for name in names:
        f, r = fields[name], fields_of(cls)[name][1]
        if r.legacy is not AS_DEFAULT:
            out[name] = r.legacy
        elif f.default is not dataclasses.MISSING:
            out[name] = f.default
        else:
            out[name] = f.default_factory()
    return out


def fields_of(cls) -> dict[str, tuple[Any, Rule]]:
    """{name: (annotation, rule)} of the dataclass ``cls``, in field order."""
    hints = get_type_hints(cls)
    return {f.name: (hints[f.name], rule_of(f)) for f in dataclasses.fields(cls) if f.init}


def check_keys(table: dict, known, where: str, error=ConfigError, prefix: str = "", also: str = "",
               empty: str = "known: none") -> None:
    """An error naming the first unknown key of ``table`` (``where.key``) and the known ones (``also``: more
    words after them; ``empty``: the words when no key is known)."""
    unknown = [k for k in table if k not in known]
    if unknown:
        path = _path(where, unknown[0])
        listed = f"known: {', '.join(known)}{also}" if known else empty
        raise error(f"{prefix}unknown key {path} ({listed})", key=path)


def from_table(cls, table: dict, where: str = "", *, error=ConfigError, prefix: str = "", base=None,
               empty: str = "known: none"):
    """An instance of the dataclass ``cls`` from the TOML table ``table`` (``where``: its name in messages):
    unknown keys refused (``empty``: the message's ending for a class without fields), each key type-checked and
    checked against its rule; keys absent take ``base``'s values (default: the class's defaults)."""
    if not isinstance(table, dict):
        raise error(f"{prefix}[{where}] must be a table", key=where)
    spec = fields_of(cls)
    check_keys(table, list(spec), where, error, prefix, empty=empty)
    values = {}
    for name, value in table.items():
        typ, r = spec[name]
        path = _path(where, name)
        values[name] = typed_value(path, value, typ, r, error, prefix)
    return dataclasses.replace(base, **values) if base is not None else cls(**values)


def checked_values(obj, where: str = "", *, error=ConfigError, prefix: str = "", names=None) -> dict[str, Any]:
    """{name: value} of ``obj``'s fields (``names``: only those) after the type and rule checks, normalised (an
    int where a float is declared becomes a float, a pair two floats). The caller sets them back."""
    spec = fields_of(type(obj))
    out = {}
    for name in names if names is not None else spec:
        typ, r = spec[name]
        path = _path(where, name)
        out[name] = typed_value(path, getattr(obj, name), typ, r, error, prefix)
    return out


def set_checked(obj, where: str = "", **kw) -> None:
    """``checked_values`` written back onto ``obj`` (frozen dataclasses too: for their ``__post_init__``)."""
    for name, value in checked_values(obj, where, **kw).items():
        object.__setattr__(obj, name, value)
