"""tests/render: the bpy layer: renders, scenes, level cameras. Every test here is marked `render` and `bpy`."""
from pathlib import Path

import pytest

from tests.conftest import mark_folder


def pytest_collection_modifyitems(items):
    mark_folder(items, Path(__file__).parent, pytest.mark.render, pytest.mark.bpy)
