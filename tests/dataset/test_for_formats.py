"""What export formats need, rendered on request (issue 57, item 4): ``blendsr render --for-formats``, the spec key
``[dataset] for_formats`` and ``blendsr dataset --for-formats`` add each format's LR levels, HR size and buffers
(``format_limits.render_for_formats``, one derivation), refuse a conflicting size in one line before anything is
rendered, and ``--dry-run`` says which formats the clips can be exported to."""
from __future__ import annotations

import tomllib

import pytest

from gbuffer_export.cli import build_parser, main
from gbuffer_export.dataset.spec import SpecError, expand, parse_spec
from gbuffer_export.dataset.writer import spec_to_toml
from gbuffer_export.format_limits import FormatLimitError, clip_problem, render_for_formats

SPEC = {"dataset": {"name": "f", "seed": 1}, "render": {"frames": 2, "hr_size": "64x36"},
        "source": [{"kind": "builtin", "seeds": "0:1"}]}


def _spec(path, **dataset):
    return parse_spec({**SPEC, "dataset": {**SPEC["dataset"], **dataset}}, path)


def test_the_spec_key_renders_what_each_format_needs(tmp_path):
    path = tmp_path / "spec.toml"
    plain, nss = _spec(path), _spec(path, for_formats=["nss"])
    assert plain.sources[0].render.scales is None and plain.sources[0].render.scale == 4
    r = nss.sources[0].render
    assert nss.for_formats == ("nss",) and r.scale == 4 and r.scales == (4.0, 2.0)  # 'lr' stays the clip's level
    assert {"radiance", "depth", "motion"} <= set(r.buffers) and r.hr_size == (64, 36)
    assert parse_spec(tomllib.loads(spec_to_toml(nss)), path) == nss  # spec.toml round trip
    jobs = expand(nss)
    assert all(j.render["scales"] == [4.0, 2.0] for j in jobs)
    # the flag adds to the key; rdg adds the buffers its configs read
    both = parse_spec(dict(SPEC, dataset={**SPEC["dataset"], "for_formats": "nss"}), path, formats=("rdg",))
    assert both.for_formats == ("nss", "rdg") and {"normal", "fbeta"} <= set(both.sources[0].render.buffers)


def test_nfru_sets_its_size_or_refuses_another_in_one_line(tmp_path):
    path = tmp_path / "spec.toml"
    with pytest.raises(SpecError) as e:
        _spec(path, for_formats=["nfru"])  # hr_size = "64x36" in [render]
    line = str(e.value)
    assert "\n" not in line and str(path) in line and "dataset.for_formats" in line and "1920x1080" in line
    doc = {**SPEC, "render": {"frames": 2}, "dataset": {**SPEC["dataset"], "for_formats": ["nfru"]}}
    r = parse_spec(doc, path).sources[0].render
    assert r.hr_size == (1920, 1080) and 2.0 in r.scales
    with pytest.raises(SpecError, match=r"dataset.for_formats: unknown format 'bogus'; choose from nss, nfru, rdg"):
        _spec(path, for_formats=["bogus"])


def test_render_flag_derives_the_same_settings():
    args = build_parser().parse_args(["render", "-o", "x", "--for-formats", "nss", "--hr-size", "64x36"])
    from gbuffer_export.commands.render import config_from_args
    cfg = config_from_args(args)
    want = render_for_formats(["nss"], scales=(4,), hr_size=(64, 36), buffers=cfg.buffers)
    assert cfg.scales == (4.0, 2.0) == want["scales"] and set(want["buffers"]) <= set(cfg.buffers)
    args = build_parser().parse_args(["render", "-o", "x", "--for-formats", "nfru", "--hr-size", "640x360"])
    with pytest.raises(FormatLimitError, match=r"--for-formats nfru: .*1920x1080"):
        config_from_args(args)
    args = build_parser().parse_args(["render", "-o", "x", "--for-formats", "nfru", "--scales", "2,4"])
    cfg = config_from_args(args)
    assert cfg.hr_size == (1920, 1080) and cfg.scales == (2.0, 4.0)


def test_help_and_dry_run_say_what_each_format_needs(tmp_path, capsys):
    text = " ".join(build_parser()._subparsers._group_actions[0].choices["render"].format_help().split())
    assert "--for-formats" in text and "nss: a 2x LR level" in text and "HR 1920x1080" in text
    spec = tmp_path / "spec.toml"
    spec.write_text(spec_to_toml(_spec(spec)))
    assert main(["dataset", str(spec), "-o", str(tmp_path / "ds"), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "export nss: 2 of 2 clips cannot be (no 2x level)" in out and "--for-formats nss" in out
    assert "export rdg: every clip can be exported" in out
    assert main(["dataset", str(spec), "-o", str(tmp_path / "ds"), "--dry-run", "--for-formats", "nss"]) == 0
    assert "export nss: every clip can be exported" in capsys.readouterr().out


def test_a_clip_rendered_for_a_format_passes_its_export_check(tmp_path):
    from gbuffer_export.clip import open_clip
    from gbuffer_export.synthetic import make_synthetic_clip
    r = render_for_formats(["nss"], scales=(4,), hr_size=(32, 16), buffers=("radiance",))
    clip = open_clip(make_synthetic_clip(tmp_path / "c", frames=(1, 2), hr_size=r["hr_size"], scales=r["scales"],
                                         buffers=r["buffers"]))
    assert clip_problem("nss", clip) == "" and clip_problem("rdg", clip) == ""
    assert "NFRU needs HR 1920x1080" in clip_problem("nfru", clip)
