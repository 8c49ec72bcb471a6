"""Families: what a clip is made of, for splits that hold out whole families (pure Python, no bpy, no torch).

A family is one thing a clip can show that training could learn by heart: an object asset (``asset:STEM``), a
level (``level:STEM``, a scene file's stem), an HDRI (``hdri:NAME``: ``builtin:NAME`` of bpy's eight, or a file's
stem), or one of the built-in generator's families (``BUILTIN_FAMILIES``: ``prop:window_pane``,
``material:voronoi``, ``geometry:railing``, ``light:neon``, ``camera:pan``, ``motion:objects``, ...). A spec lists held-out families in
``[splits]`` (``val_families``, ``test_families``); ``expand`` (``spec.py``) refuses a spec where such a family can
appear in a clip of an earlier split (a test family in a train or val clip, a val family in a train clip), counting
every family a clip could draw (its HDRI pool, its clutter candidates, its props), and records in each clip the
families it holds and whether it is ``in-family`` or ``held-out`` (it holds a declared held-out family).

``family_gap.py`` reports per-clip margins over ``demod-jbu`` of the two groups side by side, and their difference.
"""
from __future__ import annotations

from pathlib import Path

#: Family kinds: the first three come from a spec's files, the rest are the built-in generator's.
FAMILY_KINDS = ("asset", "level", "hdri", "prop", "material", "geometry", "light", "camera", "motion")

#: The built-in generator's opt-in families (``props = [...]`` of a builtin source) -> their kind; each draws from a
#: random stream of its own (the bpy layer's ``OPTIONAL_PROPS`` holds the same names).
BUILTIN_FAMILIES: dict[str, str] = {
    "broken_pane": "prop", "window_pane": "prop",
    "mat_noise": "material", "mat_voronoi": "material", "mat_wave": "material", "mat_brick": "material",
    "mat_layered": "material", "mat_surfaces": "material",
    "railing": "geometry", "wires": "geometry", "foliage_cards": "geometry", "stripes_panel": "geometry",
    "text_panel": "geometry", "scatter": "geometry",
    "neon": "light", "small_emitters": "light", "strong_sun": "light", "night": "light",
    "cam_pan": "camera", "cam_strafe": "camera", "cam_turn": "camera", "cam_cut": "camera",
    "boolean": "geometry", "displaced": "geometry", "instanced": "geometry", "fog": "light", "motion_objects": "motion",
    "motion_character": "motion",
}
#: Camera families re-key the built-in scene's own camera: only with ``cameras = ["scene"]``.
CAMERA_FAMILIES = tuple(k for k, v in BUILTIN_FAMILIES.items() if v == "camera")

IN_FAMILY, HELD_OUT = "in-family", "held-out"
#: Sub-groups of the held-out clips (``unseen_content``): those that show an object asset, or a level, that the
#: training never saw: what "real objects and levels never seen" measures. Apart, since an unseen level and an unseen
#: asset gain very differently over demod-jbu (levels far more). The other held-out clips hold out a built-in
#: generator family or an HDRI only.
HELD_OUT_ASSET, HELD_OUT_LEVEL = "held-out asset", "held-out level"
UNSEEN_CONTENT = {"asset": HELD_OUT_ASSET, "level": HELD_OUT_LEVEL}


def builtin_family(name: str) -> str:
    """The family id of a built-in generator family (a builtin source's prop): ``KIND:NAME`` without the ``mat_``,
    ``cam_`` and ``motion_`` prefixes (``mat_voronoi`` -> ``material:voronoi``, ``motion_objects`` ->
    ``motion:objects``, ``window_pane`` -> ``prop:window_pane``)."""
    kind = BUILTIN_FAMILIES[name]
    short = name.split("_", 1)[1] if kind in ("material", "camera", "motion") else name
    return f"{kind}:{short}"


def hdri_family(entry: str) -> str:
    """``hdri:NAME`` of an HDRI pool entry: ``builtin:NAME`` or a file path (its stem)."""
    return "hdri:" + (entry.split(":", 1)[1] if entry.startswith("builtin:") else Path(entry).stem)


#: Every family id the built-in generator has.
BUILTIN_FAMILY_IDS = tuple(builtin_family(n) for n in BUILTIN_FAMILIES)


def check_family_id(fid: str) -> str | None:
    """None when ``fid`` is a well-formed family id, else what is wrong with it (one phrase)."""
    kind, sep, name = fid.partition(":")
    if not sep or not name:
        return f"expected KIND:NAME with KIND one of {', '.join(FAMILY_KINDS)} (e.g. \"asset:SheenChair\")"
    if kind not in FAMILY_KINDS:
        return f"unknown kind {kind!r}: choose one of {', '.join(FAMILY_KINDS)}"
    if kind not in ("asset", "level", "hdri") and fid not in BUILTIN_FAMILY_IDS:
        same = [f for f in BUILTIN_FAMILY_IDS if f.startswith(kind + ":")]
        return f"the built-in generator has no such family: its {kind} families are {', '.join(same)}"
    return None


def held_split(families, val: tuple[str, ...], test: tuple[str, ...]) -> str | None:
    """The split the held-out families among ``families`` require: test, val, or None (none held out)."""
    fams = set(families)
    if fams & set(test):
        return "test"
    if fams & set(val):
        return "val"
    return None


def leak(split: str, possible, val: tuple[str, ...], test: tuple[str, ...]) -> tuple[str, str] | None:
    """(family, its split) of a held-out family that a clip of ``split`` could draw and must not (a test family in a
    train or val clip, a val family in a train clip); None when there is none."""
    order = {"train": 0, "val": 1, "test": 2}
    for fam in sorted(possible):
        need = "test" if fam in test else "val" if fam in val else None
        if need and order[need] > order[split]:
            return fam, need
    return None


def unseen_content(families, trained) -> tuple[str, ...]:
    """The sub-groups (``UNSEEN_CONTENT``) of a held-out clip that holds ``families``: ``held-out asset`` when it shows
    an object asset that ``trained`` (the families a training saw) lacks, ``held-out level`` for a level; ()
    when it shows neither."""
    kinds = {f.split(":", 1)[0] for f in set(families) - set(trained)}
    return tuple(g for k, g in UNSEEN_CONTENT.items() if k in kinds)


def family_group(families, val: tuple[str, ...], test: tuple[str, ...]) -> str:
    """``held-out`` when the clip holds a declared held-out family (one no train clip holds), else ``in-family``."""
    return HELD_OUT if set(families) & (set(val) | set(test)) else IN_FAMILY
