"""The one typed-table helper (gbuffer_export.typed_table): types from annotations, option() rules, errors that name
the config key, one [low, high] rule for every config, and the CLI putting its flag in the key's place."""
from __future__ import annotations

import argparse
from dataclasses import dataclass

import pytest

from gbuffer_export.config import ConfigError, RenderConfig
from gbuffer_export.typed_table import checked_values, from_table, option, set_checked


@dataclass(frozen=True)
class Table:
    crop: int = option(64, lo=1)
    eps: float = option(0.01, lo=0, lo_open=True, hi=1)
    mode: str = option("a", choices=("a", "b"))
    scale: tuple[float, float] = option((0.5, 2.0), pair=True)
    names: tuple[str, ...] = option(("x",), items=("x", "y"), unique=True)
    size: int | None = option(None, lo=0)
    on: bool = True


@pytest.mark.parametrize("table, words", [
    ({"crops": 1}, "f.toml: unknown key data.crops (known: crop, eps, mode, scale, names, size, on)"),
    ({"crop": "x"}, "f.toml: data.crop: expected an integer, got 'x'"),
    ({"crop": True}, "data.crop: expected an integer, got True"),
    ({"crop": 0}, "f.toml: data.crop 0: must be a positive integer"),
    ({"eps": 0}, "data.eps 0.0: must lie in (0, 1]"),
    ({"eps": float("nan")}, "data.eps nan: must be a finite number"),
    ({"mode": "c"}, "data.mode 'c': choose one of a, b"),
    ({"scale": [2, 1]}, "data.scale [2, 1]: need 0 < low <= high"),
    ({"scale": "x"}, "data.scale 'x': expected [low, high]"),
    ({"names": ["x", "z"]}, "data.names item 'z': choose one of x, y"),
    ({"names": ["x", "x"]}, "data.names ('x', 'x'): an item is repeated"),
    ({"size": -1}, "data.size -1: must be an integer >= 0"),
    ({"on": 1}, "data.on: expected true or false, got 1"),
])
def test_bad_values_are_one_line_errors_naming_the_key(table, words):
    with pytest.raises(ConfigError) as e:
        from_table(Table, table, "data", prefix="f.toml: ")
    assert words in str(e.value) and "\n" not in str(e.value)
    assert e.value.key.startswith("data.")


def test_a_table_parses_into_the_frozen_dataclass_with_normalised_values():
    t = from_table(Table, {"crop": 32, "eps": 1, "scale": 1.5, "names": ["y", "x"], "size": 3}, "data")
    assert t == Table(crop=32, eps=1.0, scale=(1.5, 1.5), names=("y", "x"), size=3)
    assert isinstance(t.eps, float) and from_table(Table, {}, "data") == Table()
    base = Table(crop=8)
    assert from_table(Table, {"mode": "b"}, "data", base=base) == Table(crop=8, mode="b")


def test_one_range_rule_for_the_training_config_and_the_dataset_spec():
    from gbuffer_export.dataset.spec import SpecError, parse_spec
    from training.config import config_from_dict
    assert config_from_dict({"data": {"exposure_range": 1.5}}).data.exposure_range == [1.5, 1.5]
    spec = parse_spec({"source": [{"kind": "builtin", "seeds": 0, "hdri_strength": 1.5}]})
    assert spec.sources[0].environment.strength == (1.5, 1.5)
    with pytest.raises(ConfigError, match=r"data.exposure_range \[2, inf\]: need 0 < low <= high"):
        config_from_dict({"data": {"exposure_range": [2, float("inf")]}})
    with pytest.raises(SpecError, match=r"source\[0\]\.hdri_strength \[2, inf\]: need 0 < low <= high"):
        parse_spec({"source": [{"kind": "builtin", "seeds": 0, "hdri_strength": [2, float("inf")]}]})


def test_an_instance_built_in_code_is_checked_too():
    @dataclass
    class Mutable:
        n: int = option(1, lo=1, hi=4)
        x: float = 0.0

    m = Mutable(n=2, x=3)
    set_checked(m, "model.m")
    assert m.x == 3.0 and isinstance(m.x, float)
    with pytest.raises(ConfigError, match=r"^model.m.n 9: must be an integer in 1..4$"):
        checked_values(Mutable(n=9), "model.m")


def test_the_core_names_keys_and_the_cli_its_flags(tmp_path):
    from gbuffer_export.commands import flags_named
    with pytest.raises(ConfigError) as e:
        RenderConfig(output=tmp_path / "c", hr_spp=0)
    assert str(e.value).startswith("hr_spp 0: must be an integer in 1..16777216") and e.value.key == "hr_spp"
    args = argparse.Namespace(hr_spp=0, hr_size=None)
    with pytest.raises(ConfigError, match=r"^--hr-spp 0: must be an integer in 1\.\.16777216"):
        with flags_named(args):
            RenderConfig(output=tmp_path / "c", hr_spp=0)
    with pytest.raises(ConfigError, match=r"^scene: .*; set camera_path walk$"):  # no such flag: unchanged
        with flags_named(args):
            raise ConfigError("scene: no camera; set camera_path walk", key="camera_path")


def test_dataset_specs_take_render_config_defaults():
    """One set of defaults: a spec's per-clip RenderSettings is generated from RenderConfig's keys."""
    import dataclasses

    from gbuffer_export.dataset.spec import CLIP_DEFAULTS, RENDER_KEYS, RenderSettings, parse_spec
    render = parse_spec({"source": [{"kind": "builtin", "seeds": 0}]}).sources[0].render
    defaults = RenderConfig(output=".")
    assert render == RenderSettings() and [f.name for f in dataclasses.fields(RenderSettings)] == list(RENDER_KEYS)
    for k in RENDER_KEYS:
        if k == "scales":  # None in a spec: one level, what RenderConfig spells (scale,)
            assert render.scales is None and defaults.scales == (float(defaults.scale),)
            continue
        assert getattr(render, k) == CLIP_DEFAULTS.get(k, getattr(defaults, k)), k
    assert (render.hr_spp, render.lr_spp, render.hr_denoise) == (64, 4, False)
    with pytest.raises(ConfigError, match=r"x.toml: render.lr_spp 0: must be an integer in 1..16777216"):
        parse_spec({"render": {"lr_spp": 0}, "source": [{"kind": "builtin", "seeds": 0}]}, "x.toml")
