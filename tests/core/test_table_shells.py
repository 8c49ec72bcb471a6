"""The shells derived from a typed table (gbuffer_export.table_shells): blendsr render's flags, the dataset spec's
render keys, the add-on's property table and the docs' table come from RenderConfig's fields; a key whose value is
a word or a number ("auto" | float) goes through every shell; the derived files are not stale."""
from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass

import pytest

from gbuffer_export.config import CLI, CLIP_PANEL, DATASET_PANEL, SPEC, ConfigError, RenderConfig
from gbuffer_export.commands.shells import derived_files
from gbuffer_export.table_shells import (add_arguments, markdown_table, property_table, shell_keys, value_from_text,
                                         values_from_args)
from gbuffer_export.typed_table import fields_of, from_table, option, set_checked


@dataclass
class Trial:
    """A table with one key of each kind a shell takes."""

    spp: int = option(8, lo=1, hi=64, unit="samples per pixel", label="Samples", help="samples")
    threshold: float = option(0.5, lo=0, hi=1, hi_open=True, help="a threshold")
    denoise: bool = option(False, help="denoise")
    mode: str = option("a", choices=("a", "b"), help="a mode")
    exposure: str | float = option("auto", choices=("auto",), lo=0, lo_open=True, help="auto, or a multiplier")
    bounces: int | None = option(None, lo=0, shells=(CLI,), help="bounces (none: the scene's)")
    hidden: str = option("x", shells=(), help="by hand")

    def __post_init__(self):
        set_checked(self)


def test_the_flags_come_from_the_fields():
    p = argparse.ArgumentParser()
    add_arguments(p, Trial, CLI)
    assert values_from_args(p.parse_args([]), Trial) == {
        "spp": 8, "threshold": 0.5, "denoise": False, "mode": "a", "exposure": "auto", "bounces": None}
    args = p.parse_args(["--spp", "3", "--threshold", "0.25", "--denoise", "--mode", "b", "--exposure", "1.5",
                         "--bounces", "2"])
    got = Trial(**values_from_args(args, Trial))
    assert (got.spp, got.threshold, got.denoise, got.mode, got.exposure, got.bounces) == (3, 0.25, True, "b", 1.5, 2)
    assert Trial(**values_from_args(p.parse_args(["--no-denoise", "--exposure", "auto"]), Trial)).exposure == "auto"
    with pytest.raises(SystemExit):
        p.parse_args(["--mode", "c"])  # choices from the rule
    with pytest.raises(SystemExit):
        p.parse_args(["--hidden", "y"])  # shells=(): not derived
    for bad, words in ((["--exposure", "bright"], "exposure 'bright': choose one of auto"),
                       (["--exposure", "-1"], "exposure -1.0: must be a number > 0"),
                       (["--spp", "99"], "spp 99: must be an integer in 1..64")):
        with pytest.raises(ConfigError, match=words):
            Trial(**values_from_args(p.parse_args(bad), Trial))


def test_a_word_or_a_number_in_every_shell():
    typ = fields_of(Trial)["exposure"][0]
    assert value_from_text("0.5", typ) == 0.5 and value_from_text("auto", typ) == "auto"
    assert from_table(Trial, {"exposure": 2}).exposure == 2.0 and from_table(Trial, {"exposure": "auto"})
    with pytest.raises(ConfigError, match="exposure 'dim': choose one of auto"):
        from_table(Trial, {"exposure": "dim"})
    table = {e["name"]: e for e in property_table(Trial, (CLI,))}
    assert table["exposure"]["kind"] == "text" and table["exposure"]["default"] == "auto"
    assert table["mode"]["kind"] == "enum" and table["mode"]["items"] == ["a", "b"]
    assert table["spp"] | {} == {"name": "spp", "kind": "int", "default": 8, "label": "Samples", "help": "samples",
                                 "unit": "samples per pixel", "shells": ["cli"], "min": 1, "max": 64}
    assert table["threshold"]["max"] == pytest.approx(0.999) and table["bounces"]["kind"] == "text"
    assert "hidden" not in table
    doc = markdown_table(Trial)
    assert '| `exposure` | "auto" or float > 0 | "auto" |  | auto, or a multiplier |' in doc
    assert "| `spp` | int in 1..64 | 8 | samples per pixel | samples |" in doc


def test_every_render_key_has_help_and_the_shells_take_it():
    for name, (_, r) in fields_of(RenderConfig).items():
        assert r.help, f"RenderConfig.{name}: give it option(help=...)"
    from gbuffer_export.dataset.spec import RENDER_KEYS, RenderSettings
    assert RENDER_KEYS == ("frames", *shell_keys(RenderConfig, SPEC))
    assert [f.name for f in dataclasses.fields(RenderSettings)] == list(RENDER_KEYS)
    from gbuffer_export.commands.render import add_render_arguments, config_from_args
    p = argparse.ArgumentParser()
    add_render_arguments(p)
    for key in shell_keys(RenderConfig, CLI):  # each derived flag sets its key (a non-default value)
        typ, r = fields_of(RenderConfig)[key]
        default = RenderConfig.__dataclass_fields__[key].default
        if r.choices:
            value, argv = r.choices[-1], [f"--{key.replace('_', '-')}", r.choices[-1]]
        elif typ is bool:
            value, argv = not default, [f"--{'no-' if default else ''}{key.replace('_', '-')}"]
        else:
            value = 0.5 if typ is float else 3 if key != "camera_path" else "orbit"
            argv = [f"--{key.replace('_', '-')}", str(value)]
        cfg = config_from_args(p.parse_args(["-o", "out", *argv]))
        assert getattr(cfg, key) == value, key
    panel = {e["name"] for e in property_table(RenderConfig, (CLIP_PANEL, DATASET_PANEL))}
    assert set(shell_keys(RenderConfig, DATASET_PANEL)) <= set(RENDER_KEYS) and panel


def test_the_files_derived_from_render_config_are_current():
    for path, text in derived_files().items():
        assert path.read_text() == text, f"{path} is stale: run make generate"


def test_the_training_tables_of_the_docs_are_current():
    from gbuffer_export.table_shells import CONFIG_DOC
    from training.commands.config_tables import SECTIONS, derived_doc
    text = CONFIG_DOC.read_text()
    assert derived_doc(text) == text, "docs/configuration.md is stale: run make generate"
    for section, cls in SECTIONS.items():
        for name, (_, r) in fields_of(cls).items():
            assert r.help or name == "options", f"{section}.{name}: give it option(help=...)"
