"""The dataset spec: a typed, validated description of many clips (pure Python, no bpy, no torch).

A spec is a TOML file (``examples/dataset_small.toml``) with a ``[dataset]`` table, a ``[render]`` table of
defaults, a ``[splits]`` table and one ``[[source]]`` table per source. :func:`load_spec` parses and validates it
(unknown keys are rejected with the known ones listed); :func:`expand` turns it into the explicit list of
:class:`ClipJob` that ``dataset.json`` records: every random choice (seed, environment, its rotation and strength,
clutter, camera path) is drawn here from a per-clip seed, so the same spec gives the same clips on any executor.

Splits are assigned per scene (a built-in seed) or per asset, never per frame: an asset in the test split is
never rendered into a training clip, not even as clutter.
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import tomllib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import get_type_hints

from ..config import LIGHTS, SCENE_SUFFIXES, SPEC, ConfigError, RenderConfig, camera_path_ok, parse_size
from ..conventions import parse_buffer_list
from ..table_shells import default_of, shell_keys
from ..typed_table import legacy_values
from ..typed_table import Rule, check_keys, fields_of, option, typed_value
from .families import (BUILTIN_FAMILIES, CAMERA_FAMILIES, builtin_family, check_family_id, family_group, hdri_family,
                       held_split, leak)

SPLITS = ("train", "val", "test")
SOURCE_KINDS = ("builtin", "assets", "scene")
ASSET_SUFFIXES = (".gltf", ".glb", ".blend")
#: bpy's bundled environments (``studiolights/world/<name>.exr``), usable as ``hdri = ["builtin:courtyard"]``.
BUILTIN_HDRIS = ("city", "courtyard", "forest", "interior", "night", "studio", "sunrise", "sunset")
#: Camera kinds a source may draw from; ``scene`` keeps the built-in scene's own designed camera (builtin only).
SOURCE_CAMERAS = ("orbit", "walk", "scene")
#: Opt-in props of the built-in scene (``props = [...]`` of a builtin source; the bpy layer's ``OPTIONAL_PROPS``):
#: the built-in generator's families (``families.BUILTIN_FAMILIES``), each drawn from a random stream of its own.
BUILTIN_PROPS = tuple(BUILTIN_FAMILIES)
#: Camera kinds of ``kind = "scene"`` sources: inside the level (walk, fly), around it (orbit), or the file's own
#: cameras (scene: the active one; scene:*: each clip the next of the file's cameras by name; scene:NAME).
SCENE_SOURCE_CAMERAS = ("walk", "fly", "orbit", "scene", "scene:*", "scene:NAME")
HDRI_SUFFIXES = (".hdr", ".exr")


class SpecError(ConfigError):
    """An invalid dataset spec; the message names the file and the key."""


#: The most clips one spec may expand to (checked from the seed ranges, clips per asset/scene and the number of
#: assets before anything is expanded): a larger dataset is several specs.
MAX_CLIPS = 100_000


# ----------------------------------------------------------------------------------------------
# Typed tables
# ----------------------------------------------------------------------------------------------

#: The per-clip render keys of a spec (``[render]``, overridable in each ``[[source]]``): ``frames`` (the clip's
#: length: frames 1..frames), then the keys of ``RenderConfig`` (the one render-settings class) whose rule names the
#: spec among its shells (``Rule.shells``), with its defaults: a new RenderConfig key is a spec key unless it says not.
RENDER_KEYS = ("frames", *shell_keys(RenderConfig, SPEC))
#: What datasets and job files written before a key were rendered with (an index entry or a job without the key reads
#: as this): the key's ``Rule.legacy`` (hr_fbeta: "point", before 2026-11-26), else its default.
LEGACY_RENDER_KEYS = {k: list(v) if isinstance(v, tuple) else v
                      for k, v in legacy_values(RenderConfig, RENDER_KEYS[1:]).items()}
#: RenderConfig's defaults (a source's ``light`` is its key).
RENDER_DEFAULTS = {f.name: default_of(f) for f in dataclasses.fields(RenderConfig)}
#: What a spec needs that a render of a scene file takes from the file: the clip's length and HR size (pixels).
#: ``threads`` 0 means the machine's cores divided by the local workers (``RunOptions.clip_threads``).
CLIP_DEFAULTS = {"frames": 12, "hr_size": (256, 144)}


def _render_settings_class():
    """``RenderSettings``, generated from ``RenderConfig``: its keys in ``RENDER_KEYS`` with its types, rules and
    defaults (one set of defaults), ``frames`` and ``hr_size`` with ``CLIP_DEFAULTS``, ``scale`` an integer."""
    fields, hints = {f.name: f for f in dataclasses.fields(RenderConfig)}, get_type_hints(RenderConfig)
    own = {"frames": (int, option(CLIP_DEFAULTS["frames"], lo=1)),
           "hr_size": (tuple[int, int], dataclasses.field(default=CLIP_DEFAULTS["hr_size"])),
           "scale": (int, option(fields["scale"].default, lo=1))}
    spec = [(k, *own[k]) if k in own else (k, hints[k], dataclasses.field(default=fields[k].default,
                                                                          metadata=fields[k].metadata))
            for k in RENDER_KEYS]

    def to_json(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}
    cls = dataclasses.make_dataclass("RenderSettings", spec, frozen=True, namespace={"to_json": to_json})
    cls.__module__ = __name__
    cls.__doc__ = ("A clip's render settings in a spec (``[render]`` defaults, overridable per source): the keys "
                   "``RENDER_KEYS`` of ``RenderConfig`` with its defaults; ``frames`` frames per clip (rendered as "
                   "1..frames), ``hr_size`` (W, H) pixels.")
    return cls


RenderSettings = _render_settings_class()


@dataclass(frozen=True)
class Environment:
    """How a source lights its clips: an HDRI drawn from ``hdri`` (files, folders of .hdr/.exr, or
    ``builtin:NAME`` for bpy's bundled ones), rotated about +Z uniformly in [0, 360) degrees, its strength drawn
    log-uniformly in ``strength`` (a multiplier of the file's radiance)."""

    hdri: tuple[str, ...] = ()
    strength: tuple[float, float] = (0.7, 1.5)


@dataclass(frozen=True)
class Source:
    """One ``[[source]]``: ``kind = "builtin"`` (the built-in scene over ``seeds``) or ``kind = "assets"``
    (each glTF/GLB/.blend in ``paths`` placed in a generated environment, ``clips_per_asset`` clips each)."""

    name: str
    kind: str
    render: RenderSettings
    cameras: tuple[str, ...] = ("orbit",)
    split: str | None = option(None, choices=SPLITS)  # force every scene of this source into one split
    seeds: tuple[int, int] = (0, 0)               # builtin: inclusive range
    paths: tuple[str, ...] = ()                   # assets: files or folders
    clips_per_asset: int = option(1, lo=1)
    environment: Environment = Environment()
    clutter: int = option(0, lo=0)                # assets: up to N other assets of the same split around it
    target_size_m: float = option(1.5, lo=0, lo_open=True, unit="m")  # assets: largest side after normalisation
    licence: dict = field(default_factory=dict)   # assets: stem -> {"licence": ..., "attribution": ...}
    sun: bool = True                              # builtin: keep the sun lamp
    props: tuple[str, ...] = option((), items=BUILTIN_PROPS, unique=True)  # builtin: opt-in props added to every clip
    clips_per_scene: int = option(4, lo=1)        # scene: clips per scene file
    light: str = option(RENDER_DEFAULTS["light"], choices=LIGHTS)  # scene: RenderConfig's light (its default)
    regions: tuple[int, int] = (1, 1)             # scene: grid of split regions over the level's content box
    region_val: int = option(0, lo=0)             # scene: grid cells whose clips are val
    region_test: int = option(0, lo=0)            # scene: grid cells whose clips are test
    variation: "Variation" = None                 # scene: opt-in changes of light (None: the file's light as is)


@dataclass(frozen=True)
class Variation:
    """Opt-in, recorded variation of a scene's light that keeps its look (``kind = "scene"``): multipliers drawn
    log-uniformly in ``world_strength`` (the world's background strength) and ``light_strength`` (every lamp's
    energy); ``sun_elevation_deg``: the sun lamps' (and an added sky's) elevation drawn uniformly, azimuth
    uniformly in [0, 360); ``hdri``: a replacement pool for a world that is an environment texture, rotated
    uniformly about +Z. Empty ranges / pools: unchanged."""

    world_strength: tuple[float, float] | None = None
    light_strength: tuple[float, float] | None = None
    sun_elevation_deg: tuple[float, float] | None = None
    hdri: tuple[str, ...] = ()


@dataclass(frozen=True)
class Splits:
    """Split rule: explicit ``val``/``test`` lists of scene ids (asset stems, or ``builtin:SEED``), and for the
    rest a stable hash rule with fractions ``val_fraction`` and ``test_fraction`` (0 = everything else trains).
    ``val_families``/``test_families``: held-out families (``families.py``: ``asset:STEM``, ``level:STEM``,
    ``hdri:NAME``, ``material:voronoi``, ...) that no clip of an earlier split may hold or draw."""

    val: tuple[str, ...] = ()
    test: tuple[str, ...] = ()
    val_fraction: float = 0.0
    test_fraction: float = 0.0
    val_families: tuple[str, ...] = ()
    test_families: tuple[str, ...] = ()


@dataclass(frozen=True)
class DatasetSpec:
    name: str
    seed: int
    sources: tuple[Source, ...]
    splits: Splits
    path: Path | None = None  # the spec file (relative source paths resolve against its folder)
    for_formats: tuple[str, ...] = ()  # [dataset] for_formats (and --for-formats): every clip renders what they need


# ----------------------------------------------------------------------------------------------
# Parsing
# ----------------------------------------------------------------------------------------------

_TOP_KEYS = ("dataset", "render", "splits", "source")
_DATASET_KEYS = ("name", "seed", "for_formats")
_RENDER_KEYS = RENDER_KEYS
_SPLIT_KEYS = ("val", "test", "val_fraction", "test_fraction", "val_families", "test_families")
_SOURCE_KEYS = ("name", "kind", "split", "cameras", "seeds", "paths", "clips_per_asset", "hdri", "hdri_strength",
                "clutter", "target_size_m", "licence", "sun", "props", "clips_per_scene", "light", "regions",
                "region_val", "region_test", "world_strength", "light_strength", "sun_elevation_deg", *_RENDER_KEYS)
_SCENE_ONLY = ("clips_per_scene", "light", "regions", "region_val", "region_test", "world_strength",
               "light_strength", "sun_elevation_deg")


def _prefix(spec_path) -> str:
    return f"{spec_path}: "


def _check_keys(table: dict, known, where: str, spec_path) -> None:
    """SpecError naming the first unknown key of the table ``where`` ('' at the top level)."""
    check_keys(table, known, where, SpecError, _prefix(spec_path))


def _typed(value, kind, where: str, spec_path, rule: Rule = Rule()):
    """``value`` of the key ``where`` checked as ``kind`` and against ``rule`` (``gbuffer_export.typed_table``)."""
    return typed_value(where, value, kind, rule, SpecError, _prefix(spec_path))


def _render_settings(base: RenderSettings, table: dict, where: str, spec_path) -> RenderSettings:
    """``base`` (the defaults or the ``[render]`` table's) with the render keys of ``table``, each checked as
    ``RenderConfig`` checks it, then the whole as ``RenderConfig`` (sizes, scales) would render it."""
    spec = fields_of(RenderSettings)
    out = {}
    for k in RENDER_KEYS:
        if k not in table:
            continue
        v, path = table[k], f"{where}.{k}"
        if k == "hr_size":
            v = _typed(v, str, path, spec_path)  # a SpecError naming the file once
            try:
                v = parse_size(v)
            except ConfigError as exc:
                raise SpecError(f"{spec_path}: {where}.{exc}", key=path) from None
        elif k == "buffers":
            if isinstance(v, list):
                v = ",".join(_typed(x, str, path, spec_path) for x in v)
            v = _typed(v, str, path, spec_path)
            try:
                v = parse_buffer_list(v)
            except (KeyError, ValueError) as exc:
                raise SpecError(f"{spec_path}: {path}: {str(exc).strip(chr(39))}", key=path) from None
        else:
            v = _typed(v, spec[k][0], path, spec_path, spec[k][1])
        out[k] = v
    out = dataclasses.replace(base, **out)
    if out.scales is not None and len(out.scales) == 0:
        raise SpecError(f"{spec_path}: {where}.scales = []: list the clip's LR scales, its scale first (e.g. "
                        f"scales = [{out.scale}, 2]), or leave the key out for one level", key=f"{where}.scales")
    if out.scales is not None and len(out.scales) == 1 and float(out.scales[0]) == float(out.scale):
        out = dataclasses.replace(out, scales=None)  # one level: the same clip as without the key
    if out.scales is not None and float(out.scales[0]) != float(out.scale):
        raise SpecError(f"{spec_path}: {where}.scales: the first scale is the clip's 'lr' level and must be scale "
                        f"{out.scale} (e.g. scales = [{out.scale}, 2])", key=f"{where}.scales")
    try:
        RenderConfig(output=".", frames=(1, out.frames), **{k: getattr(out, k) for k in RENDER_KEYS[1:]},
                     progress=False)
    except ConfigError as exc:
        raise SpecError(f"{spec_path}: {where}.{exc}", key=f"{where}.{exc.key}") from None
    return out


def _source_key(t: dict, name: str, where: str, spec_path):
    """The ``[[source]]`` key ``name`` of ``t`` (absent: ``Source``'s default), checked by its annotation and rule."""
    typ, rule = fields_of(Source)[name]
    default = next(f.default for f in dataclasses.fields(Source) if f.name == name)
    return _typed(t.get(name, default), typ, f"{where}.{name}", spec_path, rule)


def _str_list(v, where, spec_path) -> tuple[str, ...]:
    """A list of strings (one string: a list of one)."""
    return _typed([v] if isinstance(v, str) else v, tuple[str, ...], where, spec_path)


def _range(v, where, spec_path) -> tuple[float, float]:
    """[low, high] with 0 < low <= high (one number x: [x, x])."""
    return _typed(v, tuple[float, float], where, spec_path, Rule(pair=True))


def _seeds(v, where, spec_path) -> tuple[int, int]:
    """'A:B' (inclusive), [A, B] or a single integer."""
    if isinstance(v, int) and not isinstance(v, bool):
        a = b = v
    elif isinstance(v, str) and ":" in v:
        try:
            a, b = (int(x) for x in v.split(":"))
        except ValueError:
            raise SpecError(f"{spec_path}: {where} {v!r}: expected 'A:B' with integers") from None
    elif isinstance(v, list) and len(v) == 2:
        a, b = (_typed(x, int, where, spec_path) for x in v)
    else:
        raise SpecError(f"{spec_path}: {where} {v!r}: expected 'A:B', [A, B] or an integer")
    if b < a or a < 0:
        raise SpecError(f"{spec_path}: {where} {v!r}: need 0 <= A <= B")
    return a, b


def _for_formats(render: RenderSettings, formats, sized: bool, where: str, spec_path) -> RenderSettings:
    """``render`` with what the export formats need (``format_limits.render_for_formats``, the one derivation that
    ``blendsr render --for-formats`` uses too): their LR levels added after the clip's, their HR size (when the
    spec gives none: ``sized`` False), their buffers; SpecError naming the key on a conflict."""
    from ..conventions import parse_buffer_list
    from ..format_limits import FormatLimitError, render_for_formats
    bufs = render.buffers if not isinstance(render.buffers, str) else parse_buffer_list(render.buffers)
    try:
        r = render_for_formats(formats, scales=render.scales or (render.scale,),
                               hr_size=render.hr_size if sized else None, buffers=bufs,
                               where=f"dataset.for_formats ({where})")
    except FormatLimitError as exc:
        raise SpecError(f"{spec_path}: {exc}", key="dataset.for_formats") from None
    table = {"scales": list(r["scales"]), "buffers": list(r["buffers"])}
    if r["hr_size"] is not None:
        table["hr_size"] = f"{r['hr_size'][0]}x{r['hr_size'][1]}"
    return _render_settings(render, table, where, spec_path)


def parse_spec(data: dict, spec_path: str | Path = "<spec>", formats=()) -> DatasetSpec:
    """Validate a parsed TOML document and return the typed spec; ``formats``: export formats whose needs every
    clip renders besides the spec's ``for_formats`` (``blendsr dataset --for-formats``)."""
    _check_keys(data, _TOP_KEYS, "", spec_path)
    ds = data.get("dataset", {})
    _check_keys(ds, _DATASET_KEYS, "dataset", spec_path)
    name = _typed(ds.get("name", Path(str(spec_path)).stem), str, "dataset.name", spec_path)
    seed = _typed(ds.get("seed", 0), int, "dataset.seed", spec_path)
    from ..format_limits import FormatLimitError, parse_formats
    try:
        for_formats = parse_formats([*_str_list(ds.get("for_formats", []), "dataset.for_formats", spec_path),
                                     *formats], "dataset.for_formats")
    except FormatLimitError as exc:
        raise SpecError(f"{spec_path}: {exc}", key="dataset.for_formats") from None
    render_table = data.get("render", {})
    _check_keys(render_table, _RENDER_KEYS, "render", spec_path)
    defaults = _render_settings(RenderSettings(), render_table, "render", spec_path)
    splits = _parse_splits(data.get("splits", {}), spec_path)
    raw_sources = data.get("source", [])
    if not isinstance(raw_sources, list) or not raw_sources:
        raise SpecError(f"{spec_path}: no [[source]] tables: add at least one (kind = \"builtin\" or \"assets\")")
    sources, names = [], set()
    render_from = defaults, for_formats, "hr_size" in render_table
    for i, t in enumerate(raw_sources):
        sources.append(_parse_source(t, f"source[{i}]", i, render_from, names, spec_path))
    return DatasetSpec(name=name, seed=seed, sources=tuple(sources), splits=splits,
                       path=Path(spec_path) if spec_path != "<spec>" else None, for_formats=for_formats)


def _parse_splits(sp: dict, spec_path) -> Splits:
    """The ``[splits]`` table, checked: fractions in range, no clip or family in both val and test."""
    _check_keys(sp, _SPLIT_KEYS, "splits", spec_path)
    splits = Splits(val=_str_list(sp.get("val", []), "splits.val", spec_path),
                    test=_str_list(sp.get("test", []), "splits.test", spec_path),
                    val_fraction=_typed(sp.get("val_fraction", 0.0), float, "splits.val_fraction", spec_path),
                    test_fraction=_typed(sp.get("test_fraction", 0.0), float, "splits.test_fraction", spec_path),
                    val_families=_families(sp, "val_families", spec_path),
                    test_families=_families(sp, "test_families", spec_path))
    if not (0 <= splits.val_fraction and 0 <= splits.test_fraction and splits.val_fraction + splits.test_fraction < 1):
        raise SpecError(f"{spec_path}: splits: val_fraction and test_fraction must be >= 0 with a sum below 1")
    both = set(splits.val) & set(splits.test)
    if both:
        raise SpecError(f"{spec_path}: splits: {', '.join(sorted(both))} listed in both val and test")
    both = set(splits.val_families) & set(splits.test_families)
    if both:
        raise SpecError(f"{spec_path}: splits: {', '.join(sorted(both))} listed in both val_families and "
                        "test_families")
    return splits


def _parse_source(t, where: str, i: int, render_from: tuple, names: set, spec_path) -> Source:
    """One ``[[source]]`` table (``names``: the names taken so far, this one added); ``render_from``: the spec's
    render defaults, its export formats and whether its ``[render]`` table sets ``hr_size``."""
    if not isinstance(t, dict):
        raise SpecError(f"{spec_path}: {where}: expected a table")
    _check_keys(t, _SOURCE_KEYS, where, spec_path)
    kind = _typed(t.get("kind", ""), str, f"{where}.kind", spec_path, Rule(choices=SOURCE_KINDS))
    sname = _typed(t.get("name", kind if kind == "builtin" else f"{kind}{i}"), str, f"{where}.name", spec_path)
    if sname in names or not sname.replace("-", "").replace("_", "").isalnum():
        raise SpecError(f"{spec_path}: {where}.name {sname!r}: must be unique, letters, digits, - and _")
    names.add(sname)
    defaults, for_formats, hr_size_set = render_from
    render = _render_settings(defaults, t, where, spec_path)
    if for_formats:
        render = _for_formats(render, for_formats, "hr_size" in t or hr_size_set, where, spec_path)
    if kind != "scene":
        for k in _SCENE_ONLY:
            if k in t:
                raise SpecError(f"{spec_path}: {where}.{k}: only for kind = \"scene\"")
    split = _source_key(t, "split", where, spec_path)
    if kind == "scene":
        return _scene_source(t, sname, render, split, where, spec_path)
    cameras = _typed(_str_list(t.get("cameras", ["orbit"]), f"{where}.cameras", spec_path), tuple[str, ...],
                     f"{where}.cameras", spec_path, Rule(items=SOURCE_CAMERAS))
    if kind == "assets" and "scene" in cameras:
        raise SpecError(f"{spec_path}: {where}.cameras: 'scene' is for kind = \"builtin\" only")
    kw = dict(name=sname, kind=kind, render=render, cameras=cameras, split=split)
    kw.update(_builtin_keys(t, cameras, where, spec_path) if kind == "builtin" else _assets_keys(t, where, spec_path))
    kw["environment"] = Environment(
        hdri=_str_list(t.get("hdri", []), f"{where}.hdri", spec_path),
        strength=_range(t.get("hdri_strength", [0.7, 1.5]), f"{where}.hdri_strength", spec_path))
    return Source(**kw)


def _builtin_keys(t: dict, cameras: tuple, where: str, spec_path) -> dict:
    """A built-in source's own keys: seeds, sun and props (at most one camera family, which needs the scene camera)."""
    for k in ("paths", "clips_per_asset", "clutter", "target_size_m", "licence"):
        if k in t:
            raise SpecError(f"{spec_path}: {where}.{k}: only for kind = \"assets\"")
    if "seeds" not in t:
        raise SpecError(f"{spec_path}: {where}: kind = \"builtin\" needs seeds = \"A:B\"")
    kw = {"seeds": _seeds(t["seeds"], f"{where}.seeds", spec_path), "sun": _source_key(t, "sun", where, spec_path),
          "props": _source_key(t, "props", where, spec_path)}
    if set(kw["props"]) & set(CAMERA_FAMILIES) and cameras != ("scene",):
        raise SpecError(f"{spec_path}: {where}.props: the camera families "
                        f"({', '.join(sorted(set(kw['props']) & set(CAMERA_FAMILIES)))}) move the built-in "
                        "scene's own camera: give the source cameras = [\"scene\"]")
    if sum(p in CAMERA_FAMILIES for p in kw["props"]) > 1:
        raise SpecError(f"{spec_path}: {where}.props: at most one camera family per source (each re-keys "
                        "the one camera)")
    return kw


def _assets_keys(t: dict, where: str, spec_path) -> dict:
    """An assets source's own keys: paths (at least one), clips per asset, clutter, target size and licences."""
    if "seeds" in t or "sun" in t or "props" in t:
        raise SpecError(f"{spec_path}: {where}: seeds, sun and props are for kind = \"builtin\"")
    kw = {"paths": _str_list(t.get("paths", []), f"{where}.paths", spec_path)}
    if not kw["paths"]:
        raise SpecError(f"{spec_path}: {where}: kind = \"assets\" needs paths = [files or folders]")
    for k in ("clips_per_asset", "clutter", "target_size_m"):
        kw[k] = _source_key(t, k, where, spec_path)
    lic = t.get("licence", {})
    if not isinstance(lic, dict) or not all(isinstance(v, dict) for v in lic.values()):
        raise SpecError(f"{spec_path}: {where}.licence: expected {{ASSET = {{licence = ..., attribution = ...}}}}")
    kw["licence"] = lic
    return kw


def _families(sp: dict, key: str, spec_path) -> tuple[str, ...]:
    """``[splits]`` ``val_families`` / ``test_families``: family ids (``families.check_family_id``)."""
    out = _str_list(sp.get(key, []), f"splits.{key}", spec_path)
    for fid in out:
        bad = check_family_id(fid)
        if bad:
            raise SpecError(f"{spec_path}: splits.{key} item {fid!r}: {bad}", key=f"splits.{key}")
    return out


def _grid(v, where, spec_path) -> tuple[int, int]:
    """'NxM', [N, M] or N (N x N); SpecError echoing the value as written otherwise."""
    given = v
    if isinstance(v, int) and not isinstance(v, bool):
        v = [v, v]
    elif isinstance(v, str):
        try:
            v = [int(x) for x in v.lower().split("x")]
        except ValueError:
            v = None
    if not (isinstance(v, list) and len(v) == 2 and all(isinstance(x, int) and not isinstance(x, bool) for x in v)
            and 1 <= v[0] <= 16 and 1 <= v[1] <= 16):
        raise SpecError(f"{spec_path}: {where} = {given!r}: expected 'NxM' (1 to 16 cells a side), e.g. \"3x3\"",
                        key=where)
    return v[0], v[1]


def _scene_source(t: dict, name: str, render: RenderSettings, split, where: str, spec_path) -> "Source":
    """A ``kind = "scene"`` source: the user's scene files kept as they are (docs/dataset.md)."""
    for k in ("seeds", "sun", "props", "clips_per_asset", "clutter", "target_size_m", "hdri_strength"):
        if k in t:
            raise SpecError(f"{spec_path}: {where}.{k}: not for kind = \"scene\" (a scene keeps its own world)")
    paths = _str_list(t.get("paths", []), f"{where}.paths", spec_path)
    if not paths:
        raise SpecError(f"{spec_path}: {where}: kind = \"scene\" needs paths = [scene files or folders]")
    cameras = _str_list(t.get("cameras", ["walk", "fly"]), f"{where}.cameras", spec_path)
    for c in cameras:
        if not camera_path_ok(c) or c == "scene:":
            raise SpecError(f"{spec_path}: {where}.cameras item {c!r}: choose one of "
                            f"{', '.join(SCENE_SOURCE_CAMERAS)}", key=f"{where}.cameras")
    clips = _source_key(t, "clips_per_scene", where, spec_path)
    light = _source_key(t, "light", where, spec_path)
    regions = _grid(t.get("regions", [1, 1]), f"{where}.regions", spec_path)
    rv, rt = _source_key(t, "region_val", where, spec_path), _source_key(t, "region_test", where, spec_path)
    if rv + rt >= regions[0] * regions[1] and (rv or rt):
        raise SpecError(f"{spec_path}: {where}: need region_val + region_test below the "
                        f"{regions[0] * regions[1]} cells of regions (the rest train)")
    if (rv or rt) and split is not None:
        raise SpecError(f"{spec_path}: {where}: split and region_val/region_test exclude each other")
    if (rv or rt) and any(c not in ("walk", "fly") for c in cameras):
        raise SpecError(f"{spec_path}: {where}.cameras: regions split a level by where its cameras stand, so only "
                        "walk and fly (whose paths stay in their region) go with region_val/region_test")
    var = Variation(
        world_strength=_range(t["world_strength"], f"{where}.world_strength", spec_path) if "world_strength" in t
        else None,
        light_strength=_range(t["light_strength"], f"{where}.light_strength", spec_path) if "light_strength" in t
        else None,
        sun_elevation_deg=_range(t["sun_elevation_deg"], f"{where}.sun_elevation_deg", spec_path)
        if "sun_elevation_deg" in t else None,
        hdri=_str_list(t.get("hdri", []), f"{where}.hdri", spec_path))
    if var.sun_elevation_deg is not None and var.sun_elevation_deg[1] > 90:
        raise SpecError(f"{spec_path}: {where}.sun_elevation_deg: need 0 < low <= high <= 90")
    return Source(name=name, kind="scene", render=render, cameras=cameras, split=split, paths=paths,
                  clips_per_scene=clips, light=light, regions=regions, region_val=rv, region_test=rt,
                  variation=var, licence=t.get("licence", {}) if isinstance(t.get("licence", {}), dict) else {})


def load_spec(path: str | Path, formats=()) -> DatasetSpec:
    """Read and validate a spec file (``formats``: as ``parse_spec``); SpecError (one line naming the file) on any
    problem."""
    path = Path(path)
    if not path.is_file():
        raise SpecError(f"{path}: dataset spec not found")
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SpecError(f"{path}: not valid TOML ({str(exc).splitlines()[0]})") from None
    return parse_spec(data, path, formats)


# ----------------------------------------------------------------------------------------------
# Expansion into clips
# ----------------------------------------------------------------------------------------------

def stable_hash(*parts) -> int:
    """A 63-bit integer from the parts' text: the same on every machine and Python (no ``hash()``)."""
    h = hashlib.sha256("\x1f".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(h[:8], "big") >> 1


def mixed_rank(clip_id: str) -> int:
    """A clip's place in the mixed order: ``blendsr dataset --order mixed`` renders in it, and
    ``benchmarks/data_scaling.py`` takes its nested training subsets in it, so the clips rendered first are the first
    subsets trained, and the clips finished at any moment are a sample of every source and split."""
    return stable_hash("subset", clip_id)


def assign_split(scene_id: str, splits: Splits, forced: str | None, dataset_seed: int, *, spec_path=None,
                 source: str | None = None, family: str | None = None) -> str:
    """The split of one scene: the source's forced split, an explicit list or the held-out family the scene is
    (``family``: ``asset:STEM``, ``level:STEM``), else the hash rule. A forced split that contradicts the explicit
    lists (a test asset in a ``split = "train"`` source: a leak) is a SpecError."""
    stem = scene_id
    listed = "test" if stem in splits.test else "val" if stem in splits.val else None
    held = held_split([family], splits.val_families, splits.test_families) if family else None
    if listed and held and listed != held:
        raise SpecError(f"{spec_path}: {scene_id!r} is listed under [splits] {listed} but its family {family!r} is "
                        f"in {held}_families: list it once")
    listed = listed or held
    if forced and listed and forced != listed:
        why = (f"listed under [splits] {listed}" if stem in splits.test + splits.val
               else f"whose family {family!r} is in [splits] {listed}_families")
        raise SpecError(f"{spec_path}: source {source!r} has split = {forced!r} but holds {scene_id!r}, {why}: take "
                        "it out of the source or of the list")
    if forced:
        return forced
    if listed:
        return listed
    u = (stable_hash("split", dataset_seed, scene_id) % 1_000_000) / 1_000_000
    if u < splits.test_fraction:
        return "test"
    if u < splits.test_fraction + splits.val_fraction:
        return "val"
    return "train"


def _resolve(p: str, base: Path | None) -> Path:
    path = Path(p).expanduser()
    if not path.is_absolute() and base is not None:
        path = base / path
    return path.resolve()


def find_assets(source: Source, base: Path | None, spec_path) -> list[Path]:
    """The asset (or, for ``kind = "scene"``, scene) files of a source, sorted by stem: files as given, folders
    searched recursively."""
    suffixes = SCENE_SUFFIXES if source.kind == "scene" else ASSET_SUFFIXES
    what = "scene" if source.kind == "scene" else "glTF, GLB or .blend"
    out: dict[str, Path] = {}
    for p in source.paths:
        path = _resolve(p, base)
        if path.is_file():
            files = [path]
        elif path.is_dir():
            files = sorted(f for f in path.rglob("*") if f.suffix.lower() in suffixes and f.is_file())
        else:
            raise SpecError(f"{spec_path}: source {source.name!r}: {path}: no such file or folder")
        for f in files:
            if f.suffix.lower() not in suffixes:
                raise SpecError(f"{spec_path}: source {source.name!r}: {f}: not a {what} file")
            if f.stem in out and out[f.stem] != f:
                raise SpecError(f"{spec_path}: source {source.name!r}: two assets named {f.stem!r} "
                                f"({out[f.stem]}, {f}): asset stems must be unique")
            out[f.stem] = f
    if not out:
        raise SpecError(f"{spec_path}: source {source.name!r}: no {what} files under its paths")
    return [out[k] for k in sorted(out)]


def find_hdris(env: Environment, base: Path | None, spec_path, source_name: str) -> list[str]:
    """The HDRI pool: absolute file paths and ``builtin:NAME`` entries, sorted. Empty pool: bpy's builtins."""
    out = []
    for h in env.hdri or tuple(f"builtin:{n}" for n in BUILTIN_HDRIS):
        if h.startswith("builtin:"):
            if h.split(":", 1)[1] not in BUILTIN_HDRIS:
                raise SpecError(f"{spec_path}: source {source_name!r}: hdri {h!r}: builtin names are "
                                f"{', '.join(BUILTIN_HDRIS)}")
            out.append(h)
            continue
        path = _resolve(h, base)
        if path.is_dir():
            for f in sorted(path.iterdir()):
                if f.suffix.lower() not in HDRI_SUFFIXES:
                    continue
                if not f.is_file():
                    raise SpecError(f"{spec_path}: source {source_name!r}: hdri {f}: not a file (a folder named "
                                    f"like an HDRI)")
                out.append(str(f))
        elif path.is_file() and path.suffix.lower() in HDRI_SUFFIXES:
            out.append(str(path))
        else:
            raise SpecError(f"{spec_path}: source {source_name!r}: hdri {path}: not an .hdr/.exr file or folder")
    if not out:
        raise SpecError(f"{spec_path}: source {source_name!r}: the hdri pool is empty")
    return sorted(set(out))


def read_asset_licence(path: Path) -> dict:
    """Licence and attribution of an asset from the files beside it: a Khronos-sample ``metadata.json`` (its
    ``legal`` entries) up to two folders above, else the glTF's ``asset.copyright``; ``unknown`` otherwise."""
    import json
    for folder in (path.parent, path.parent.parent, path.parent.parent.parent):
        meta = folder / "metadata.json"
        if meta.is_file():
            try:
                legal = json.loads(meta.read_text()).get("legal", [])
            except (ValueError, OSError, AttributeError, RecursionError):
                legal = []
            if legal:
                lic = sorted({e.get("spdx") or e.get("license") or "unknown" for e in legal})
                attr = "; ".join(f"{e.get('what', 'asset')}: {e.get('artist', '?')} ({e.get('year', '?')}, "
                                 f"{e.get('spdx') or e.get('license', '?')})" for e in legal)
                return {"licence": " + ".join(lic), "attribution": attr, "licence_source": str(meta)}
    if path.suffix.lower() == ".gltf":
        try:
            asset = json.loads(path.read_text()).get("asset", {})
        except (ValueError, OSError, AttributeError, RecursionError):  # unreadable: its import names the problem
            asset = {}
        if isinstance(asset, dict) and isinstance(asset.get("copyright"), str) and asset["copyright"]:
            return {"licence": "unknown", "attribution": asset["copyright"], "licence_source": str(path)}
    return {"licence": "unknown", "attribution": "unknown", "licence_source": None}


@dataclass
class ClipJob:
    """One clip of the dataset, fully explicit (what ``dataset.json`` stores and a worker renders)."""

    id: str
    source: str
    kind: str                 # builtin | assets
    scene_id: str             # builtin:SEED or the asset's stem
    split: str
    seed: int                 # the clip's render/camera seed
    render: dict              # RenderSettings.to_json()
    camera: str               # orbit | walk
    asset: str | None = None  # absolute path of the main asset
    clutter: list = field(default_factory=list)   # absolute paths of clutter assets
    hdri: str | None = None
    hdri_rotation_deg: float = 0.0
    hdri_strength: float = 1.0
    target_size_m: float = 1.5
    sun: bool = True
    licence: dict = field(default_factory=dict)
    props: list | None = None         # builtin: opt-in props (None: none, so that older indexes compare equal)
    # kind = "scene" only (None elsewhere, so that older indexes compare equal):
    light: str | None = None          # scene | sky
    camera_index: int | None = None   # scene:*: which of the file's cameras (by name, cycling)
    region: dict | None = None        # {"grid": [nx, ny], "cell": [i, j], "cells": {split: [[i, j], ...]}}
    variation: dict | None = None     # the drawn light variation (docs/dataset.md)
    # what the clip holds (``families.py``); derived from the fields above, so not compared on resume:
    families: list | None = None      # its family ids (asset, clutter, level, HDRI, built-in families)
    family_group: str | None = None   # in-family | held-out (it holds a declared held-out family)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @staticmethod
    def from_json(d: dict) -> "ClipJob":
        names = {f.name for f in dataclasses.fields(ClipJob)}
        return ClipJob(**{k: v for k, v in d.items() if k in names})


def _draw(seed: int):
    import random
    return random.Random(seed)


def count_clips(spec: DatasetSpec, base: Path | None = None) -> int:
    """How many clips ``expand`` makes, from the seed ranges, clips per asset/scene and the asset files, without
    expanding (SpecError above MAX_CLIPS, naming the source that passes it)."""
    total = 0
    for src in spec.sources:
        if src.kind == "builtin":
            n = src.seeds[1] - src.seeds[0] + 1
        else:
            per = src.clips_per_scene if src.kind == "scene" else src.clips_per_asset
            if total + per > MAX_CLIPS:  # before looking for the files
                n = per
            else:
                n = per * len(find_assets(src, base, spec.path))
        total += n
        if total > MAX_CLIPS:
            raise SpecError(f"{spec.path}: source {src.name!r} brings the spec to {total} clips or more; one spec "
                            f"makes at most {MAX_CLIPS} (split it into several specs)")
    return total


def expand(spec: DatasetSpec) -> list[ClipJob]:
    """Every clip of the spec, in a fixed order (source by source). Pure and deterministic. At most MAX_CLIPS
    clips (counted before anything is expanded)."""
    base = spec.path.parent.resolve() if spec.path else None
    count_clips(spec, base)
    jobs: list[ClipJob] = []
    levels = {stem: [owner, 0] for stem, owner in level_layouts(spec, base).items()}
    for src in spec.sources:
        if src.kind == "scene":
            jobs += _expand_scene(src, spec, base, levels)
        elif src.kind == "builtin":
            jobs += _expand_builtin(src, spec, find_hdris(src.environment, base, spec.path, src.name))
        else:
            jobs += _expand_assets(src, spec, base, find_hdris(src.environment, base, spec.path, src.name))
    counts = Counter(j.id for j in jobs)
    dup = sorted(i for i, n in counts.items() if n > 1)
    if dup:
        raise SpecError(f"{spec.path}: clip ids collide ({', '.join(dup[:3])}): rename a source or an asset")
    held = {f for j in jobs for f in j.families or ()}
    for key in ("test_families", "val_families"):
        lost = [f for f in getattr(spec.splits, key) if f not in held]
        if lost:
            raise SpecError(f"{spec.path}: splits.{key}: {', '.join(lost)} held by no clip of the spec (held out "
                            "but never measured: a typo, or no source draws it)", key=f"splits.{key}")
    return jobs


def _expand_builtin(src: Source, spec: DatasetSpec, hdris: list) -> list[ClipJob]:
    """A built-in source's clips: one per seed, its camera, HDRI and strength drawn from the clip's own stream."""
    jobs = []
    for s in range(src.seeds[0], src.seeds[1] + 1):
        scene_id = f"builtin:{s}"
        cid = f"{src.name}-s{s:04d}"
        rng = _draw(stable_hash("clip", spec.seed, cid) % (2 ** 31))
        jobs.append(ClipJob(
            id=cid, source=src.name, kind="builtin", scene_id=scene_id,
            split=assign_split(scene_id, spec.splits, src.split, spec.seed, spec_path=spec.path,
                               source=src.name), seed=s,
            render=src.render.to_json(), camera=rng.choice(src.cameras),
            hdri=rng.choice(hdris), hdri_rotation_deg=round(rng.uniform(0.0, 360.0), 3),
            hdri_strength=round(_loguniform(rng, *src.environment.strength), 4), sun=src.sun,
            props=list(src.props) or None,
            licence={"licence": "MIT (BlendSR built-in scene)", "attribution": "BlendSR built-in scene"}))
        props = [builtin_family(p) for p in src.props]
        _hold(jobs[-1], spec, [hdri_family(jobs[-1].hdri), *props], [*map(hdri_family, hdris), *props])
    return jobs


def _expand_assets(src: Source, spec: DatasetSpec, base, hdris: list) -> list[ClipJob]:
    """An assets source's clips: ``clips_per_asset`` per asset, each with clutter of the same split drawn from the
    clip's own stream (held-out objects are never train clutter), its camera, HDRI and strength."""
    jobs = []
    assets = find_assets(src, base, spec.path)
    split_of = {a.stem: assign_split(a.stem, spec.splits, src.split, spec.seed, spec_path=spec.path,
                                     source=src.name, family=f"asset:{a.stem}") for a in assets}
    for a in assets:
        lic = dict(read_asset_licence(a))
        if a.stem in src.licence:
            lic.update({k: str(v) for k, v in src.licence[a.stem].items()})
        same_split = [b for b in assets if b != a and split_of[b.stem] == split_of[a.stem]]
        for k in range(src.clips_per_asset):
            cid = f"{src.name}-{_slug(a.stem)}-{k:02d}"
            seed = stable_hash("clip", spec.seed, cid) % (2 ** 31)
            rng = _draw(seed)
            n_clutter = rng.randint(0, min(src.clutter, len(same_split))) if src.clutter else 0
            clutter = sorted(rng.sample(same_split, n_clutter), key=lambda p: p.stem) if n_clutter else []
            jobs.append(ClipJob(
                id=cid, source=src.name, kind="assets", scene_id=a.stem, split=split_of[a.stem], seed=seed,
                render=src.render.to_json(), camera=rng.choice(src.cameras), asset=str(a),
                clutter=[str(c) for c in clutter], hdri=rng.choice(hdris),
                hdri_rotation_deg=round(rng.uniform(0.0, 360.0), 3),
                hdri_strength=round(_loguniform(rng, *src.environment.strength), 4),
                target_size_m=src.target_size_m, licence=lic))
            mine = [f"asset:{a.stem}", *(f"asset:{c.stem}" for c in clutter), hdri_family(jobs[-1].hdri)]
            could = [f"asset:{b.stem}" for b in same_split] if src.clutter else []
            _hold(jobs[-1], spec, mine, [*mine, *could, *map(hdri_family, hdris)])
    return jobs


def plan_totals(jobs: list[ClipJob]) -> dict:
    """Clips, frames and HR pixels of a plan, in all and by split and family group (``blendsr dataset --dry-run``):
    {"all": {...}, "train": {...}, ..., "test held-out": {...}} with keys clips, frames, hr_pixels."""
    out: dict[str, dict] = {}
    for j in jobs:
        w, h = j.render["hr_size"]
        f = int(j.render["frames"])
        for key in ("all", j.split, f"{j.split} {j.family_group or 'in-family'}"):
            t = out.setdefault(key, {"clips": 0, "frames": 0, "hr_pixels": 0})
            t["clips"] += 1
            t["frames"] += f
            t["hr_pixels"] += f * w * h
    return out


def region_cells(src: Source, spec_seed: int, stem: str, owner: str | None = None) -> dict[str, list[list[int]]]:
    """The grid cells of each split of one scene: a seeded shuffle of the ``regions`` grid gives its first
    ``region_test`` cells to test, the next ``region_val`` to val, the rest to train. ``owner``: the name of the
    source that draws the level's layout (the first source listing the level: ``level_layouts``; default ``src``)."""
    import random
    nx, ny = src.regions
    cells = [[i, j] for j in range(ny) for i in range(nx)]
    random.Random(stable_hash("regions", spec_seed, owner or src.name, stem)).shuffle(cells)
    t, v = src.region_test, src.region_val
    return {"test": cells[:t], "val": cells[t:t + v], "train": cells[t + v:]}


def level_layouts(spec: DatasetSpec, base: Path | None) -> dict[str, str]:
    """For every level (a scene file's stem: ``garage.blend`` and ``garage.gltf`` are one level) of the spec's
    ``kind = "scene"`` sources, the name of the first source that lists it: that source draws the level's region
    layout and every other source of the level reuses it, so a cell is in one split in the whole spec. SpecError
    (one line) when two sources of one level split it differently (another grid, other test/val counts, or regions
    in one and none in the other): a test region of one would be training data of the other."""
    owners: dict[str, Source] = {}
    key = lambda s: (s.regions, s.region_test, s.region_val, s.split)  # noqa: E731
    for src in spec.sources:
        if src.kind != "scene":
            continue
        for a in find_assets(src, base, spec.path):
            first = owners.setdefault(a.stem, src)
            if key(first) != key(src):
                forced = f", split = \"{first.split}\"" if first.split else ", no split key"
                raise SpecError(f"{spec.path}: source {src.name!r}: level {a.stem!r} is split otherwise than in "
                                f"source {first.name!r}: use its regions = \"{first.regions[0]}x{first.regions[1]}\", "
                                f"region_test = {first.region_test}, region_val = {first.region_val}{forced} (one "
                                "layout per level)")
    return {stem: src.name for stem, src in owners.items()}


def _expand_scene(src: Source, spec: DatasetSpec, base: Path | None, levels: dict) -> list[ClipJob]:
    """The clips of a ``kind = "scene"`` source: ``clips_per_scene`` per file, clip k with camera kind k of
    ``cameras`` (cycling). With split regions, the level's n-th clip in the spec (counted over every source of the
    level, in spec order: ``levels`` maps a stem to [layout owner, clips so far]) starts in cell n of the order test
    cells, val cells, train cells (cycling), so the level's first clips cover every split and a source appended to
    a spec leaves the clips before it unchanged; its path stays in that cell, or, when no path fits there,
    in the cells of its split (the renderer decides: the index does not know the geometry)."""
    jobs = []
    var = src.variation or Variation()
    hdris = find_hdris(Environment(hdri=var.hdri), base, spec.path, src.name) if var.hdri else []
    for a in find_assets(src, base, spec.path):
        lic = dict(read_asset_licence(a))
        if a.stem in src.licence:
            lic.update({k: str(v) for k, v in src.licence[a.stem].items()})
        split_regions = bool(src.region_val or src.region_test)
        held = held_split([f"level:{a.stem}"], spec.splits.val_families, spec.splits.test_families)
        if split_regions and held:
            raise SpecError(f"{spec.path}: source {src.name!r}: level {a.stem!r} is a {held} family ([splits] "
                            f"{held}_families) but split by regions (its train cells would hold it): take region_val "
                            "and region_test off")
        cells = region_cells(src, spec.seed, a.stem, levels[a.stem][0]) if split_regions else None
        order = [(sp, c) for sp in ("test", "val", "train") for c in (cells or {}).get(sp, [])]
        for k in range(src.clips_per_scene):
            cid = f"{src.name}-{_slug(a.stem)}-{k:02d}"
            seed = stable_hash("clip", spec.seed, cid) % (2 ** 31)
            rng = _draw(seed)
            camera = src.cameras[k % len(src.cameras)]  # cycling: every kind appears once clips >= kinds
            if split_regions:
                split, cell = order[levels[a.stem][1] % len(order)]
                levels[a.stem][1] += 1
                region = {"grid": list(src.regions), "cell": cell, "split": split, "cells": cells}
                scene_id = f"{a.stem}@cell{cell[0]}-{cell[1]}"
            else:
                split = assign_split(a.stem, spec.splits, src.split, spec.seed, spec_path=spec.path,
                                     source=src.name, family=f"level:{a.stem}")
                region, scene_id = None, a.stem
            jobs.append(ClipJob(
                id=cid, source=src.name, kind="scene", scene_id=scene_id, split=split, seed=seed,
                render=src.render.to_json(), camera=camera, asset=str(a), hdri=None, licence=lic, light=src.light,
                camera_index=k if camera == "scene:*" else None, region=region,
                variation=_draw_variation(var, hdris, rng)))
            drawn = (jobs[-1].variation or {}).get("hdri")
            mine = [f"level:{a.stem}", *([hdri_family(drawn)] if drawn else [])]
            _hold(jobs[-1], spec, mine, [*mine, *map(hdri_family, hdris)])
    return jobs


def _hold(job: ClipJob, spec: DatasetSpec, mine: list[str], could: list[str]) -> None:
    """Record the families ``job`` holds (``mine``) and its family group; SpecError when it could draw (``could``:
    its pools) a held-out family of a later split (a test HDRI in a train source's pool)."""
    val, test = spec.splits.val_families, spec.splits.test_families
    bad = leak(job.split, could, val, test)
    if bad:
        raise SpecError(f"{spec.path}: source {job.source!r}: clip {job.id} is in {job.split} but can hold "
                        f"{bad[0]!r}, a {bad[1]} family ([splits] {bad[1]}_families): take it out of the source's "
                        f"pool (hdri, props, clutter) or give the source split = \"{bad[1]}\"")
    job.families = sorted(set(mine))
    job.family_group = family_group(job.families, val, test)


def _draw_variation(var: Variation, hdris: list[str], rng) -> dict | None:
    out = {}
    if var.world_strength:
        out["world_strength"] = round(_loguniform(rng, *var.world_strength), 4)
    if var.light_strength:
        out["light_strength"] = round(_loguniform(rng, *var.light_strength), 4)
    if var.sun_elevation_deg:
        out["sun_elevation_deg"] = round(rng.uniform(*var.sun_elevation_deg), 3)
        out["sun_azimuth_deg"] = round(rng.uniform(0.0, 360.0), 3)
    if hdris:
        out["hdri"] = rng.choice(hdris)
        out["hdri_rotation_deg"] = round(rng.uniform(0.0, 360.0), 3)
    return out or None


def _loguniform(rng, lo: float, hi: float) -> float:
    import math
    return math.exp(rng.uniform(math.log(lo), math.log(hi))) if hi > lo else lo


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in text)
