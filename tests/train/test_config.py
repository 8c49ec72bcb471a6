"""Training configuration: the shared [model] keys, each model's own [model.<name>] table, the legacy rule for old
flat keys, and every shipped or example configuration and checkpoint still loading."""
import dataclasses
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from gbuffer_export.config import ConfigError
from training.config import (LEGACY_FLAT_KEYS, ModelConfig, config_from_checkpoint, config_from_dict,
                             legacy_model_keys, load_config)
from training.models import MODELS
from training.models.options import FuseSRLightOptions, FuseSROptions, NoOptions, RDGSmallOptions

ROOT = Path(__file__).resolve().parents[2]

#: The [model] table of a configuration written before per-model tables (the shipped weights hold this form).
OLD_FLAT_MODEL = {"name": "fusesr", "scale": 4, "history": -1, "hr_gbuffer": False, "demodulation": True,
                  "input_transform": "log1p", "depth_norm": "ratio", "width": 0, "blocks": 2, "residual": True,
                  "upsample_by_class": True, "hr_guide": False, "guided_upsample": True, "guide_sigma_depth": 0.2,
                  "guide_sigma_normal": 0.3, "zero_init_refine": True, "jitter": True, "norm": "none",
                  "remod_filter": "BLACKMAN_HARRIS", "remod_filter_px": 1.5, "rdg_demod": False,
                  "rdg_gbuffers": ["normal", "brdf", "depth", "motion"]}


@pytest.mark.parametrize("name", list(MODELS))
def test_an_unknown_option_of_a_model_is_rejected_with_that_models_options_listed(name):
    fields = [f.name for f in dataclasses.fields(MODELS[name].options)]
    with pytest.raises(ConfigError) as err:
        load_config(None, [f'model.name="{name}"', f"model.{name}.zap=1"])
    msg = str(err.value)
    assert f"unknown key model.{name}.zap" in msg and "\n" not in msg
    if fields:
        assert msg.endswith(f"(known: {', '.join(fields)})")
    else:
        assert msg.endswith(f"(model {name} has no options of its own)")
    # the defaults of every model's options are valid, and a model without options needs nothing in the table
    cfg = load_config(None, [f'model.name="{name}"'])
    assert type(cfg.model.options) is MODELS[name].options and not cfg.notes


