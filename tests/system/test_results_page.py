"""docs/results.md is generated from the records under docs/bench/ (gbuffer_export/results_page.py)."""
from __future__ import annotations

import json

import pytest

from gbuffer_export import results_page
from gbuffer_export.results_page import MAX_LINES, PAGE, PageError, page_text


def test_the_committed_page_is_what_its_records_give_and_short():
    text = page_text()
    assert PAGE.read_text() == text, "docs/results.md is stale: run python -m training.commands.generate"
    assert len(text.splitlines()) <= MAX_LINES, f"docs/results.md has {len(text.splitlines())} lines (at most {MAX_LINES})"


def _worst_case_record(psnr: float, margin: float) -> dict:
    mean = {"psnr": psnr, "margin": margin, "margin_min": margin - 1, "margin_min_clip": "datasets/x/clips/a-00",
            "ssim": 0.9, "tpsnr": psnr - 2, "artifact_fraction": 0.0001, "artifact_fraction_max": 0.0003}
    return {"objects": {"clips": ["a-00", "b-00"], "models": {"pretrained:m": {"mean": mean}}}}


def _page(tmp_path, monkeypatch, record: dict) -> str:
    (tmp_path / "docs" / "bench").mkdir(parents=True)
    (tmp_path / "docs" / "bench" / "r.json").write_text(json.dumps(record))
    definition = tmp_path / "docs" / "bench" / "page.toml"
    definition.write_text('[page]\ntitle = "T"\nintro = "I"\n[[section]]\ntitle = "S"\ndate = "2026-11-28"\n'
                          'command = "cmd"\n[[section.table]]\nkind = "margins"\ngroups = ["objects"]\n'
                          'rows = [{record = "docs/bench/r.json", model = "pretrained:m"}]\n')
    monkeypatch.setattr(results_page, "REPO", tmp_path)
    return page_text(definition)


def test_a_table_cell_changes_with_its_record(tmp_path, monkeypatch):
    text = _page(tmp_path, monkeypatch, _worst_case_record(31.234, 1.5))
    assert ("| objects (2 clips) | `pretrained:m` | 31.23 | +1.50 | +0.50 (a-00) | 0.9000 | 29.23 | 0.010% | 0.030% |"
            in text)
    text = _page(tmp_path / "2", monkeypatch, _worst_case_record(30.0, -0.25))
    assert "| 30.00 | -0.25 | -1.25 (a-00) |" in text


def test_a_section_without_its_command_or_a_missing_record_is_refused(tmp_path, monkeypatch):
    with pytest.raises(PageError, match="r.json, which does not exist"):
        (tmp_path / "docs" / "bench").mkdir(parents=True)
        definition = tmp_path / "docs" / "bench" / "page.toml"
        definition.write_text('[page]\ntitle = "T"\nintro = "I"\n[[section]]\ntitle = "S"\ndate = "d"\ncommand = "c"\n'
                              '[[section.table]]\nkind = "table"\nrecord = "docs/bench/r.json"\n')
        monkeypatch.setattr(results_page, "REPO", tmp_path)
        page_text(definition)
    definition.write_text('[page]\ntitle = "T"\nintro = "I"\n[[section]]\ntitle = "S"\ndate = "d"\n')
    with pytest.raises(PageError, match="has no 'command'"):
        page_text(definition)


def test_pivoted_rows_and_significant_digits(tmp_path, monkeypatch):
    rows = [{"model": "a", "variant": "fp32", "ms": 36335.2}, {"model": "a", "variant": "bf16", "ms": 0.30612},
            {"model": "b", "variant": "fp32", "ms": 2.4051}]
    (tmp_path / "r.json").write_text(json.dumps({"rows": rows}))
    monkeypatch.setattr(results_page, "REPO", tmp_path)
    table = results_page.rows_table({"record": "r.json", "columns": [["model", "model"]],
                                     "pivot": ["model", "variant", "ms", "sig3"], "pivot_header": "{} ms"}, "t")
    assert table.splitlines() == ["| model | fp32 ms | bf16 ms |", "|---|---|---|", "| a | 36,335 | 0.306 |",
                                  "| b | 2.41 |  |"]


def test_a_dotted_column_reads_a_nested_value(tmp_path, monkeypatch):
    rows = [{"model": "fusesr", "x": 3.04, "margin_by_family": {"held-out": 1.234, "in-family": 2.0}},
            {"model": "demod-jbu", "x": None}]
    (tmp_path / "r.json").write_text(json.dumps({"rows": rows}))
    monkeypatch.setattr(results_page, "REPO", tmp_path)
    table = results_page.rows_table({"record": "r.json", "columns": [
        ["model", "model"], ["x", "x", "{:.1f}"], ["held-out", "margin_by_family.held-out", "{:+.2f}"]]}, "t")
    assert table.splitlines()[2:] == ["| fusesr | 3.0 | +1.23 |", "| demod-jbu |  |  |"]


def test_a_table_record_holding_several_tables_is_read_by_key(tmp_path, monkeypatch):
    """family_gap --json writes its tables under names; the page's `table` kind picks one with `key`."""
    gap = {"columns": ["model", "gap (dB)"], "rows": [["`fusesr`", "+0.40"]]}
    (tmp_path / "g.json").write_text(json.dumps({"gap": gap, "by_kind": {"columns": ["model"], "rows": []}}))
    monkeypatch.setattr(results_page, "REPO", tmp_path)
    table = results_page.literal_table({"record": "g.json", "key": "gap"}, "t")
    assert table.splitlines() == ["| model | gap (dB) |", "|---|---|", "| `fusesr` | +0.40 |"]
    with pytest.raises(PageError, match="g.json: no table 'kind'"):
        results_page.literal_table({"record": "g.json", "key": "kind"}, "t")


def test_generate_check_finds_every_derived_file_current():
    from training.commands.generate import main
    assert main(["--check"]) == 0
