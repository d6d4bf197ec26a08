"""SessionNode: a session ticked on a thread of its own; a failed tick is counted and retried;
close keeps the bus when asked; a session that cannot be made closes the bus."""

from __future__ import annotations

import threading

import pytest

from shared.runtime.adapter import SessionNode
from shared.runtime.status import StatusBook


class FakeBus:
    def __init__(self) -> None:
        self.closed = False

    def close(self) -> None:
        self.closed = True


class FakeSession:
    def __init__(self, bus) -> None:
        self.bus, self.book = bus, StatusBook("query")
        self.ticks: list[float] = []
        self.closed = False
        self.ticked = threading.Event()

    def tick(self, now: float) -> None:
        self.ticks.append(now)
        if len(self.ticks) == 2:
            raise RuntimeError("one bad tick")
        if len(self.ticks) >= 3:
            self.ticked.set()

    def close(self) -> None:
        self.closed = True


def test_ticks_until_closed_and_counts_a_failed_tick():
    bus = FakeBus()
    node = SessionNode(bus, FakeSession, name="query", tick_s=0.01, stop_timeout_s=5)
    assert node.session.ticked.wait(5)
    node.close(keep_bus=True)
    n = len(node.session.ticks)
    assert node.session.closed and not bus.closed and node.book.report().errors == 1
    assert node.session.ticks == sorted(node.session.ticks)
    node.close()  # once closed, again does nothing
    assert len(node.session.ticks) == n and not bus.closed


def test_a_session_that_cannot_be_made_closes_the_bus():
    bus = FakeBus()

    def broken(b):
        raise ValueError("frame_every must be at least 1")

    with pytest.raises(ValueError, match="frame_every"):
        SessionNode(bus, broken, name="viewer", tick_s=0.01, stop_timeout_s=5)
    assert bus.closed