def test_every_models_options_are_a_dataclass_with_a_validate_and_the_table_stays_torch_free():
    for name, info in MODELS.items():
        assert dataclasses.is_dataclass(info.options) and callable(info.options().validate), name
        shared = {f.name for f in dataclasses.fields(ModelConfig)}
        assert not shared & {f.name for f in dataclasses.fields(info.options)}, name  # one place per key
    assert dataclasses.fields(NoOptions) == ()
    code = ("import sys, training.config as c, training.models; c.load_config(None, ['model.fusesr.width=8']); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "False"


def test_per_model_tables_from_toml_and_set_round_trip_through_the_saved_form(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('[model]\nname = "fusesr-l"\njitter = false\n[model.fusesr-l]\nwidth = 32\nnorm = "batch"\n'
                 '[model.rdg]\ndemod = true\n')
    cfg = load_config(p, ["model.fusesr-l.blocks=2", "model.fusesr-l.width=48"])
    assert cfg.model.name == "fusesr-l" and cfg.model.jitter is False
    assert cfg.model.options == FuseSRLightOptions(width=48, blocks=2, norm="batch")
    # another model's table is checked, then left out with a note (one file can serve several models)
    assert cfg.notes == (f"{p}: [model.rdg] is not used (model.name is 'fusesr-l')",)
    saved = cfg.to_dict()["model"]
    assert saved["fusesr-l"]["width"] == 48 and "rdg" not in saved and "width" not in saved
    back = tmp_path / "back.toml"
    back.write_text(cfg.to_toml())
    assert "[model.fusesr-l]\n" in back.read_text()
    again = load_config(back)
    assert again.to_dict() == cfg.to_dict() and not again.notes
    assert config_from_checkpoint(cfg.to_dict()).to_dict() == cfg.to_dict()  # new-form checkpoints load as saved
    with pytest.raises(ConfigError, match=r"unknown key model.rdg.width_px \(known: width, demod, gbuffers, "
                                          r"residual, zero_init_head\)"):
        load_config(p, ["model.rdg.width_px=3"])
    with pytest.raises(ConfigError, match=r"model.rdg.gbuffers item 'albedo'"):
        load_config(p, ['model.rdg.gbuffers=["albedo"]'])
    with pytest.raises(ConfigError, match="model.fusesr-l.width: expected an integer"):
        load_config(p, ["model.fusesr-l.width=wide"])
    with pytest.raises(ConfigError, match=r"model.fusesr-l.width 0: must be an integer in 1..1024"):
        load_config(p, ["model.fusesr-l.width=0"])
    with pytest.raises(ConfigError, match=r"model.fusesr must be a table"):
        load_config(None, ["model.fusesr=3"])
    with pytest.raises(ConfigError, match=r"unknown key model.srgan .*table \[model.NAME\]"):
        load_config(None, ["model.srgan.width=3"])


def test_model_config_of_splits_shared_keys_and_options():
    cfg = ModelConfig.of("rdg-s", jitter=False, demod=True, width=8)
    assert not cfg.jitter and cfg.options == RDGSmallOptions(width=8, demod=True)
    assert ModelConfig(name="fusesr").options == FuseSROptions()
    with pytest.raises(ConfigError, match="model bilinear: no key 'width'"):
        ModelConfig.of("bilinear", width=3)
    bad = ModelConfig(name="rdg", options=FuseSROptions())
    with pytest.raises(ConfigError, match="model.rdg: options of type FuseSROptions, expected RDGOptions"):
        bad.validate()


def test_legacy_flat_keys_map_to_the_table_of_the_model_in_use(tmp_path):
    # an old-style TOML file and old-style --set overrides
    p = tmp_path / "old.toml"
    p.write_text('[model]\nname = "fusesr"\nhr_gbuffer = false\nwidth = 0\nguide_sigma_depth = 0.2\n'
                 'rdg_demod = false\n')
    cfg = load_config(p, ["model.blocks=2"])
    assert cfg.model.options == FuseSROptions(hr_gbuffer=False, blocks=2, guide_sigma_depth=0.2)  # width 0: default
    assert not cfg.notes  # rdg_demod at its old default: nothing to say
    rdg = load_config(p, ['model.name="rdg-s"', "model.rdg_demod=true", 'model.rdg_gbuffers=["normal"]',
                          "model.width=8"])
    assert (rdg.model.options.demod, rdg.model.options.gbuffers, rdg.model.options.width) == (True, ["normal"], 8)
    assert rdg.notes == (f"{p}: model.hr_gbuffer is not an option of model rdg-s (not used)",
                         f"{p}: model.guide_sigma_depth is not an option of model rdg-s (not used)")
    assert "hr_gbuffer" not in rdg.to_dict()["model"]["rdg-s"]
    with pytest.raises(ConfigError, match="model.width and model.fusesr.width both given; keep model.fusesr.width"):
        load_config(p, ["model.width=8", "model.fusesr.width=8"])
    with pytest.raises(ConfigError, match=r"model.fusesr.width -3: must be an integer"):
        load_config(p, ["model.width=-3"])
    # the rule itself: a pure function of the [model] table
    table, notes = legacy_model_keys(OLD_FLAT_MODEL, "ck")
    assert set(table) == {"name", "scale", "history", "input_transform", "depth_norm", "upsample_by_class", "jitter",
                          "remod_filter", "remod_filter_px", "fusesr"}
    assert table["fusesr"] == {"hr_gbuffer": False, "demodulation": True, "blocks": 2, "residual": True,
                               "hr_guide": False, "guided_upsample": True, "guide_sigma_depth": 0.2,
                               "guide_sigma_normal": 0.3, "zero_init_refine": True, "norm": "none"}
    assert notes == [] and OLD_FLAT_MODEL["width"] == 0  # the input is not modified
    assert legacy_model_keys(table) == (table, [])  # the new form passes unchanged
    every_option = {f.name for info in MODELS.values() for f in dataclasses.fields(info.options)}
    assert {new for new, _ in LEGACY_FLAT_KEYS.values()} <= every_option


def test_old_checkpoint_configurations_load_with_their_old_behaviour():
    new = config_from_checkpoint({"model": OLD_FLAT_MODEL})
    assert new.model.options == FuseSROptions(hr_gbuffer=False, blocks=2, guide_sigma_depth=0.2,
                                              zero_init_refine=True)
    assert new.model.remod_filter == "BLACKMAN_HARRIS"
    # a checkpoint from before jitter, norm, the pixel filter, class-aware and guided upsampling
    oldest = {k: v for k, v in OLD_FLAT_MODEL.items() if k not in
              ("jitter", "norm", "remod_filter", "remod_filter_px", "upsample_by_class", "guided_upsample",
               "zero_init_refine", "hr_guide", "guide_sigma_depth", "guide_sigma_normal", "rdg_demod",
               "rdg_gbuffers")}
    cfg = config_from_checkpoint({"model": oldest, "data": {"crop": 32}})
    assert (cfg.model.jitter, cfg.model.remod_filter, cfg.model.upsample_by_class) == (False, "NONE", False)
    assert (cfg.model.options.norm, cfg.model.options.guided_upsample, cfg.model.options.zero_init_refine) == \
        ("batch", False, False)
    assert cfg.data.reflectance_range == [1.0, 1.0]
    rdg = config_from_checkpoint({"model": {**oldest, "name": "rdg-s", "rdg_demod": True}})
    assert rdg.model.options.demod and rdg.model.options.width == 16  # fusesr-only keys and width 0 dropped


@pytest.mark.parametrize("path", sorted((ROOT / "examples").glob("*config*.toml")) + [ROOT / "benchmarks" /
                                                                                    "pretrain.toml"],
                         ids=lambda p: p.name)
def test_example_configurations_load_in_the_new_form(path):
    raw = tomllib.loads(path.read_text()).get("model", {})
    assert not set(raw) & set(LEGACY_FLAT_KEYS), "old flat [model] keys in an example"
    cfg = load_config(path)
    assert type(cfg.model.options) is MODELS[cfg.model.name].options


@pytest.mark.torch
@pytest.mark.parametrize("path", sorted((ROOT / "training" / "weights").glob("*.safetensors")), ids=lambda p: p.name)
def test_every_shipped_checkpoint_loads_and_runs_as_trained(path):
    pytest.importorskip("torch")
    from training.checkpoint import load_checkpoint
    from training.models import build_model
    ck = load_checkpoint(path)
    cfg = config_from_checkpoint(ck["config"], source=str(path))
    assert cfg.model.name == ck["model_name"] and type(cfg.model.options) is MODELS[cfg.model.name].options
    model = build_model(cfg.model, int(ck["scale"]))
    model.load_state_dict(ck["model"])  # strict: every weight of the saved network and nothing else
    saved = ck["config"]["model"]
    flat = {k: saved[k] for k in LEGACY_FLAT_KEYS if k in saved}  # the shipped files hold the old flat form
    for old, value in flat.items():
        new, _ = LEGACY_FLAT_KEYS[old]
        if hasattr(cfg.model.options, new) and not (old in ("width", "blocks") and value == 0):
            assert getattr(cfg.model.options, new) == value, old
    assert config_from_checkpoint(cfg.to_dict()).to_dict() == cfg.to_dict()


def test_config_from_dict_keeps_the_other_sections_strict():
    with pytest.raises(ConfigError, match=r"unknown key data.crops \(known: clips, crop,"):
        config_from_dict({"data": {"crops": 3}})
    with pytest.raises(ConfigError, match=r"model.name 3: choose one of|model.name: expected a string"):
        config_from_dict({"model": {"name": 3}})


@pytest.mark.torch
def test_train_prints_a_note_for_the_table_of_another_model(tmp_path, capsys):
    pytest.importorskip("torch")
    from gbuffer_export.cli import main
    code = main(["train", "--model", "fusesr-l", "-o", str(tmp_path / "run"), "--set", "model.rdg.demod=true"])
    err = capsys.readouterr().err
    assert code == 2 and "note: --set: [model.rdg] is not used (model.name is 'fusesr-l')" in err
    assert "no training clips" in err


def test_docs_configuration_lists_every_key_and_every_models_table():
    from typing import get_type_hints

    from training.config import TrainConfig
    text = (ROOT / "docs" / "configuration.md").read_text()
    sections = re.split(r"\n## ", text)
    hints = get_type_hints(TrainConfig)
    for section, cls in ((f.name, hints[f.name]) for f in dataclasses.fields(TrainConfig)):
        body = next(s for s in sections if s.startswith(f"`[{section}]`"))
        for f in dataclasses.fields(cls):
            if f.name != "options":
                assert f"| `{f.name}` |" in body, (section, f.name)
    for name, info in MODELS.items():
        fields = dataclasses.fields(info.options)
        if not fields:
            assert f"`{name}`" in text, name
            continue
        head = next(h for h in re.findall(r"\n### (.*)\n", text) if f"`[model.{name}]`" in h)
        body = text.split(f"\n### {head}\n")[1].split("\n### ")[0]
        for f in fields:
            assert f"| `{f.name}` |" in body, (name, f.name)
    block = re.search(r"```toml\n(.*?)```", text, re.S).group(1)
    cfg = config_from_dict(tomllib.loads(block))
    assert cfg.model.options == FuseSRLightOptions(width=48) and cfg.model.jitter is True
