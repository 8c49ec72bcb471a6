"""tests/core: the numpy core (gbuffer_export without bpy or torch). Every test here is marked `core`."""
from pathlib import Path

import pytest

from tests.conftest import mark_folder


def pytest_collection_modifyitems(items):
    mark_folder(items, Path(__file__).parent, pytest.mark.core)
