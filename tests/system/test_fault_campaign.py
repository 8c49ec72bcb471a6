"""The fault campaign's fast subset (benchmarks/fault_campaign.py; the whole campaign, numbers: docs/results.md).

The families whose cost is the point (a kill -9 or Ctrl-C at a moment, a disk filled mid-render, every importer in
the sandbox, appends racing in subprocesses) are marked ``heavy``: ``make test-heavy`` (and CI) runs them. Each keeps
a cheap representative in ``make test``, named in its docstring."""
import importlib.util
import random
import sys

import pytest
from tests.conftest import REPO, requires_bpy

spec = importlib.util.spec_from_file_location("fault_campaign", REPO / "benchmarks" / "fault_campaign.py")
fc = importlib.util.module_from_spec(spec)
sys.modules["fault_campaign"] = fc  # dataclasses look their module up
spec.loader.exec_module(fc)


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory):
    pytest.importorskip("torch")
    return fc.Fixtures(tmp_path_factory.mktemp("faults"))


def _clean(tally):
    assert tally.failures == [] and tally.bad() == 0, tally.failures


@pytest.mark.torch
def test_bad_and_random_inputs_give_one_line_and_no_traceback(fixtures):
    pytest.importorskip("hypothesis")
    tally = fc.Tally()
    fc.bad_inputs(fixtures, tally, quick=True, log=lambda m: None)
    assert tally.inputs_tried == sum(c.quick for c in fc.BAD_INPUTS) >= 10
    fc.random_inputs(fixtures, tally, examples=6, log=lambda m: None)
    assert tally.inputs_tried >= 10 + 3 * 6
    _clean(tally)
    assert len(fc.BAD_INPUTS) >= 50


@pytest.mark.heavy
@pytest.mark.torch
def test_training_killed_and_resumed_gives_bit_identical_weights(fixtures):
    """Part 3 for training (heavy: a reference run, then kill -9 and resume). In make test:
    tests/train/test_train.py::test_resume_is_bit_identical (a resumed run's weights are bit-identical) and
    tests/train/test_reliability_train_inputs.py::test_killed_trainer_takes_its_loader_workers_and_frees_the_lock_*
    (a trainer killed with kill -9)."""
    tally = fc.Tally()
    fc.train_kills(fixtures, tally, kills=1, rng=random.Random(1), steps=6, log=lambda m: None)
    assert tally.faults == 1 and tally.results_compared == 1
    _clean(tally)


@pytest.mark.heavy
@requires_bpy
@pytest.mark.bpy
def test_render_killed_and_resumed_validates_with_every_frame(tmp_path):
    """Part 3 for render (heavy: a reference render, then kill -9 and resume). In make test:
    tests/dataset/test_dataset.py::test_dataset_resumes_after_kill_9 (a killed dataset resumes to valid clips with
    the uninterrupted run's geometry)."""
    tally = fc.Tally()
    fc.render_kills(tmp_path, tally, kills=1, rng=random.Random(2), frames=2, log=lambda m: None)
    assert tally.faults == 1 and tally.results_compared == 1
    _clean(tally)


def test_issue26_families_concurrent_writers_and_traversal(fixtures, capsys):
    """Fast forms of parts 5 and 6: in-process writers, index paths and links."""
    tally = fc.Tally()
    fc.concurrent_writers(fixtures, tally, races=0, log=lambda m: None)
    fc.traversal_inputs(fixtures, tally, quick=True, log=lambda m: None)
    with capsys.disabled():
        print(f"\ncampaign (concurrent writers, traversal and symlinks): {tally.inputs_tried} "
              f"cases, {tally.tracebacks} tracebacks, {tally.wrong_exit} wrong exits, {tally.escapes} escapes")
    assert tally.inputs_tried >= 6 + 12 + 5
    _clean(tally)


@pytest.mark.heavy
def test_issue26_family_full_filesystem(fixtures):
    """Part 8 (heavy: training, a render and a dataset on a tmpfs filled under them). In make test:
    tests/train/test_reliability_training.py (a simulated ENOSPC and a real 1 MB tmpfs under the training cache),
    tests/train/test_checkpoint_full_disk.py, tests/core/test_export_full_disk.py and
    tests/cli/test_reliability_errors.py::test_a_full_disk_under_cycles_is_not_blamed_on_the_exr."""
    tally = fc.Tally()
    fc.full_filesystem(fixtures, tally, log=lambda m: None)
    assert tally.inputs_tried >= 1
    _clean(tally)


