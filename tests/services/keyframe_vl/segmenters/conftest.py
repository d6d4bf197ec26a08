"""Fixtures of the segmenter tests."""

from __future__ import annotations

import pytest
from seg_room import render_room

from services.keyframe_vl.types import KeyframeImage


@pytest.fixture(scope="session")
def room() -> KeyframeImage:
    """Shared by every test: treat it as read-only."""
    return render_room()
