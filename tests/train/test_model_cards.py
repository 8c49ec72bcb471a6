"""Issue 57 item 7: every shipped network has a model card generated from its weights JSON; a stale card fails."""
from __future__ import annotations

import copy
import json

import pytest

from tests.conftest import REPO, shared_or_skip
from training.commands import model_cards
from training.pretrained import PRETRAINED, WEIGHTS_DIR


@pytest.fixture(scope="module")
def readme():
    return shared_or_skip("scenes/README.md").read_text(encoding="utf-8")


def test_every_shipped_network_has_a_current_card(readme):
    cards = model_cards.cards()
    assert len(cards) == len(PRETRAINED)
    assert model_cards.stale() == [], "run: make generate"


def test_cards_name_every_third_party_scene_with_its_licence_and_the_recorded_margins(readme):
    for path, text in model_cards.cards().items():
        meta = json.loads((WEIGHTS_DIR / (path.stem + ".json")).read_text())
        assert "not listed in ../shared/scenes/README.md" not in text, path.name
        assert meta["sha256"] in text and f"{meta['params']:,} parameters" in text
        scores = meta.get("scores_on_test_split") or meta["scores_on_val_split"]  # test: deferred (release_weights)
        test, base = scores[meta["model"]], scores["demod-jbu"]
        assert f"margin {test['psnr'] - base['psnr']:+.2f} dB over `demod-jbu`" in text
        for needle in ("## What it is for", "## Inputs", "## Training data", "## Speed", "## Limits"):
            assert needle in text, (path.name, needle)
    fusesr = (model_cards.CARDS_DIR / "fusesr_x4.md").read_text()
    assert "| CC-BY 4.0 | Copyright 2020 Wayfair LLC, model and textures by Eric Chadwick |" in fusesr  # SheenChair


def test_a_changed_record_or_licence_makes_the_card_stale(readme):
    stem = "fusesr_l_x4"
    meta = json.loads((WEIGHTS_DIR / f"{stem}.json").read_text())
    spec = (REPO / meta["dataset"]["spec_file"]).read_text()
    buffers = json.loads(model_cards.BUFFERS_JSON.read_text())
    now = model_cards.card_text(stem, meta, spec, readme, buffers)
    assert now == (model_cards.CARDS_DIR / f"{stem}.md").read_text()
    other = copy.deepcopy(meta)
    other["scores_on_val_split"]["fusesr-l"]["psnr"] -= 2.0  # the recorded val score changes
    assert "Below `demod-jbu` on the val split's mean" in model_cards.card_text(stem, other, spec, readme, buffers)
    relicensed = readme.replace("| CC0 + CC-BY 4.0 | Low poly fox", "| CC-BY 4.0 | Low poly fox")
    assert model_cards.card_text(stem, meta, spec, relicensed, buffers) != now
    assert "absent when generated" in model_cards.card_text(stem, meta, spec, None, buffers)


def test_an_asset_of_a_source_over_several_folders_is_found_in_the_readme():
    """``examples/dataset_scale.toml``'s objects scan gltf, gltf_extra and gltf_more: each asset's row is found by
    its folder name or its file stem, only under the source's folders."""
    rows = [{"path": "gltf/Fox/glTF-Binary/Fox.glb", "licence": "CC0", "attribution": "a"},
            {"path": "gltf_more/DutchShip/dutch_ship_medium_1k.gltf", "licence": "CC0", "attribution": "b"},
            {"path": "other/Lamp/Lamp.glb", "licence": "x", "attribution": "c"}]
    folders = ["gltf", "gltf_more"]
    assert model_cards.asset_row("Fox", folders, rows)["attribution"] == "a"
    assert model_cards.asset_row("dutch_ship_medium_1k", folders, rows)["attribution"] == "b"
    assert model_cards.asset_row("Lamp", folders, rows) is None and model_cards.asset_row("glTF-Binary", folders,
                                                                                         rows) is None
