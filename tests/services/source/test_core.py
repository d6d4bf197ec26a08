"""Replay scheduling of the source, with a fake clock (no Zenoh, no sleeping)."""

from __future__ import annotations

import numpy as np

from services.source.core import planned_indices, replay
from shared.config import SourceConfig
from shared.datasets.base import SequenceReader
from shared.geometry import Intrinsics
from shared.messages import Frame


class FakeReader(SequenceReader):
    def __init__(self, n: int) -> None:
        self.n = n
        self.intrinsics = Intrinsics(fx=10, fy=10, cx=1.5, cy=1.5, width=4, height=4)
        self.depth_scale = 1000.0
        self.loaded: list[int] = []

    def __len__(self) -> int:
        return self.n

    def pose(self, i: int) -> np.ndarray:
        T = np.eye(4)
        T[0, 3] = i
        return T

    def frame(self, i: int) -> Frame:
        self.loaded.append(i)
        return Frame(
            frame_index=i,
            rgb=np.zeros((4, 4, 3), np.uint8),
            depth=np.ones((4, 4), np.uint16),
            depth_scale=self.depth_scale,
            intrinsics=self.intrinsics,
            T_world_cam=self.pose(i),
        )


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        assert dt >= 0
        self.t += dt


def test_planned_indices():
    assert planned_indices(10, 1) == list(range(10))
    assert planned_indices(10, 3) == [0, 3, 6, 9]
    assert planned_indices(10, 3, max_frames=2) == [0, 3]
    assert planned_indices(0, 2) == []


def test_lossless_sends_everything_in_order():
    reader = FakeReader(12)
    sent = []
    stats = replay(reader, SourceConfig(mode="lossless", stride=2), lambda f: sent.append(f.frame_index))
    assert sent == [0, 2, 4, 6, 8, 10]
    assert stats.published == 6 and stats.dropped == 0 and stats.last_frame_index == 10


def test_live_paces_at_rate_when_consumer_keeps_up():
    clock = FakeClock()
    sent_at = []
    reader = FakeReader(10)
    stats = replay(
        reader, SourceConfig(mode="live", rate_hz=10.0), lambda f: sent_at.append(clock.t),
        clock=clock, sleep=clock.sleep,
    )  # fmt: skip
    assert stats.published == 10 and stats.dropped == 0
    np.testing.assert_allclose(sent_at, np.arange(10) * 0.1, atol=1e-9)


def test_live_drops_and_counts_when_publish_blocks():
    clock = FakeClock()
    reader = FakeReader(20)

    def slow_publish(frame: Frame) -> None:
        # A lagging subscriber makes each put block for 2.5 frame periods.
        clock.t += 0.25

    stats = replay(reader, SourceConfig(mode="live", rate_hz=10.0), slow_publish, clock=clock, sleep=clock.sleep)
    assert stats.published + stats.dropped == 20
    assert stats.dropped > 0 and stats.published < 20
    assert sorted(set(reader.loaded) | set(stats.dropped_indices)) == list(range(20))
    assert not set(reader.loaded) & set(stats.dropped_indices), "dropped frames are never loaded"
    # Roughly one frame in 2.5 gets through.
    assert 6 <= stats.published <= 10


def test_stop_request_ends_replay():
    reader = FakeReader(100)
    sent = []
    replay(reader, SourceConfig(), lambda f: sent.append(f.frame_index), should_stop=lambda: len(sent) >= 5)
    assert sent == [0, 1, 2, 3, 4]
