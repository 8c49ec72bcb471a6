"""Bit-identical training on this machine: a fixed seed trained twice gives the same parameter digest, and a run
interrupted at step 2 and resumed gives the digest of the straight run, for a feed-forward and a recurrent model.

The digests are compared with each other, never with a digest measured on another CPU: float kernels differ between
instruction sets (AVX2 and AVX-512 give different last bits), so a pinned value fails on other machines."""
import pytest

torch = pytest.importorskip("torch")

from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training.config import load_config  # noqa: E402
from training.train import train  # noqa: E402


SMALL = ["data.crop=8", "data.batch_size=2", "model.width=16", "model.blocks=1", "run.progress=false",
         "run.log_every=1", "run.amp=\"none\"", "run.threads=1", "data.prefetch=1", "run.max_steps=3",
         "optim.decay_steps=3", "run.checkpoint_every=1", "run.seed=7"]
EXTRA = {
    "fusesr": ["loss.temporal_weight=0.5", "optim.ema_decay=0.5", "loss.fft_weight=0.1"],
    "rdg-s": ["data.window=3", "data.detach_every=2"],
}


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 6), hr_size=(64, 36), scale=4)


def _config(name, clip):
    over = [o for o in SMALL if not (name == "rdg-s" and o.startswith(("model.width", "model.blocks")))]
    cfg = load_config(None, over + EXTRA[name] + [f'model.name="{name}"'])
    cfg.data.clips = [str(clip)]
    return cfg


@pytest.mark.parametrize("name", sorted(EXTRA))
def test_fixed_seed_training_is_bit_identical_twice_and_after_a_resume(clip, tmp_path, name):
    first = train(_config(name, clip), tmp_path / "a")
    second = train(_config(name, clip), tmp_path / "b")
    assert first["step"] == second["step"] == 3
    assert len(first["param_digest"]) == 16
    assert first["param_digest"] == second["param_digest"]
    half = train(_config(name, clip), tmp_path / "c", stop_at=2)
    assert half["step"] == 2 and half["param_digest"] != first["param_digest"]
    resumed = train(None, tmp_path / "c", resume=True)
    assert resumed["step"] == 3
    assert resumed["param_digest"] == first["param_digest"]
