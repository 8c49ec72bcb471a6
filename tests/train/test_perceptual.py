"""The perceptual loss's VGG-16 weights: torchvision's vgg16-397923af.pth, which the user downloads; a missing or
different file is refused in one line naming loss.vgg_weights and what to download, and nothing is downloaded."""
import hashlib
import re

import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.config import ConfigError  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training import perceptual  # noqa: E402
from training.config import load_config  # noqa: E402
from tests.conftest import set_args  # noqa: E402

SMALL = ["data.crop=8", "data.batch_size=2", "model.width=16", "model.blocks=1", "run.progress=false",
         'run.amp="none"', "run.threads=0", "run.max_steps=1", "loss.perceptual_weight=0.5"]


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 4), hr_size=(64, 36), scale=4)


def test_the_named_file_is_torchvisions_vgg16():
    """The file name carries the first 8 hex digits of its sha256 (torch.hub's convention), the URL names it."""
    assert perceptual.VGG16_URL == "https://download.pytorch.org/models/vgg16-397923af.pth"
    assert re.fullmatch(r"[0-9a-f]{64}", perceptual.VGG16_SHA256)
    assert perceptual.VGG16_FILE.split("-")[1].split(".")[0] == perceptual.VGG16_SHA256[:8]
    hint = perceptual.download_hint()
    assert perceptual.VGG16_URL in hint and perceptual.VGG16_SHA256 in hint and "loss.vgg_weights" in hint


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


@pytest.mark.parametrize("case", ["unset", "missing", "other file"])
def test_missing_or_wrong_vgg_weights_name_the_key_and_the_download(case, clip, tmp_path, capsys, monkeypatch):
    calls = []
    monkeypatch.setattr("urllib.request.urlopen", lambda *a, **k: calls.append(a))  # nothing is downloaded
    monkeypatch.setattr("torch.hub.load_state_dict_from_url", lambda *a, **k: calls.append(a))
    over = list(SMALL)
    if case == "missing":
        over.append(f'loss.vgg_weights="{tmp_path / "vgg16-397923af.pth"}"')
    elif case == "other file":
        other = tmp_path / "vgg16.pth"
        torch.save({"features.0.weight": torch.zeros(64, 3, 3, 3)}, other)
        over.append(f'loss.vgg_weights="{other}"')
    run = tmp_path / "run"
    assert main(["train", "--model", "fusesr-l", "--data", str(clip), "-o", str(run), *set_args(over)]) == 2
    line = _one_line(capsys)
    assert "loss.vgg_weights" in line and perceptual.VGG16_URL in line and perceptual.VGG16_SHA256 in line, line
    if case == "other file":
        assert "is not that of vgg16-397923af.pth" in line and str(other) in line
        sha = hashlib.sha256(other.read_bytes()).hexdigest()
        assert sha[:16] in line
    assert not calls
    assert not (run / "checkpoints" / "last.pt").exists()


def test_the_configuration_refuses_a_missing_file_before_training(tmp_path):
    with pytest.raises(ConfigError, match=r"loss.vgg_weights .*nope.pth: file not found; download https://"):
        load_config(None, ["loss.perceptual_weight=0.5", f'loss.vgg_weights="{tmp_path / "nope.pth"}"'])


def test_a_file_with_the_right_hash_loads(tmp_path, monkeypatch):
    from training.perceptual import VGGFeatures, vgg16_features
    f = tmp_path / "vgg16-397923af.pth"
    torch.save({f"features.{k}": v for k, v in vgg16_features().state_dict().items()}, f)
    with pytest.raises(ConfigError, match="is not that of vgg16-397923af.pth"):
        VGGFeatures.from_file(f)
    monkeypatch.setattr(perceptual, "VGG16_SHA256", hashlib.sha256(f.read_bytes()).hexdigest())
    assert perceptual.require_vgg_file(f) == f
    assert len(VGGFeatures.from_file(f).features) == perceptual.TAPS[-1] + 1
