"""docs/results.md, written from the measurement records under docs/bench/ (no bpy, no torch).

The page is a function of two things only: ``docs/bench/results_page.toml`` (which sections, in which order, each
with its title, date, the command that reproduces it and a few lines on what was measured) and the JSON records the
benchmarks wrote (``docs/bench/<topic>/*.json``). Every table cell is read from a record; no number is typed into the
page. ``python -m training.commands.generate`` rewrites the page; ``tests/system/test_results_page.py`` fails
when the committed page differs from what the records give, or when it grows past ``MAX_LINES``.

Table kinds (``[[section.table]] kind = ...``):

- ``margins``: rows of ``benchmarks/worst_case.py`` records (``{group: {clips, models: {name: {mean: ...}}}}``): PSNR,
  margin over the baseline, smallest per-clip margin and its clip, SSIM, tPSNR, artifact pixels (all clips, and the
  clip with the most), per group.
- ``rows``: the ``rows`` list of a record (what ``blendsr bench models`` and the benchmark scripts write), one
  column per ``[header, key, format]``; with ``pivot = [row_key, column_key, value_key, format]`` one row per
  ``row_key`` and one column per value of ``column_key`` (e.g. model x variant -> ms). A dotted key, in a column,
  ``only`` or ``pivot``, reads a nested value (``margin_by_family.held-out``).
- ``table``: a record that is itself a table, ``{"columns": [...], "rows": [[...], ...]}`` (measurements whose
  script printed a table rather than writing rows), or holds several under names (``key``: ``family_gap --json``).
- ``fields``: one row per ``[label, dotted.key, format]`` of ``fields``, one column per ``[header, record]`` of
  ``records`` (e.g. a campaign's counts before and after a change).

``rows`` may name a dict instead of a list (``key``): each entry becomes a row with its name under ``name``. A format
``MB`` prints bytes as megabytes.
"""
from __future__ import annotations

import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PAGE = REPO / "docs" / "results.md"
DEFINITION = REPO / "docs" / "bench" / "results_page.toml"
MAX_LINES = 400
GENERATED_BY = "python -m training.commands.generate"


class PageError(ValueError):
    """The page definition or a record it names is unusable; the message names the file and the key."""


@dataclass(frozen=True)
class Cell:
    """One formatted value: ``fmt`` is a str.format spec such as ``{:+.2f}``, or ``sigN`` (N significant digits,
    never an exponent: 0.306, 2.41, 1137, 36,335); None prints empty."""
    value: object
    fmt: str = "{}"

    def __str__(self) -> str:
        if self.value is None or self.value == "":
            return ""
        if self.fmt == "MB" and isinstance(self.value, (int, float)):
            return f"{self.value / 1e6:,.0f}"
        if self.fmt.startswith("sig") and isinstance(self.value, (int, float)):
            return significant(float(self.value), int(self.fmt[3:]))
        try:
            return self.fmt.format(self.value)
        except (ValueError, TypeError):
            return str(self.value)


def significant(x: float, digits: int) -> str:
    """``x`` to ``digits`` significant digits in plain notation (thousands separated)."""
    if x == 0:
        return "0"
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(x))))
    return f"{x:,.{decimals}f}"


def _record(path: str, where: str) -> dict:
    file = REPO / path
    try:
        return json.loads(file.read_text())
    except FileNotFoundError:
        raise PageError(f"{DEFINITION.name}: {where} names {path}, which does not exist") from None
    except json.JSONDecodeError as exc:
        raise PageError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None


