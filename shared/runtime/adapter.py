"""What a node adds to its session: a bus that delivers on its own threads (Zenoh), and a
thread of its own driving the session's ``tick(now)``. In one process the caller drives the
session itself, over the in-process bus."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from shared.runtime.session import Ticker

log = logging.getLogger(__name__)


class SessionNode:
    """A session on ``bus`` (``make_session(bus)``, which has ``book``, ``tick(now)`` and
    ``close()``), ticked every ``tick_s`` seconds. What ``trackgraph serve`` needs of a node:
    ``book``, ``bus``, ``close(keep_bus=False)``. If the session cannot be made, the bus is
    closed and the error raised."""

    def __init__(self, bus: Any, make_session: Callable[[Any], Any], *, name: str, tick_s: float, stop_timeout_s: float) -> None:
        self.bus = bus
        try:
            self.session = make_session(bus)
        except BaseException:
            bus.close()
            raise
        self.book = self.session.book
        self._stop_timeout_s = stop_timeout_s
        self._ticker = Ticker(self.session.tick, tick_s, name=f"{name}:tick", on_error=self.book.error)
        self._closed = False

    def close(self, keep_bus: bool = False) -> None:
        """Stop ticking and close the session; with ``keep_bus`` the bus stays open (for the
        last status report; its owner closes it). Calling it again does nothing."""
        if self._closed:
            return
        self._closed = True
        self._ticker.stop(timeout=self._stop_timeout_s)  # a snapshot request may be in flight
        self.session.close()
        if not keep_bus:
            self.bus.close()
