"""Fixtures of the service tests: tiny valid frames, and a fake clock for the sessions."""

from __future__ import annotations

import numpy as np
import pytest

from shared.geometry import Intrinsics
from shared.messages.frames import Frame


def tiny_frame(i: int, h: int = 4, w: int = 4) -> Frame:
    """A valid RGB-D frame ``i``, ``w`` x ``h`` pixels, the camera 0.1 m further along x each frame."""
    pose = np.eye(4)
    pose[0, 3] = 0.1 * i
    return Frame(
        frame_index=i, time_s=i / 30.0, rgb=np.full((h, w, 3), i % 256, np.uint8), depth=np.full((h, w), 1000, np.uint16),
        depth_scale=1000.0, intrinsics=Intrinsics(fx=10, fy=10, cx=(w - 1) / 2, cy=(h - 1) / 2, width=w, height=h), T_world_cam=pose,
    )  # fmt: skip


class FakeClock:
    """Seconds that pass only when a test says so."""

    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> float:
        self.t += dt
        return self.t


@pytest.fixture
def make_frame():
    return tiny_frame


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()
