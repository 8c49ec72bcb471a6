"""tests/dataset: dataset specs, planning and building. Every test here is marked `dataset`."""
from pathlib import Path

import pytest

from tests.conftest import mark_folder


def pytest_collection_modifyitems(items):
    mark_folder(items, Path(__file__).parent, pytest.mark.dataset)
