"""tests/train: the torch layer: data, models, trainer, evaluation (every test here needs torch). Every test here is marked `train` and `torch`."""
from pathlib import Path

import pytest

from tests.conftest import mark_folder


def pytest_collection_modifyitems(items):
    mark_folder(items, Path(__file__).parent, pytest.mark.train, pytest.mark.torch)

