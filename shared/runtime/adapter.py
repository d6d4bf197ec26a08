"""The one shell of every service node: what a node adds to its session.

A session is the service's coordination on a bus; in one process (``trackgraph map``) the
caller drives it itself over the in-process bus. A node runs it on Zenoh: the bus (which
delivers on its own threads), an optional inbox whose one worker hands the session its queued
inputs in arrival order, a thread driving the session's ``tick(now)``, the service's liveliness
token and state ``running``, and a close that undoes all of it in order. A node class only
wires: it builds its core and says how to make its session.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from shared.runtime.session import Inbox, Ticker
from shared.runtime.status import StatusBook
from shared.topics import Topics

log = logging.getLogger(__name__)


def open_bus(cfg: Any, session: Any = None) -> Any:
    """A node's Zenoh bus for ``cfg`` (a ``TrackGraphConfig``): a session of its own per
    ``cfg.transport``, or one wrapping ``session``, an open zenoh session to share (its owner
    closes it, not the bus)."""
    # Zenoh is the shell's: importing the runtime does not load it.
    from shared.transport import ZenohBus

    if session is None:
        return ZenohBus.open(cfg.transport, cfg.robot_id)
    return ZenohBus(session, cfg.robot_id, cfg.transport.codec)


def session_attr(name: str) -> property:
    """A read-only node attribute that is its session's ``name`` (what tests, benchmarks and
    ``trackgraph serve`` look at on a node)."""
    return property(lambda node: getattr(node.session, name), doc=f"The session's ``{name}``.")


class SessionNode:
    """A session on ``bus`` (``make_session(bus)``, which has ``book``, ``tick(now)`` and
    ``close()``), run as a service: what ``trackgraph serve`` needs of a node is ``book``,
    ``bus`` and ``close(keep_bus=False)``.

    - ``tick_s``: the session is ticked every ``tick_s`` seconds on a thread of its own (None:
      the node's caller drives it, as the source's replay loop does).
    - ``inbox``: the capacity of an :class:`Inbox` made before the session (``make_session``
      hands ``self.inbox`` to it) and started once the session is made; 0 for none.
    - ``alive``: the service whose liveliness token the node declares once the session is made
      (None: the session declares its own, when it is ready); with ``running`` the state goes
      ``running`` then too (False: the node says when).
    - ``book``: the status book to report from before the session exists (``start=False``:
      the node calls :meth:`start` itself, after its models loaded).

    If the session cannot be made, what was opened (the bus included) is closed and the error
    raised.
    """

    def __init__(
        self, bus: Any, make_session: Callable[[Any], Any], *, name: str, tick_s: float | None = None, stop_timeout_s: float = 30.0,
        inbox: int = 0, alive: str | None = None, running: bool = True, book: StatusBook | None = None, start: bool = True,
    ) -> None:  # fmt: skip
        self.bus = bus
        self.name = name
        self.book = book
        self.session: Any = None
        self.inbox: Inbox | None = None
        self.token: Any = None
        """The liveliness token the node declared (``alive``), until closed."""
        self._make_session = make_session
        self._tick_s, self._stop_timeout_s, self._inbox_capacity = tick_s, stop_timeout_s, inbox
        self._alive, self._running = alive, running
        self._ticker: Ticker | None = None
        self._owned: list[Any] = []
        self._closed = False
        if start:
            try:
                self.start()
            except BaseException:
                self.close()
                raise

    def own(self, resource: Any) -> Any:
        """Close ``resource`` (anything with ``close()``: a ROS 2 wire, a liveliness watcher)
        with the node, after the session and its token; the last owned is closed first."""
        self._owned.append(resource)
        return resource

    def start(self) -> None:
        """Make the session, then run it: the inbox's worker, the ticker, the liveliness token
        and state ``running``. Once started (``trackgraph serve`` calls it on every node),
        calling it again does nothing."""
        if self.session is not None:
            return
        if self._inbox_capacity:
            # started only once the session is made: its worker may hand it an input at once
            self.inbox = Inbox(self._inbox_capacity, name=f"{self.name}:worker", start=False)
        self.session = self._make_session(self.bus)
        self.book = self.session.book
        if self.inbox is not None:
            self.inbox.start()
        if self._tick_s is not None:
            self._ticker = Ticker(self.session.tick, self._tick_s, name=f"{self.name}:tick", on_error=self.book.error)
        if self._alive is not None:
            self.token = self.bus.declare_alive(Topics(self.bus.robot_id).alive(self._alive))
            if self._running:
                self.book.set_state("running")

    @property
    def errors(self) -> int:
        return self.book.errors

    def close(self, keep_bus: bool = False, **how: Any) -> None:
        """Stop ticking, stop the inbox after the item in hand, close the session (with
        ``how``: e.g. fusion's ``save``), undeclare the token, close what the node owns; with
        ``keep_bus`` the bus stays open (for the last status report; its owner closes it).
        Calling it again does nothing."""
        if self._closed:
            return
        self._closed = True
        if self._ticker is not None:
            self._ticker.stop(timeout=self._stop_timeout_s)  # a snapshot request may be in flight
        if self.inbox is not None:
            self.inbox.stop()
        if self.session is not None:
            self.session.close(**how)
        if self.token is not None:
            self.token.undeclare()
        for resource in reversed(self._owned):
            resource.close()
        if not keep_bus:
            self.bus.close()
