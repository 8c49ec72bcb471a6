"""tests/system: the whole project: architecture rules, the wheel, the demo, the fault campaign. Every test here is marked `system`."""
from pathlib import Path

import pytest

from tests.conftest import mark_folder


def pytest_collection_modifyitems(items):
    mark_folder(items, Path(__file__).parent, pytest.mark.system)
