"""tests/cli: the command line: help, errors, extras, interrupts. Every test here is marked `cli`."""
from pathlib import Path

import pytest

from tests.conftest import mark_folder


def pytest_collection_modifyitems(items):
    mark_folder(items, Path(__file__).parent, pytest.mark.cli)
