"""Fixtures of the evaluation tests; the hand-built scene lives in eval_fixtures.py."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

# The helper module is imported by bare name; make that work under any pytest import mode.
sys.path.insert(0, str(Path(__file__).parent))

from eval_fixtures import Scene, make_scene  # noqa: E402


@pytest.fixture
def scene() -> Scene:
    return make_scene()