@pytest.mark.heavy
@requires_bpy
@pytest.mark.bpy
def test_issue26_family_signals_during_render(tmp_path):
    """Fast form of part 7: one SIGINT during a render, then the rerun finishes a valid clip (heavy: Ctrl-C timing).
    In make test: tests/render/test_reliability_render.py::test_ctrl_c_stops_a_render_keeping_finished_frames and
    tests/dataset/test_dataset_interrupt.py (Ctrl-C to a dataset's coordinator)."""
    tally = fc.Tally()
    fc.signal_render(tmp_path, tally, signals=1, rng=random.Random(3), frames=3, log=lambda m: None)
    assert tally.faults == 1


@pytest.mark.torch
def test_huge_specs_and_non_finite_values_are_refused_or_warned_at_once(fixtures):
    """Issue 26: the families 'huge specs' and 'non-finite values through evaluate and upscale' (quick subset)."""
    tally = fc.Tally()
    lines = []
    fc.huge_and_nonfinite(fixtures, tally, quick=True, log=lines.append)
    assert tally.inputs_tried == sum(c[3] for c in fc.HUGE_AND_NONFINITE) >= 8
    print("\n".join(lines))
    _clean(tally)


@requires_bpy
@pytest.mark.bpy
def test_issue56_scene_references_outside_the_folder_are_refused_by_render(tmp_path):
    """Part 11's cheap representative, through ``blendsr render``: a glTF buffer URI leaving the folder and a folder
    named s.glb are refused in one line naming the file and the reference (every reference rule:
    tests/core/test_scene_refs.py; every case and Ctrl-C during an import: the heavy test below)."""
    tally = fc.Tally()
    lines = []
    names = ("glTF buffer URI ../../../../etc/passwd", "a folder named s.glb")
    fc.sandbox_imports(tmp_path, tally, quick=True, log=lines.append, names=names, sigint=False)
    print("\n".join(lines))
    assert tally.inputs_tried == 2
    _clean(tally)


@pytest.mark.heavy
@requires_bpy
@pytest.mark.bpy
def test_issue56_family_scene_files_in_a_sandbox(tmp_path):
    """Fast form of part 11: references outside the folder refused naming file and reference, the 10^9 accessor and
    the folder named s.glb named, an FBX with a lamp imports, Ctrl-C during an import exits 130 with no clip (heavy:
    a render per case; the representative in make test is the test above)."""
    tally = fc.Tally()
    lines = []
    fc.sandbox_imports(tmp_path, tally, quick=True, log=lines.append)
    print("\n".join(lines))
    assert tally.inputs_tried == sum(c[3] for c in fc.SANDBOX_CASES) + 1 >= 8
    assert tally.faults == tally.faults_survived == 1
    _clean(tally)


@pytest.mark.heavy
def test_exports_appends_at_once_consumer_limits_and_the_nss_round_trip(fixtures):
    """Part 12, quick form (NSS and RDG races; NFRU's 1920x1080 race in the full campaign). Heavy: a subprocess per
    export; in make test: tests/core/test_export_append_race.py (the race for every format),
    tests/core/test_export_rules.py (the NFRU refusals) and
    tests/core/test_formats.py::test_the_nss_round_trip_validates."""
    tally = fc.Tally()
    fc.export_cases(fixtures, tally, quick=True, log=lambda m: None)
    assert tally.inputs_tried == 5
    _clean(tally)


@pytest.mark.torch
def test_issue56_frames_with_nothing_and_untrusted_clips_are_refused(fixtures):
    """Issue 56: the quick subset of part ``empty`` (a truncated OBJ refused before rendering; train and evaluate
    refusing a clip whose exposure was edited or whose radiance was scaled, naming the check; the cache rebuilt
    after an EXR changed under kept file times, a linked EXR refused)."""
    pytest.importorskip("bpy")
    tally = fc.Tally()
    lines = []
    fc.empty_and_untrusted(fixtures, tally, quick=True, log=lines.append)
    assert tally.inputs_tried == sum(c[3] for c in fc.EMPTY_AND_UNTRUSTED) + 2 >= 7
    print("\n".join(lines))
    _clean(tally)
