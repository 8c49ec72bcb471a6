"""Bit-identical behaviour: a fixed seed trained for a few steps gives the parameter digest measured before the
trainer was restructured (issue 29), for a feed-forward and a recurrent model."""
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training.config import load_config  # noqa: E402
from training.train import train  # noqa: E402

pytestmark = pytest.mark.torch

SMALL = ["data.crop=8", "data.batch_size=2", "model.width=16", "model.blocks=1", "run.progress=false",
         "run.log_every=1", "run.amp=\"none\"", "run.threads=0", "data.prefetch=1", "run.max_steps=3",
         "optim.decay_steps=3", "run.checkpoint_every=2", "run.seed=7"]
#: Measured on the trainer before the restructuring (8976331 + locks, CPU, torch's float32 kernels).
EXPECTED = {
    "fusesr": "c4f4fbfce3229fbc",
    "rdg-s": "dd34e8a7a4393172",
}
EXTRA = {
    "fusesr": ["loss.temporal_weight=0.5", "optim.ema_decay=0.5", "loss.fft_weight=0.1"],
    "rdg-s": ["data.window=3", "data.detach_every=2"],
}


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 6), hr_size=(64, 36), scale=4)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_fixed_seed_training_gives_the_recorded_parameter_digest(clip, tmp_path, name):
    over = [o for o in SMALL if not (name == "rdg-s" and o.startswith(("model.width", "model.blocks")))]
    cfg = load_config(None, over + EXTRA[name] + [f'model.name="{name}"'])
    cfg.data.clips = [str(clip)]
    summary = train(cfg, tmp_path / "run")
    assert summary["step"] == 3
    assert summary["param_digest"] == EXPECTED[name]
