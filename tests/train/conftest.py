"""tests/train: the torch layer: data, models, trainer, evaluation (every test here needs torch). Every test here is marked `train` and `torch`."""
from pathlib import Path

import pytest

from tests.conftest import mark_folder


def pytest_collection_modifyitems(items):
    mark_folder(items, Path(__file__).parent, pytest.mark.train, pytest.mark.torch)


@pytest.fixture(scope="module", autouse=True)
def _one_thread_by_default():
    """A run's default thread count (``run.threads = 0``, the commands' ``--threads 0``: ``resources.usable_cores``
    through ``training.device.set_threads``) is 1 in these tests: the suite runs one test per core (``make test``:
    2 workers on 2 cores), and torch's threads wait for each other when another process holds a core (a fine-tune
    ran 8x slower with 2 threads beside two busy processes: ``resources.idle_cores``). It also keeps one test's
    2 threads from staying set for the tests after it in the same worker. A test that gives a count keeps it.
    Module-scoped (and autouse, so set up first in its scope), it holds for the module-scoped fixtures that train
    or evaluate too; it ends with the module, so tests of other folders see the real ``usable_cores``."""
    from gbuffer_export import resources
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(resources, "usable_cores", lambda root=None: 1)
        yield
