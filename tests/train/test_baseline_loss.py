"""The ``baseline`` loss term (``loss.baseline_weight``): the hinge over the guided baseline ``demod-jbu``.

Closed forms of the hinge, and trainings: FuseSR-fast started at its residual base (demod-jbu's guided upsampling,
in log space) pays almost nothing at its first step, a random head much more; a recurrent model without HR G-buffers (RDG-s) reads
demod-jbu's inputs for the term and logs it per frame."""
import csv

import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)  # 2 threads on a shared 2-core machine can be 10x slower

from gbuffer_export.cli import main  # noqa: E402
from gbuffer_export.synthetic import make_synthetic_clip  # noqa: E402
from training.config import LossConfig  # noqa: E402
from training.losses import Criterion, baseline_loss  # noqa: E402
from tests.conftest import set_args  # noqa: E402

SMALL = ["data.crop=8", "data.batch_size=2", "run.progress=false", "run.log_every=1", "run.amp=\"none\"",
         "run.threads=0", "loss.ssim_weight=0.0"]


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_synthetic_clip(tmp_path_factory.mktemp("clip") / "c", frames=range(1, 6), hr_size=(64, 36), scale=4)


def test_hinge_closed_forms():
    g = torch.Generator().manual_seed(0)
    a, b, j = (torch.rand(2, 3, 5, 7, generator=g) for _ in range(3))
    # by hand, element by element
    want = sum(max(0.0, abs(x - y) - abs(z - y)) for x, y, z in zip(a.flatten().tolist(), b.flatten().tolist(),
                                                                       j.flatten().tolist())) / a.numel()
    assert float(baseline_loss(a, b, j)) == pytest.approx(want, rel=1e-6)
    assert float(baseline_loss(j, b, j)) == 0.0                         # the baseline itself pays nothing
    assert float(baseline_loss(a, b, b)) == pytest.approx(float((a - b).abs().mean()), rel=1e-6)  # exact base: L1
    assert float(baseline_loss(b, b, j)) == 0.0                         # the ground truth pays nothing
    # the criterion: the term in the loss space (log1p), weighted, skipped without a baseline SR
    crit = Criterion(LossConfig(pixel_weight=1.0, ssim_weight=0.0, baseline_weight=0.5))
    total, terms = crit(a, b, base=j)
    assert float(terms["baseline"]) == pytest.approx(float(baseline_loss(a.log1p(), b.log1p(), j.log1p())))
    assert float(total) == pytest.approx(float(terms["pixel"] + 0.5 * terms["baseline"]), rel=1e-6)
    assert "baseline" not in crit(a, b)[1]


def rows(run):
    return list(csv.DictReader(open(run / "log.csv")))


def test_a_network_at_its_guided_base_pays_almost_nothing(clip, tmp_path):
    def first_rows(name, *sets):
        run = tmp_path / name
        assert main(["train", "--model", "fusesr-fast", "--data", str(clip), "-o", str(run), "--max-steps", "2",
                     *set_args(SMALL + ["loss.baseline_weight=1.0", "model.width=8", "model.blocks=1", *sets])]) == 0
        log = rows(run)
        assert [int(r["step"]) for r in log] == [1, 2]
        for r in log:
            assert float(r["loss"]) == pytest.approx(float(r["pixel"]) + float(r["baseline"]), rel=1e-5)
        return log[0]
    # step 1 runs the initial weights on the same batch in both runs. Started at its residual base (the guided
    # upsampling of L_D in log1p space; demod-jbu's is in linear space, the only difference), the network is
    # almost never further from the ground truth than demod-jbu; a randomly initialised head is, often.
    at_base = first_rows("at_base", "model.fusesr-fast.zero_init_refine=true")
    random_head = first_rows("random_head")
    assert float(at_base["pixel"]) == pytest.approx(float(random_head["pixel"]), rel=0.5)
    assert float(at_base["baseline"]) < 0.01 * float(at_base["pixel"])
    assert float(random_head["baseline"]) > 10 * float(at_base["baseline"])


def test_a_model_without_hr_gbuffers_reads_the_baselines_inputs(clip, tmp_path):
    run = tmp_path / "rdg"
    assert main(["train", "--model", "rdg-s", "--data", str(clip), "-o", str(run), "--max-steps", "2",
                 *set_args(SMALL + ["loss.baseline_weight=2.0", "model.width=8", "data.window=3",
                                    "data.detach_every=2"])]) == 0
    for r in rows(run):
        assert float(r["baseline"]) > 0
        assert float(r["loss"]) == pytest.approx(float(r["pixel"]) + 2.0 * float(r["baseline"]), rel=1e-4)
