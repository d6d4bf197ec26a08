"""Fixtures of the segmenter tests."""

from __future__ import annotations

import pytest
from seg_room import render_room

from shared.perception import KeyframeImage


@pytest.fixture(scope="session")
def room() -> KeyframeImage:
    """Shared by every test: treat it as read-only."""
    return render_room()
