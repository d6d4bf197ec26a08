"""Fixtures of the dataset-reader tests; the writers live in dataset_fixtures.py and
bag_fixtures.py next to this file."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

# The helper modules are imported by bare name; make that work under any pytest import mode.
sys.path.insert(0, str(Path(__file__).parent))

from dataset_fixtures import Scene, make_scene  # noqa: E402


@pytest.fixture(scope="session")
def scene() -> Scene:
    return make_scene()