def markdown(header: list[str], rows: list[list[object]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


MARGIN_HEADER = ["data", "model", "PSNR (dB)", "margin (dB)", "smallest per-clip margin (clip)", "SSIM",
                 "tPSNR (dB)", "artifact pixels", "artifact pixels, worst clip"]


def margins_table(spec: dict, where: str) -> str:
    """Per group, one row per ``{record, model, label}`` of ``spec["rows"]``, from worst_case.py records."""
    out = []
    for group in spec.get("groups", ["objects", "levels"]):
        for row in spec["rows"]:
            data = _record(row["record"], where)
            if group not in data:
                raise PageError(f"{row['record']}: no group {group!r} (named by {where})")
            models = data[group]["models"]
            if row["model"] not in models:
                raise PageError(f"{row['record']}: no model {row['model']!r} in {group} (named by {where})")
            m = models[row["model"]]["mean"]
            worst = ""
            if m.get("margin_min_clip") and row["model"] != spec.get("baseline", "demod-jbu"):
                worst = f"{m['margin_min']:+.2f} ({Path(m['margin_min_clip']).name})"
            label = row.get("label") or f"`{row['model']}`"
            out.append([f"{group} ({len(data[group]['clips'])} clips)", label, Cell(m["psnr"], "{:.2f}"),
                        Cell(m["margin"], "{:+.2f}"), worst, Cell(m["ssim"], "{:.4f}"), Cell(m["tpsnr"], "{:.2f}"),
                        Cell(m.get("artifact_fraction"), "{:.3%}"), Cell(m.get("artifact_fraction_max"), "{:.3%}")])
    return markdown(spec.get("header", MARGIN_HEADER), out)


def rows_table(spec: dict, where: str) -> str:
    """Columns picked from a record's ``rows`` (optionally pivoted); ``only`` keeps rows whose key is listed."""
    data = _record(spec["record"], where)
    rows = _at(data, spec.get("key", "rows"))
    if isinstance(rows, dict):
        rows = [{"name": k, **v} for k, v in rows.items() if isinstance(v, dict)]
    if not isinstance(rows, list):
        raise PageError(f"{spec['record']}: no list {spec.get('key', 'rows')!r} (named by {where})")
    only = spec.get("only")
    if only:
        key, values = only
        rows = [r for r in rows if _at(r, key) in values]
    columns = spec.get("columns", [])
    if "pivot" not in spec:
        return markdown([c[0] for c in columns], [[Cell(_at(r, c[1]), c[2] if len(c) > 2 else "{}") for c in columns]
                                                  for r in rows])
    row_key, col_key, value_key, fmt = spec["pivot"]
    order = spec.get("pivot_columns") or list(dict.fromkeys(_at(r, col_key) for r in rows))
    by_row: dict[object, dict] = {}
    for r in rows:
        by_row.setdefault(_at(r, row_key), {"first": r})[_at(r, col_key)] = _at(r, value_key)
    header = [c[0] for c in columns] + [spec.get("pivot_header", "{}").format(v) for v in order]
    body = [[Cell(_at(d["first"], c[1]), c[2] if len(c) > 2 else "{}") for c in columns]
            + [Cell(d.get(v), fmt) for v in order] for d in by_row.values()]
    return markdown(header, body)


def _at(data, dotted: str):
    """``data``'s value at ``a.b.c`` (None where a key is missing)."""
    for part in dotted.split("."):
        data = data.get(part) if isinstance(data, dict) else None
    return data


def fields_table(spec: dict, where: str) -> str:
    records = [(header, _record(path, where)) for header, path in spec["records"]]
    body = [[label] + [Cell(_at(data, key), fmt) for _, data in records] for label, key, fmt in spec["fields"]]
    return markdown([spec.get("label_header", "")] + [h for h, _ in records], body)


def literal_table(spec: dict, where: str) -> str:
    data = _record(spec["record"], where)
    if spec.get("key"):  # one table of a record holding several (family_gap --json)
        if spec["key"] not in data:
            raise PageError(f"{spec['record']}: no table {spec['key']!r} (named by {where})")
        data = data[spec["key"]]
    if "columns" not in data or "rows" not in data:
        raise PageError(f"{spec['record']}: a table record needs 'columns' and 'rows' (named by {where})")
    return markdown(data["columns"], data["rows"])


TABLE_KINDS = {"margins": margins_table, "rows": rows_table, "table": literal_table, "fields": fields_table}


def section_text(section: dict, index: int) -> str:
    where = f"section {index + 1} ({section.get('title', '?')!r})"
    for key in ("title", "date", "command"):
        if not section.get(key):
            raise PageError(f"{DEFINITION.name}: {where} has no {key!r}")
    parts = [f"## {section['title']} ({section['date']})", "```\n" + section["command"].strip() + "\n```"]
    if section.get("text"):
        parts.append(section["text"].strip())
    for t, table in enumerate(section.get("table", [])):
        kind = TABLE_KINDS.get(table.get("kind"))
        if kind is None:
            raise PageError(f"{DEFINITION.name}: {where}, table {t + 1}: kind must be one of {sorted(TABLE_KINDS)}")
        if table.get("caption"):
            parts.append(table["caption"].strip())
        parts.append(kind(table, where))
        if table.get("after"):
            parts.append(table["after"].strip())
    for image in section.get("images", []):
        parts.append(f"![{image[1]}]({image[0]})")
    return "\n\n".join(parts)


def page_text(definition: Path = DEFINITION) -> str:
    """The page as the definition and the records give it."""
    try:
        spec = tomllib.loads(definition.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise PageError(f"{definition}: {exc}") from None
    head = [f"# {spec['page']['title']}",
            f"<!-- written by {GENERATED_BY} from {definition.relative_to(REPO)} and the records it names; "
            "edit those, not this page -->", spec["page"]["intro"].strip()]
    body = [section_text(s, i) for i, s in enumerate(spec.get("section", []))]
    return "\n\n".join(head + body) + "\n"


def write_page(page: Path = PAGE) -> bool:
    """Rewrite the page if it is stale (atomically); True when it changed."""
    text = page_text()
    if page.is_file() and page.read_text() == text:
        return False
    tmp = page.with_suffix(".md.tmp")
    tmp.write_text(text)
    tmp.replace(page)
    return True
