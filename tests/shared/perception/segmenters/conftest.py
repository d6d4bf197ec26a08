"""Fixtures of the segmenter tests."""

from __future__ import annotations

import pytest
from seg_room import RoomImage, render_room


@pytest.fixture(scope="session")
def room() -> RoomImage:
    """Shared by every test: treat it as read-only."""
    return render_room()
