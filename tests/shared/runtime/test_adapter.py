"""SessionNode: a session ticked on a thread of its own; a failed tick is counted and retried;
close keeps the bus when asked; a session that cannot be made closes the bus; the inbox works
only once the session is made; the token, state and close order of a service node."""

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


class Token:
    def __init__(self, key: str, log: list[str]) -> None:
        self.key, self.log = key, log

    def undeclare(self) -> None:
        self.log.append(f"undeclare {self.key}")


class AliveBus(FakeBus):
    robot_id = "robot0"

    def __init__(self, log: list[str]) -> None:
        super().__init__()
        self.log = log

    def declare_alive(self, key: str) -> Token:
        self.log.append(f"declare {key}")
        return Token(key, self.log)

    def close(self) -> None:
        self.log.append("bus")
        super().close()


class Owned:
    def __init__(self, name: str, log: list[str]) -> None:
        self.name, self.log = name, log

    def close(self) -> None:
        self.log.append(self.name)


class InboxSession(FakeSession):
    """Made with the node's inbox; records what it was handed through it and how it closed."""

    def __init__(self, bus, inbox, log: list[str]) -> None:
        super().__init__(bus)
        self.log = log
        self.handled: list[str] = []
        inbox.put("frames", lambda: self.handled.append("early"))  # queued before the node holds the session

    def close(self, **how) -> None:
        self.log.append(f"session {how}")
        super().close()


def test_inbox_token_state_and_close_order():
    log: list[str] = []
    bus = AliveBus(log)
    node = None

    def make(b):
        node.own(Owned("wire", log))
        node.own(Owned("watcher", log))
        return InboxSession(b, node.inbox, log)

    node = SessionNode(bus, make, name="tracker", inbox=4, alive="tracker", start=False)
    assert node.session is None and node.token is None
    node.start()
    session = node.session
    node.start()  # `trackgraph serve` starts every node: once is all
    assert node.session is session
    for _ in range(100):
        if node.session.handled:
            break
        threading.Event().wait(0.05)
    assert node.session.handled == ["early"]  # the worker ran it once the session existed
    assert log == ["declare trackgraph/robot0/alive/tracker"] and node.book.state == "running" and node.errors == 0
    node.close(keep_bus=False, save=False)
    assert log[1:] == ["session {'save': False}", "undeclare trackgraph/robot0/alive/tracker", "watcher", "wire", "bus"]


def test_running_is_the_nodes_to_say_when_asked():
    bus = AliveBus([])
    node = SessionNode(bus, FakeSession, name="source", alive="source", running=False)
    assert node.token is not None and node.book.state == "starting"
    node.close()
    assert bus.closed
